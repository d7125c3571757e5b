"""Reading and writing weights files and checkpoints, without building a model.

Everything here works on plain data: a configuration (``CRFDepth`` keyword arguments)
and a state dict (parameter name -> tensor). Building the
:class:`~crfdepth.model.CRFDepth` is left to the caller (``CRFDepth.from_stored``), so this
module does not import :mod:`crfdepth.model` and the model can import it (docs/design.md
section 8).

- The shipped weight sets: :func:`weights_path`, :func:`pretrained_state`.
- The JSON weights file: :func:`read_weights`, :func:`write_weights`.
- crfdepth's own model file: :func:`write_model_file`.
- Any checkpoint (the three kinds of the :mod:`crfdepth.checkpoints` docstring):
  :func:`read_checkpoint`. Torch files are read with ``torch.load(weights_only=True)``;
  every floating tensor must be finite. A bare ``state_dict()`` is refused
  (:data:`BARE_STATE_DICT`): it does not say which structure its weights belong to.
"""

from __future__ import annotations

import json
import math
import os
import warnings
from pathlib import Path
from typing import Any, Mapping

import torch

from crfdepth.errors import InputError
from crfdepth.io.files import atomic_write, atomic_write_bytes, check_output_file

__all__ = ["BARE_STATE_DICT", "DEFAULT_WEIGHTS", "LEARNED", "MODEL_FORMAT", "MODEL_VERSION", "WEIGHTS",
           "WEIGHTS_FORMAT", "WEIGHTS_VERSION", "pretrained_state", "read_checkpoint", "read_weights", "weights_path",
           "write_model_file", "write_weights"]

WEIGHTS = ("kitti", "paper")
"""Names of the shipped weight sets (:func:`crfdepth.load_pretrained`, ``--weights``)."""
DEFAULT_WEIGHTS = "kitti"
"""The weight set used when none is named and no checkpoint is given."""
WEIGHTS_FORMAT = "crfdepth-weights"
"""Value of the ``"format"`` key of a JSON weights file."""
WEIGHTS_VERSION = 1
"""Version of the weights-file layout that this module reads and writes."""
MODEL_FORMAT = "crfdepth"
"""Value of the ``"format"`` key of a crfdepth model file (:func:`crfdepth.save_model`)."""
MODEL_VERSION = 1
"""Version of the model-file layout that this module reads and writes."""
LEARNED = ("alpha", "beta", "gamma", "delta", "sigma_d", "sigma_n", "sigma_p", "confidence", "refine_prior",
           "std_scale")
"""The learnable values in a configuration (the keys of ``CRFDepth.weights()``)."""

#: What a configuration written before these options existed meant: an old checkpoint is
#: rebuilt as it was trained (docs/design.md section 3b).
_OLD_DEFAULTS = {"variable": "depth", "gate": False, "head": False, "prior": "nearest", "uncertainty": "posterior"}

BARE_STATE_DICT = (
    "path: {file}: expected a complete model file, got a bare state dict: it holds weights but not the "
    "model's structure (mode, variable, gate ...); load it into the model it came from and save that with "
    "crfdepth.save_model(model, path), or give the trainer's Lightning .ckpt as it is")
"""The refusal of a bare ``state_dict()`` (no configuration): run in another structure (the default
one), the weights would give wrong depth without any error."""

_FOLDER = Path(__file__).resolve().parent  # the shipped files lie beside this module
_LIGHTNING_PREFIX = "model."  # the trainer's LightningModule stores the CRF as ``self.model``


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
    for key in LEARNED:
        value = config.get(key)
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


# --------------------------------------------------------------------------- torch files


def write_model_file(path: str | os.PathLike, config: Mapping[str, Any], state: Mapping[str, torch.Tensor]) -> Path:
    """Write a crfdepth model file ``{"format", "version", "config", "state_dict"}``, atomically.

    Tuples of ``config`` are stored as lists and tensors are moved to the CPU (their dtype
    is kept), so the file loads with ``torch.load(weights_only=True)``. The file is
    written beside ``path`` and renamed over it: a failed write leaves no file behind.

    Raises:
        InputError: ``path`` is a folder.
        FileNotFoundError: the folder of ``path`` does not exist.
    """
    file = check_output_file(path)
    payload = {
        "format": MODEL_FORMAT,
        "version": MODEL_VERSION,
        "config": _plain(dict(config)),
        "state_dict": {k: v.detach().cpu().clone() for k, v in state.items()},
    }
    atomic_write(file, lambda temporary: torch.save(payload, temporary))
    return file


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
    weights would run in another structure (:data:`BARE_STATE_DICT`).

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
    device = _check_device(map_location)
    if _is_json(file):
        data = read_weights(file)
        state = _tensors(file, data.get("state", {}), device)
        return _upgrade_config(dict(data["config"]), state), state, "weights file"
    config, state, kind = _unpack(file, _torch_load(file, device))
    _check_finite(file, state)
    state = _upgrade(file, state)
    return _upgrade_config(config, state), state, kind


