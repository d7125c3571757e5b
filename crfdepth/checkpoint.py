"""Save and load trained :class:`~crfdepth.model.CRFDepth` models (no Lightning needed).

:func:`load_model` reads four kinds of file. The first three are read with
``torch.load(weights_only=True)`` (only tensors and plain containers are unpickled; no
code in the file runs):

(a) a Lightning checkpoint (``.ckpt``) of the trainer in ``train/``: ``{"state_dict":
    {"model.<name>": tensor, ...}, "hyper_parameters": {"crf": {CRFDepth kwargs}}, ...}``.
    The model is rebuilt as ``CRFDepth(**hyper_parameters["crf"])`` and given the
    ``model.``-prefixed tensors (prefix stripped); other keys of the LightningModule (a
    loss module, optimizer and loop states) are ignored.
(b) crfdepth's own model file, written by :func:`save_model`: ``{"format": "crfdepth",
    "version": 1, "config": {CRFDepth kwargs}, "state_dict": {name: tensor}}``.
(c) a bare ``CRFDepth().state_dict()`` (``torch.save(model.state_dict(), path)``): it
    holds no configuration, so the model is built with the default configuration
    (superpixel mode, all potentials, refinement on) unless ``overrides`` say otherwise.
(d) a JSON weights file of :mod:`crfdepth.pretrained` (such as the shipped
    ``crfdepth/weights/kitti.json``): the configuration with the learned values written
    in; recognised by its first character ``{``.

The configuration is ``CRFDepth.config``: the constructor's keyword arguments, JSON
friendly. Its initial weights (``alpha``, ``sigma_d`` ...) are overwritten by the stored
tensors; the structural options (``mode``, ``potentials``, ``refine``, solver settings)
define the model the weights run in.
"""

from __future__ import annotations

import logging
import os
import warnings
from pathlib import Path
from typing import Any, Mapping

import torch

from crfdepth.errors import InputError
from crfdepth.io.files import atomic_write, check_output_file
from crfdepth.model import CRFDepth
from crfdepth.pretrained import read_weights

__all__ = ["FORMAT", "VERSION", "load_model", "save_model"]

logger = logging.getLogger(__name__)

FORMAT = "crfdepth"
"""Value of the ``"format"`` key of a file written by :func:`save_model`."""
VERSION = 1
"""Version of that file layout; :func:`load_model` reads this version."""

_LIGHTNING_PREFIX = "model."  # the trainer's LightningModule stores the CRF as ``self.model``


def save_model(model: CRFDepth, path: str | os.PathLike) -> Path:
    """Write ``model`` as a crfdepth model file (layout (b) of this module), atomically.

    The file holds ``{"format": "crfdepth", "version": 1, "config": model.config,
    "state_dict": {name: tensor on CPU}}`` (tensors keep their dtype). It is written to a
    temporary file in the same folder and renamed over ``path`` (``os.replace``), so a
    reader never sees a partial file and a failed write leaves no file behind.

    Args:
        model: the :class:`~crfdepth.model.CRFDepth` to save (any device, any dtype).
        path: the output file; its folder must exist. An existing file is replaced.

    Returns:
        ``path`` as a :class:`~pathlib.Path`.

    Raises:
        InputError: ``model`` is not a CRFDepth, or ``path`` is a folder.
        FileNotFoundError: the folder of ``path`` does not exist.
    """
    if not isinstance(model, CRFDepth):
        raise InputError(f"model: expected a CRFDepth, got {type(model).__name__}")
    file = check_output_file(path)
    payload = {
        "format": FORMAT,
        "version": VERSION,
        "config": _plain(dict(model.config)),
        "state_dict": {k: v.detach().cpu().clone() for k, v in model.state_dict().items()},
    }
    atomic_write(file, lambda temporary: torch.save(payload, temporary))
    logger.info("saved CRFDepth (%s mode) to %s", model.mode, file)
    return file


