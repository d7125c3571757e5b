"""Torch checkpoint files: crfdepth's model file written, and any torch file opened safely.

- :func:`write_model_file`: crfdepth's own model file ``{"format", "version", "config",
  "state_dict"}`` (:data:`MODEL_FORMAT`, :data:`MODEL_VERSION`).
- :func:`load_torch_file` and :func:`unpack_torch_file`: a torch file read with
  ``torch.load(weights_only=True)`` (so loading one never runs code) and taken apart into
  configuration, state dict and kind: a crfdepth model file or the trainer's Lightning
  checkpoint. A bare ``state_dict()`` is refused (:data:`BARE_STATE_DICT`): it does not say
  which structure its weights belong to.

:func:`crfdepth.weights.files.read_checkpoint` reads every kind of checkpoint through these
and brings old layouts up to date (docs/design.md section 8). Nothing here builds a model.
"""

from __future__ import annotations

import os
import warnings
from pathlib import Path
from typing import Any, Mapping

import torch

from crfdepth.config import plain_data
from crfdepth.errors import InputError
from crfdepth.io.files import atomic_write, check_output_file

__all__ = ["BARE_STATE_DICT", "MODEL_FORMAT", "MODEL_VERSION", "check_device", "is_config", "load_torch_file",
           "some_keys", "unpack_torch_file", "write_model_file"]

MODEL_FORMAT = "crfdepth"
"""Value of the ``"format"`` key of a crfdepth model file (:func:`crfdepth.save_model`)."""
MODEL_VERSION = 1
"""Version of the model-file layout that this module reads and writes."""

BARE_STATE_DICT = (
    "path: {file}: expected a complete model file, got a bare state dict: it holds weights but not the "
    "model's structure (mode, variable, gate ...); load it into the model it came from and save that with "
    "crfdepth.save_model(model, path), or give the trainer's Lightning .ckpt as it is")
"""The refusal of a bare ``state_dict()`` (no configuration): run in another structure (the default
one), the weights would give wrong depth without any error."""

_LIGHTNING_PREFIX = "model."  # the trainer's LightningModule stores the CRF as ``self.model``


# --------------------------------------------------------------------------- writing


def write_model_file(path: str | os.PathLike, config: Mapping[str, Any], state: Mapping[str, torch.Tensor],
                     regimes: Mapping[str, tuple[Mapping[str, Any], Mapping[str, torch.Tensor]]] | None = None) -> Path:
    """Write a crfdepth model file ``{"format", "version", "config", "state_dict"}``, atomically; ``regimes``
    (name -> ``(config, state)``, :mod:`crfdepth.weights.regimes`): the same pair of each under ``"regimes"``.

    Tuples of ``config`` are stored as lists and tensors are moved to the CPU (their dtype
    is kept), so the file loads with ``torch.load(weights_only=True)``. The file is
    written beside ``path`` and renamed over it: a failed write leaves no file behind.

    Raises:
        InputError: ``path`` is a folder.
        FileNotFoundError: the folder of ``path`` does not exist.
    """
    file = check_output_file(path)
    payload = {"format": MODEL_FORMAT, "version": MODEL_VERSION, **_entry(config, state)}
    if regimes:
        payload["regimes"] = {name: _entry(*pair) for name, pair in regimes.items()}
    atomic_write(file, lambda temporary: torch.save(payload, temporary))
    return file


def _entry(config: Mapping[str, Any], state: Mapping[str, torch.Tensor]) -> dict[str, Any]:
    return {"config": plain_data(dict(config)), "state_dict": {k: v.detach().cpu().clone() for k, v in state.items()}}


# --------------------------------------------------------------------------- reading


def check_device(map_location: str | torch.device) -> torch.device:
    """``map_location`` as a ``torch.device``; refused when unknown, or CUDA without CUDA."""
    try:
        device = torch.device(map_location)
    except (RuntimeError, TypeError):
        raise InputError(f"map_location: expected a device such as 'cpu' or 'cuda', got {map_location!r}") from None
    if device.type == "cuda" and not torch.cuda.is_available():
        raise InputError(f"map_location: CUDA is not available on this machine/PyTorch installation, "
                         f"got {map_location!r}; use 'cpu'")
    return device