# --------------------------------------------------------------------------- helpers


def _check_device(map_location: str | torch.device) -> torch.device:
    try:
        device = torch.device(map_location)
    except (RuntimeError, TypeError):
        raise InputError(f"map_location: expected a device such as 'cpu' or 'cuda', got {map_location!r}") from None
    if device.type == "cuda" and not torch.cuda.is_available():
        raise InputError(f"map_location: CUDA is not available on this machine/PyTorch installation, "
                         f"got {map_location!r}; use 'cpu'")
    return device


def _is_json(file: Path) -> bool:
    """Whether ``file`` starts (after white space) with ``{``: a JSON weights file."""
    with open(file, "rb") as handle:
        return handle.read(64).lstrip()[:1] == b"{"


def _torch_load(file: Path, map_location: torch.device) -> Any:
    try:
        with warnings.catch_warnings():  # e.g. "pickle protocol 4": the error below says it all
            warnings.simplefilter("ignore", UserWarning)
            return torch.load(file, weights_only=True, map_location=map_location)
    except Exception as exc:  # unpickling errors come in many types; all mean "not a checkpoint"
        with open(file, "rb") as handle:
            head = handle.read(8)
        if head.startswith(b"PK\x03\x04") or head.startswith(b"\x80"):  # zip archive / pickle >= 2
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


def _unpack(file: Path, loaded: Any) -> tuple[dict[str, Any], dict[str, torch.Tensor], str]:
    """(configuration, state dict, kind of file) of a loaded torch file."""
    if isinstance(loaded, dict) and loaded.get("format") == MODEL_FORMAT:
        kind = "crfdepth model file"
        if loaded.get("version") != MODEL_VERSION:
            raise InputError(f"{file}: {kind} version {loaded.get('version')!r} is not supported "
                             f"(this crfdepth reads version {MODEL_VERSION})")
        config = loaded.get("config")
        if not _is_config(config):
            raise InputError(f"{file}: {kind} without a valid 'config' (a dict of CRFDepth keyword "
                             f"arguments); got {type(config).__name__}")
        return dict(config), _state_dict(file, loaded.get("state_dict"), kind), kind
    if isinstance(loaded, dict) and "state_dict" in loaded:
        kind = "Lightning checkpoint"
        hparams = loaded.get("hyper_parameters")
        config = hparams.get("crf") if isinstance(hparams, Mapping) else None
        if not _is_config(config):
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
        return {**_OLD_DEFAULTS, **config}
    if state:
        return {"gate": "log_gate_threshold" in state, "head": any(k.startswith("head.") for k in state),
                "uncertainty": "predictive" if "std_head.weights" in state else "posterior"}
    return config


def _tensors(file: Path, value: Any, device: torch.device) -> dict[str, torch.Tensor]:
    """The ``"state"`` of a weights file (name -> nested lists) as float32 tensors, checked finite."""
    if not _is_config(value):
        raise InputError(f"{file}: expected \"state\" to map parameter names to nested lists of numbers, "
                         f"got {type(value).__name__}")
    try:
        state = {k: torch.tensor(v, dtype=torch.float32, device=device) for k, v in value.items()}
    except (TypeError, ValueError) as exc:
        raise InputError(f"{file}: \"state\": expected nested lists of numbers ({exc})") from None
    _check_finite(file, state)
    return state


def _upgrade(file: Path, state: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
    """Older state dicts kept the refinement prior as a buffer ``refine_prior``; it is now the
    parameter ``log_refine_prior``."""
    if "refine_prior" in state and "log_refine_prior" not in state:
        positive = state["refine_prior"] > 0
        if not bool(positive.all()):
            raise InputError(f"path: {file}: parameter refine_prior: expected values > 0, "
                             f"got {state['refine_prior'][~positive].flatten()[0].item()}")
        state = dict(state)
        state["log_refine_prior"] = state.pop("refine_prior").log()
    return state


def _is_config(value: Any) -> bool:
    return isinstance(value, Mapping) and all(isinstance(k, str) for k in value)


def some_keys(keys: list[str], n: int = 5) -> str:
    return ", ".join(keys[:n]) + (" ..." if len(keys) > n else "")


def _plain(value: Any) -> Any:
    """Tuples as lists, recursively (the file stays loadable with ``weights_only=True``)."""
    if isinstance(value, dict):
        return {k: _plain(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_plain(v) for v in value]
    return value
