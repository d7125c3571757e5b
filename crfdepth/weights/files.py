"""Reading and writing weights files and checkpoints, without building a model.

Everything here works on plain data: a configuration (``CRFDepth`` keyword arguments)
and a state dict (parameter name -> tensor). Building the
:class:`~crfdepth.model.CRFDepth` is left to the caller (``CRFDepth.from_stored``), so this
module does not import :mod:`crfdepth.model` and the model can import it (docs/design.md
section 8).

- The shipped weight sets: :func:`weights_path`, :func:`pretrained_state`.
- The JSON weights file: :func:`read_weights`, :func:`write_weights`.
- Any checkpoint (the three kinds of the :mod:`crfdepth.checkpoints` docstring):
  :func:`read_checkpoint`, every floating tensor checked finite and old layouts brought up
  to date. Torch files (crfdepth's own model file, the trainer's Lightning checkpoint) are
  written and opened by :mod:`crfdepth.weights.torch_files`: read with
  ``torch.load(weights_only=True)``, a bare ``state_dict()`` refused
  (:data:`~crfdepth.weights.torch_files.BARE_STATE_DICT`): it does not say which structure
  its weights belong to.
"""

from __future__ import annotations

import json
import math
import os
from pathlib import Path
from typing import Any, Mapping

import torch

from crfdepth.config import flat_view, is_grouped
from crfdepth.errors import InputError
from crfdepth.io.files import atomic_write_bytes, check_output_file
from crfdepth.weights.torch_files import check_device, is_config, load_torch_file, unpack_torch_file

__all__ = ["DEFAULT_WEIGHTS", "LEARNED", "WEIGHTS", "WEIGHTS_FORMAT", "WEIGHTS_VERSION", "pretrained_state",
           "read_checkpoint", "read_weights", "weights_path", "write_weights"]

WEIGHTS = ("kitti", "paper")
"""Names of the shipped weight sets (:func:`crfdepth.load_pretrained`, ``--weights``)."""
DEFAULT_WEIGHTS = "kitti"
"""The weight set used when none is named and no checkpoint is given."""
WEIGHTS_FORMAT = "crfdepth-weights"
"""Value of the ``"format"`` key of a JSON weights file."""
WEIGHTS_VERSION = 1
"""Version of the weights-file layout that this module reads and writes."""
LEARNED = ("alpha", "beta", "gamma", "delta", "sigma_d", "sigma_n", "sigma_p", "confidence", "refine_prior",
           "std_scale")
"""The learnable values in a configuration (the keys of ``CRFDepth.weights()``)."""

#: What a configuration written before these options existed meant: an old checkpoint is
#: rebuilt as it was trained (docs/design.md section 3b).
_OLD_DEFAULTS = {"variable": "depth", "gate": False, "head": False, "prior": "nearest", "uncertainty": "posterior"}
_FOLDER = Path(__file__).resolve().parent  # the shipped files lie beside this module


# --------------------------------------------------------------------------- shipped weight sets


def weights_path(name: str) -> Path | None:
    """The file of the shipped weight set ``name`` (None for "paper", which has none).

    Raises:
        InputError: ``name`` is not one of :data:`WEIGHTS`.
    """
    if not isinstance(name, str) or name not in WEIGHTS:
        raise InputError(f"name: expected one of the shipped weights {', '.join(WEIGHTS)}, got {name!r}")
    return None if name == "paper" else _FOLDER / f"{name}.json"


def pretrained_state(name: str) -> tuple[dict[str, Any], dict[str, torch.Tensor]]:
    """The configuration and state dict of the shipped weight set ``name``.

    The model is ``CRFDepth(**{**config, **overrides})``, then, when ``state`` is not
    empty, ``model.load_state_dict(state)``:

    - ``"kitti"``: ``crfdepth/weights/kitti.json``, a JSON weights file. Its
      configuration holds the learned values as constructor arguments (``alpha=0.469``
      ...), so ``state`` is empty and an override of a learned value (``alpha=0.3``)
      replaces it.
    - ``"paper"``: the hand-set initial values of ``CRFDepth()``: ``({}, {})``.

    A shipped set stored as a torch file would come back as :func:`read_checkpoint` reads
    any checkpoint (old layouts upgraded, tensors checked finite).

    Args:
        name: one of :data:`WEIGHTS`.

    Returns:
        ``(config, state)``: fresh objects, the caller may change them.

    Raises:
        InputError: an unknown ``name`` (the choices are listed).
    """
    file = weights_path(name)
    if file is None:
        return {}, {}
    config, state, _ = read_checkpoint(file)
    return config, state


