"""Stored tensors into a built model, every key checked: the one loading step of every path.

:meth:`CRFDepth.from_pretrained <crfdepth.model.CRFDepth.from_pretrained>` and
:func:`crfdepth.checkpoints.load_model` both end here, so a shipped set, a weights file and a
checkpoint get the same checks. This module works on any ``nn.Module`` and does not import the
model (docs/design.md section 8).
"""

from __future__ import annotations

from pathlib import Path

import torch

from crfdepth.errors import InputError
from crfdepth.weights.torch_files import some_keys

__all__ = ["load_state"]


def load_state(file: Path | None, model: torch.nn.Module, state: dict[str, torch.Tensor]) -> torch.nn.Module:
    """``model`` with ``state`` loaded, in the dtype of its floating tensors when they share one.

    A JSON weights file stores the learned head's tensors only (its scalars are in the
    configuration); a file saved before the predictive std has no ``std_head.weights`` and keeps
    the configured ones. Anything else must match the model key for key and shape for shape.

    Raises:
        InputError: missing, unexpected or misshapen keys, naming ``file``.
    """
    expected = model.state_dict()
    partial = all(k.startswith("head.") for k in state)
    if partial:
        expected = {k: v for k, v in expected.items() if k.startswith("head.")}
    elif "std_head.weights" not in state:
        expected.pop("std_head.weights", None)
        partial = True
    if getattr(model, "std_head", None) is None:  # uncertainty="posterior": a stored predictive std is not used
        state = {k: v for k, v in state.items() if not k.startswith("std_head.")}
    _check_keys(file, state, expected)
    model.load_state_dict(state, strict=not partial)
    dtypes = {v.dtype for v in state.values() if v.is_floating_point()}
    if len(dtypes) == 1:
        model = model.to(dtypes.pop())
    return model


def _check_keys(file: Path | None, state: dict[str, torch.Tensor], expected: dict[str, torch.Tensor]) -> None:
    missing = sorted(set(expected) - set(state))
    unexpected = sorted(set(state) - set(expected))
    wrong = sorted(k for k in set(expected) & set(state) if state[k].shape != expected[k].shape)
    if missing or unexpected or wrong:
        details = "; ".join(
            f"{label} ({len(keys)}): {some_keys(keys)}"
            for label, keys in (("missing keys", missing), ("unexpected keys", unexpected),
                                ("wrong shapes", [f"{k} {tuple(state[k].shape)} instead of "
                                                  f"{tuple(expected[k].shape)}" for k in wrong]))
            if keys)
        raise InputError(f"{file} does not match CRFDepth, a checkpoint of another model or "
                         f"configuration ({details})")