def load_model(path: str | os.PathLike, *, map_location: str | torch.device = "cpu",
               overrides: Mapping[str, Any] | None = None) -> CRFDepth:
    """Rebuild a :class:`~crfdepth.model.CRFDepth` from a checkpoint file.

    Reads a Lightning ``.ckpt`` (configuration from ``hyper_parameters["crf"]``), a file of
    :func:`save_model`, or a bare ``CRFDepth`` state dict (which carries no configuration:
    the **default** ``CRFDepth()`` configuration is used), as described in the module
    docstring. The file is read with ``torch.load(path, weights_only=True,
    map_location=map_location)``: a file holding anything but tensors and plain
    containers is refused without running any of its code.

    Args:
        path: the checkpoint file.
        map_location: device to load the tensors to and to put the model on ("cpu",
            "cuda", "cuda:1", a ``torch.device``).
        overrides: CRFDepth keyword arguments that replace those of the stored
            configuration (e.g. ``{"mode": "pixel"}``: the learned weights run on the
            pixel graph). Default: none.

    Returns:
        The model with the stored parameters and buffers, on ``map_location``, in the
        dtype of the stored tensors, in eval mode (call ``.train()`` to fine-tune).
        ``model.config`` is the configuration it was built with.

    Raises:
        FileNotFoundError: ``path`` does not exist (the path is named).
        InputError: naming the file and the problem: a folder; not a checkpoint (random
            bytes, a text file, a pickle of other objects); no state dict in it; a
            Lightning checkpoint without ``hyper_parameters["crf"]`` or without
            ``model.`` keys; an invalid configuration; tensors that do not fit the
            configured model (missing or unexpected keys, wrong shapes); a CUDA
            ``map_location`` without CUDA.
    """
    file = Path(path)
    if not file.exists():
        raise FileNotFoundError(f"no such checkpoint file: {file}")
    if file.is_dir():
        raise InputError(f"{file}: expected a checkpoint file, got a folder")
    device = _check_device(map_location)
    if _is_json(file):  # a weights file (crfdepth.pretrained): the configuration is the model
        config = {**read_weights(file)["config"], **dict(overrides or {})}
        try:
            model = CRFDepth(**config)
        except TypeError as exc:
            raise InputError(f"{file}: the weights file's configuration does not fit CRFDepth ({exc})") from None
        except InputError as exc:
            raise InputError(f"{file}: invalid model configuration in the weights file ({exc})") from None
        logger.info("loaded CRFDepth (%s mode) from %s (weights file)", model.mode, file)
        return model.to(device).eval()
    loaded = _torch_load(file, map_location)
    config, state, kind = _unpack(file, loaded)
    config = {**config, **dict(overrides or {})}
    try:
        model = CRFDepth(**config)
    except TypeError as exc:  # unknown or missing keyword arguments
        raise InputError(f"{file}: the {kind}'s model configuration does not fit CRFDepth ({exc})") from None
    except InputError as exc:
        raise InputError(f"{file}: invalid model configuration in the {kind} ({exc})") from None
    state = _upgrade(state)
    _check_state(file, state, model.state_dict())
    model.load_state_dict(state)
    dtypes = {v.dtype for v in state.values() if v.is_floating_point()}
    if len(dtypes) == 1:
        model = model.to(dtypes.pop())
    logger.info("loaded CRFDepth (%s mode) from %s (%s)", model.mode, file, kind)
    return model.to(device).eval()


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


def _torch_load(file: Path, map_location: str | torch.device) -> Any:
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
    """(configuration, state dict, kind of file) of a loaded checkpoint."""
    if isinstance(loaded, dict) and loaded.get("format") == FORMAT:
        kind = "crfdepth model file"
        if loaded.get("version") != VERSION:
            raise InputError(f"{file}: {kind} version {loaded.get('version')!r} is not supported "
                             f"(this crfdepth reads version {VERSION})")
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
                             f"is stored as the LightningModule's 'model'); got {_some(sorted(full))}")
        return dict(config), state, kind
    return {}, _state_dict(file, loaded, "file"), "state dict"


def _state_dict(file: Path, value: Any, kind: str) -> dict[str, torch.Tensor]:
    if not isinstance(value, dict) or not value or not all(
            isinstance(k, str) and isinstance(v, torch.Tensor) for k, v in value.items()):
        what = type(value).__name__ if not isinstance(value, dict) else (
            "an empty dict" if not value else "a dict holding other things than name -> tensor")
        raise InputError(f"{file}: the {kind} does not hold a state dict (a mapping of parameter names "
                         f"to tensors); got {what}")
    return value


def _upgrade(state: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
    """Older state dicts kept the refinement prior as a buffer ``refine_prior``; it is now the
    parameter ``log_refine_prior``."""
    if "refine_prior" in state and "log_refine_prior" not in state:
        state = dict(state)
        state["log_refine_prior"] = state.pop("refine_prior").log()
    return state


def _check_state(file: Path, state: dict[str, torch.Tensor], expected: dict[str, torch.Tensor]) -> None:
    missing = sorted(set(expected) - set(state))
    unexpected = sorted(set(state) - set(expected))
    wrong = sorted(k for k in set(expected) & set(state) if state[k].shape != expected[k].shape)
    if missing or unexpected or wrong:
        details = "; ".join(
            f"{label} ({len(keys)}): {_some(keys)}"
            for label, keys in (("missing keys", missing), ("unexpected keys", unexpected),
                                ("wrong shapes", [f"{k} {tuple(state[k].shape)} instead of "
                                                  f"{tuple(expected[k].shape)}" for k in wrong]))
            if keys)
        raise InputError(f"{file} does not match CRFDepth, a checkpoint of another model or "
                         f"configuration ({details})")


def _is_config(value: Any) -> bool:
    return isinstance(value, Mapping) and all(isinstance(k, str) for k in value)


def _some(keys: list[str], n: int = 5) -> str:
    return ", ".join(keys[:n]) + (" ..." if len(keys) > n else "")


def _plain(value: Any) -> Any:
    """Tuples as lists, recursively (the file stays loadable with ``weights_only=True``)."""
    if isinstance(value, dict):
        return {k: _plain(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_plain(v) for v in value]
    return value