# --------------------------------------------------------------------------- JSON weights file


def read_weights(path: str | os.PathLike) -> dict[str, Any]:
    """Read and check a weights file; returns ``{"format", "version", "config", "about"}``.

    Raises:
        FileNotFoundError: no such file.
        InputError: naming the file and the problem: not JSON, another format or
            version, no ``config`` mapping, or a learned value that is missing or not a
            finite number.
    """
    file = Path(path)
    if not file.is_file():
        raise FileNotFoundError(f"no such weights file: {file}")
    try:
        data = json.loads(file.read_text(encoding="utf-8"))
    except (UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise InputError(f"{file}: expected a crfdepth weights file (JSON), got unreadable content ({exc})") from None
    if not isinstance(data, dict) or data.get("format") != WEIGHTS_FORMAT:
        found = data.get("format") if isinstance(data, dict) else type(data).__name__
        raise InputError(f"{file}: expected a JSON object with \"format\": \"{WEIGHTS_FORMAT}\", got format {found!r}")
    if data.get("version") != WEIGHTS_VERSION:
        raise InputError(f"{file}: expected weights-file version {WEIGHTS_VERSION}, got {data.get('version')!r}")
    config = data.get("config")
    if not isinstance(config, dict):
        raise InputError(f"{file}: expected a \"config\" object (CRFDepth arguments), got {type(config).__name__}")
    values = flat_view(config)  # grouped (current files) or flat (earlier ones)
    for key in LEARNED:
        value = values.get(key)
        if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
            raise InputError(f"{file}: config[{key!r}]: expected a finite number, got {value!r}")
    data.setdefault("about", {})
    return data


def write_weights(path: str | os.PathLike, config: Mapping[str, Any], about: Mapping[str, Any] | None = None,
                  state: Mapping[str, torch.Tensor] | None = None) -> Path:
    """Write a weights file holding ``config`` (with the learned values) and ``about``, atomically.

    ``state``: the tensors that are not constructor arguments (the weights of the learned
    head, :mod:`crfdepth.potentials.head`), stored as nested lists under ``"state"``.

    Raises:
        InputError: ``path`` is a folder, or ``config`` / ``about`` are not
            JSON-serialisable (nothing is written).
        FileNotFoundError: the folder of ``path`` does not exist.
    """
    file = check_output_file(path)
    payload = {"format": WEIGHTS_FORMAT, "version": WEIGHTS_VERSION, "config": dict(config),
               "about": dict(about or {})}
    if state:
        payload["state"] = {k: v.detach().cpu().float().tolist() for k, v in state.items()}
    for name in ("about", "config"):
        try:
            json.dumps(payload[name])
        except (TypeError, ValueError) as exc:
            raise InputError(f"{name}: expected JSON-serialisable values ({exc})") from None
    text = json.dumps(payload, indent=2) + "\n"
    atomic_write_bytes(file, text.encode("utf-8"))
    return file


# --------------------------------------------------------------------------- any checkpoint


def read_checkpoint(path: str | os.PathLike, map_location: str | torch.device = "cpu"
                    ) -> tuple[dict[str, Any], dict[str, torch.Tensor], str]:
    """The configuration, state dict and kind of a checkpoint file of any of the three kinds.

    A JSON weights file gives its configuration and an empty state dict (the learned
    values are in the configuration). A torch file is read with ``torch.load(path,
    weights_only=True, map_location=map_location)``: a file holding anything but tensors
    and plain containers is refused without running any of its code. Its state dict is
    brought to the current layout (the old buffer ``refine_prior`` becomes the parameter
    ``log_refine_prior``) and every floating tensor in it must be finite. A bare state dict
    (``torch.save(model.state_dict(), path)``) is refused: without its configuration the
    weights would run in another structure (:data:`~crfdepth.weights.torch_files.BARE_STATE_DICT`).

    Args:
        path: the checkpoint file.
        map_location: device to load the tensors to ("cpu", "cuda", a ``torch.device``).

    Returns:
        ``(config, state, kind)``: the stored ``CRFDepth`` keyword arguments, the state
        dict (``{}`` for a weights file without a head), and the kind of file for messages
        ("weights file", "crfdepth model file", "Lightning checkpoint").

    Raises:
        FileNotFoundError: ``path`` does not exist.
        InputError: naming the file and the problem: a folder; not a checkpoint; no state
            dict in it; a bare state dict without a configuration; a Lightning checkpoint
            without ``hyper_parameters["crf"]`` or without ``model.`` keys; a tensor with NaN or inf (``path: <file>: parameter
            raw_alpha: expected finite values, got nan``); a CUDA ``map_location``
            without CUDA.
    """
    file = Path(path)
    if not file.exists():
        raise FileNotFoundError(f"no such checkpoint file: {file}")
    if file.is_dir():
        raise InputError(f"{file}: expected a checkpoint file, got a folder")
    device = check_device(map_location)
    if _is_json(file):
        data = read_weights(file)
        state = _tensors(file, data.get("state", {}), device)
        return _upgrade_config(dict(data["config"]), state), state, "weights file"
    config, state, kind = unpack_torch_file(file, load_torch_file(file, device))
    _check_finite(file, state)
    state = _upgrade(file, state)
    return _upgrade_config(config, state), state, kind


# --------------------------------------------------------------------------- helpers


def _is_json(file: Path) -> bool:
    """Whether ``file`` starts (after white space) with ``{``: a JSON weights file."""
    with open(file, "rb") as handle:
        return handle.read(64).lstrip()[:1] == b"{"


def _check_finite(file: Path, state: Mapping[str, torch.Tensor]) -> None:
    """Every floating tensor of ``state`` is finite; the message names the file and the parameter
    as stored in the file (a NaN weight would otherwise surface deep inside a solve)."""
    for key, value in state.items():
        if not (value.is_floating_point() or value.is_complex()):
            continue
        finite = torch.isfinite(value)
        if not bool(finite.all()):
            bad = value[~finite].flatten()
            got = str(bad[0].item())
            if value.numel() > 1:
                got += f" ({bad.numel()} of {value.numel()} values not finite)"
            raise InputError(f"path: {file}: parameter {key}: expected finite values, got {got}")


def _upgrade_config(config: dict[str, Any], state: Mapping[str, torch.Tensor]) -> dict[str, Any]:
    """Options a configuration predates take their old meaning; an empty configuration (a
    Lightning checkpoint of ``CRFDepth()`` with every default) says by its state's keys whether
    it has a gate and a head."""
    if config:
        return config if is_grouped(config) else {**_OLD_DEFAULTS, **config}
    if state:
        return {"gate": "log_gate_threshold" in state, "head": any(k.startswith("head.") for k in state),
                "uncertainty": "predictive" if "std_head.weights" in state else "posterior"}
    return config


def _tensors(file: Path, value: Any, device: torch.device) -> dict[str, torch.Tensor]:
    """The ``"state"`` of a weights file (name -> nested lists) as float32 tensors, checked finite."""
    if not is_config(value):
        raise InputError(f"{file}: expected \"state\" to map parameter names to nested lists of numbers, "
                         f"got {type(value).__name__}")
    try:
        state = {k: torch.tensor(v, dtype=torch.float32, device=device) for k, v in value.items()}
    except (TypeError, ValueError) as exc:
        raise InputError(f"{file}: \"state\": expected nested lists of numbers ({exc})") from None
    _check_finite(file, state)
    return state


def _upgrade(file: Path, state: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
    """A state dict holding the refinement prior as the buffer ``refine_prior`` gets the parameter
    ``log_refine_prior`` the model loads (its log: learned in log space, the prior stays > 0)."""
    if "refine_prior" in state and "log_refine_prior" not in state:
        positive = state["refine_prior"] > 0
        if not bool(positive.all()):
            raise InputError(f"path: {file}: parameter refine_prior: expected values > 0, "
                             f"got {state['refine_prior'][~positive].flatten()[0].item()}")
        state = dict(state)
        state["log_refine_prior"] = state.pop("refine_prior").log()
    return state