def load_torch_file(file: Path, map_location: torch.device) -> Any:
    """``torch.load(file, weights_only=True)``; a file it refuses is one InputError saying why."""
    try:
        with warnings.catch_warnings():  # e.g. "pickle protocol 4": the error below says it all
            warnings.simplefilter("ignore", UserWarning)
            return torch.load(file, weights_only=True, map_location=map_location)
    except Exception as exc:  # unpickling errors come in many types; all mean "not a checkpoint"
        with open(file, "rb") as handle:
            head = handle.read(8)
        if head.startswith((b"PK\x03\x04", b"\x80")):  # zip archive / pickle >= 2
            reason = f"torch.load with weights_only=True refused it: {_reason(exc)}"
        else:
            reason = f"neither a torch.save archive nor a pickle; it starts with {head!r}"
        raise InputError(f"{file} is not a torch state dict, crfdepth model file or Lightning checkpoint "
                         f"({reason})") from None


def _reason(exc: Exception) -> str:
    """The useful part of a ``torch.load`` error, on one line.

    The weights-only unpickler's message is mostly advice to retry with
    ``weights_only=False`` (which would run the file's code); only its
    ``WeightsUnpickler error:`` part says what was found (e.g. ``Unsupported global:
    GLOBAL posix.system``).
    """
    text = str(exc)
    if "Weights only load failed" in text:
        body = text.split("Check the documentation", 1)[0]
        if "WeightsUnpickler error:" in body:
            body = body.split("WeightsUnpickler error:", 1)[1]
        else:  # drop the first paragraph (the advice)
            body = body.split("\n", 1)[1] if "\n" in body else ""
        body = " ".join(body.split()).split(" Please use", 1)[0]
        return body[:200] or "the file holds objects other than tensors and plain containers"
    words = " ".join(text.split())
    return f"{type(exc).__name__}: {words}"[:200] if words else type(exc).__name__


def unpack_torch_file(file: Path, loaded: Any) -> tuple[dict[str, Any], dict[str, torch.Tensor], str]:
    """(configuration, state dict, kind of file) of a loaded torch file."""
    if isinstance(loaded, dict) and loaded.get("format") == MODEL_FORMAT:
        kind = "crfdepth model file"
        if loaded.get("version") != MODEL_VERSION:
            raise InputError(f"{file}: {kind} version {loaded.get('version')!r} is not supported "
                             f"(this crfdepth reads version {MODEL_VERSION})")
        config = loaded.get("config")
        if not is_config(config):
            raise InputError(f"{file}: {kind} without a valid 'config' (a dict of CRFDepth keyword "
                             f"arguments); got {type(config).__name__}")
        return dict(config), _state_dict(file, loaded.get("state_dict"), kind), kind
    if isinstance(loaded, dict) and "state_dict" in loaded:
        kind = "Lightning checkpoint"
        hparams = loaded.get("hyper_parameters")
        config = hparams.get("crf") if isinstance(hparams, Mapping) else None
        if not is_config(config):
            found = sorted(map(str, hparams)) if isinstance(hparams, Mapping) else f"{type(hparams).__name__}"
            raise InputError(f"{file}: {kind} without the CRF configuration: expected "
                             f"hyper_parameters['crf'] (a dict of CRFDepth keyword arguments), got "
                             f"hyper_parameters {found}")
        full = _state_dict(file, loaded["state_dict"], kind)
        state = {k[len(_LIGHTNING_PREFIX):]: v for k, v in full.items() if k.startswith(_LIGHTNING_PREFIX)}
        if not state:
            raise InputError(f"{file}: {kind} has no '{_LIGHTNING_PREFIX}' keys in its state_dict (the CRF "
                             f"is stored as the LightningModule's 'model'); got {some_keys(sorted(full))}")
        return dict(config), state, kind
    _state_dict(file, loaded, "file")  # not even a state dict: that is the message
    raise InputError(BARE_STATE_DICT.format(file=file))


def _state_dict(file: Path, value: Any, kind: str) -> dict[str, torch.Tensor]:
    if not isinstance(value, dict) or not value or not all(
            isinstance(k, str) and isinstance(v, torch.Tensor) for k, v in value.items()):
        what = type(value).__name__ if not isinstance(value, dict) else (
            "an empty dict" if not value else "a dict holding other things than name -> tensor")
        raise InputError(f"{file}: the {kind} does not hold a state dict (a mapping of parameter names "
                         f"to tensors); got {what}")
    return value


def is_config(value: Any) -> bool:
    """Whether ``value`` is a mapping with string keys (a configuration, or a stored ``state``)."""
    return isinstance(value, Mapping) and all(isinstance(k, str) for k in value)


def some_keys(keys: list[str], n: int = 5) -> str:
    """The first ``n`` keys, comma-separated, ``...`` when there are more (for messages)."""
    return ", ".join(keys[:n]) + (" ..." if len(keys) > n else "")
