"""Models to and from files: shipped weight sets, weights files, checkpoints.

One home for every way weights come in or go out (docs/design.md section 8); no
Lightning needed.

Shipped weight sets (:func:`load_pretrained`, ``CRFDepth.from_pretrained``, the default of
:func:`crfdepth.api.complete_depth` and of the ``crfdepth`` commands):

- ``"kitti"`` (the default): learned on real KITTI frames by the Lightning trainer in
  ``train/``; the file is ``crfdepth/weights/kitti.json`` and ``crfdepth/weights/README.md``
  beside it says which frames, config and command made it, and what it measured.
- ``"paper"``: the hand-set initial values of ``CRFDepth()`` (no file).

:func:`load_model` reads three kinds of file (:func:`crfdepth.weights.files.read_checkpoint`),
each holding the weights *and* the structure they were made for (one structure per
weights). The torch files are read with ``torch.load(weights_only=True)`` (only tensors and
plain containers are unpickled; no code in the file runs), and every floating tensor in
them must be finite:

(a) a Lightning checkpoint (``.ckpt``) of the trainer in ``train/``: ``{"state_dict":
    {"model.<name>": tensor, ...}, "hyper_parameters": {"crf": {configuration}}, ...}``.
    The model is rebuilt as ``CRFDepth(hyper_parameters["crf"])`` and given the
    ``model.``-prefixed tensors (prefix stripped); other keys of the LightningModule (a
    loss module, optimizer and loop states) are ignored.
(b) crfdepth's own model file, written by :func:`save_model`: ``{"format": "crfdepth",
    "version": 1, "config": {configuration}, "state_dict": {name: tensor}}``.
(c) a JSON weights file, written by :func:`save_weights` (such as the shipped
    ``kitti.json``): recognised by its first character ``{``. The CRF has ten learnable
    numbers, so the file is not a pickle but its complete ``CRFDepth`` configuration
    (``model.config`` with the learned values of ``alpha .. std_scale`` written in) plus
    a free-form ``"about"`` record::

        {"format": "crfdepth-weights", "version": 1,
         "config": {"structure": {"mode": "pixel", ...}, "potentials": {"alpha": 0.41, ...}, ...},
         "about": {"data": ..., "command": ..., "validation": ...}}

Files (b) and (c) of a model with regimes (the default's models for few returns, :mod:`crfdepth.inference.regime`)
hold them under ``"regimes"`` (:mod:`crfdepth.weights.regimes`): a reloaded default completes those frames as it
did. An override of the structure or the potentials at loading asks for that one model, without them, as
``CRFDepth.from_pretrained`` does.

    ``CRFDepth(config)`` rebuilds the model (the learned values are float32 values
    written out in full, so the rebuilt parameters equal the trained ones to float32
    rounding of the logit/log, about 1e-7 relative). ``python -m train.export`` turns a
    trainer checkpoint into one.

A bare ``state_dict()`` (``torch.save(model.state_dict(), path)``) is refused with a
one-line :class:`~crfdepth.errors.InputError` (``path: <file>: expected a complete model
file, got a bare state dict ...``): it holds no configuration, and the same tensors run in
another structure (the shipped pixel / log-depth / gate weights in the default superpixel
model) give a wrong depth without any error. Load it into the model it came from and
:func:`save_model` that.

The configuration is ``CRFDepth.config``: its five groups (:mod:`crfdepth.config`) as plain,
JSON-friendly data; files written before the groups hold the flat keyword arguments instead
(``{"mode": "pixel", "gate": true, "alpha": 0.41, ...}``) and load the same. Its initial weights (``alpha``, ``sigma_d`` ...) are overwritten by the stored
tensors; the structural options (``mode``, ``potentials``, ``refine``, solver settings)
define the model the weights run in.

The file formats themselves are in :mod:`crfdepth.weights.files` (torch files:
:mod:`crfdepth.weights.torch_files`) and the loading step every
path ends in (tensors into the built model, every key checked) in
:func:`crfdepth.weights.state.load_state`; neither imports the model, so
``CRFDepth.from_pretrained`` uses them directly and this module sits above the model, with no
import cycle (docs/design.md section 8).
"""

from __future__ import annotations

import logging
import os
import zipfile
from pathlib import Path
from typing import Any, Mapping

import torch

from crfdepth.config import POTENTIALS, CRFConfig, flat_view, plain_data
from crfdepth.errors import InputError
from crfdepth.inference.regime import REGIMES
from crfdepth.model import CRFDepth, asks_one_model
from crfdepth.weights.files import DEFAULT_WEIGHTS, pretrained_state, read_checkpoint, write_weights
from crfdepth.weights.regimes import json_regimes, read_regimes
from crfdepth.weights.torch_files import MODEL_FORMAT, check_device, load_torch_file, some_keys, write_model_file

__all__ = ["describe", "load_model", "load_pretrained", "own_structure", "read_trainer_checkpoint", "save_model",
           "save_weights"]

logger = logging.getLogger(__name__)


def load_pretrained(name: str = DEFAULT_WEIGHTS, **overrides: Any) -> CRFDepth:
    """A :class:`~crfdepth.model.CRFDepth` with a shipped weight set, in eval mode.

    Args:
        name: "kitti" (learned on KITTI; see ``crfdepth/weights/README.md``) or "paper"
            (the hand-set initial values of ``CRFDepth()``).
        **overrides: ``CRFDepth`` keyword arguments that replace the stored ones, e.g.
            ``mode="pixel"`` (the learned weights on the pixel graph) or
            ``potentials=("colour",)``. Overriding a learned value (``alpha=...``) is
            allowed and replaces it.

    Returns:
        The model on the CPU, float32, in eval mode.

    Raises:
        InputError: an unknown ``name``, or overrides that ``CRFDepth`` rejects.
    """
    return CRFDepth.from_pretrained(name, **overrides)


def own_structure(name: str) -> dict[str, Any]:
    """The structure the shipped weight set ``name`` is made for, by flat names: its stored
    configuration with the defaults for what it does not store (``"paper"``: the defaults).

    Raises:
        InputError: an unknown ``name``.
    """
    config, _ = pretrained_state(name)
    return plain_data(CRFConfig.build(config).flat())


def describe(model_or_config: CRFDepth | Mapping[str, Any]) -> str:
    """The structure of a model (or of a configuration) in words, for the commands' model line.

    Example: ``"pixel grid, log depth, occlusion gate"`` (the shipped kitti weights) or
    ``"superpixel graph (5500 segments) + pixel refinement, depth, no gate"`` (``CRFDepth()``).
    Potentials other than all three, the learned head, the IP-Basic prior and the
    posterior std are added where they are set.
    """
    config = model_or_config.config if isinstance(model_or_config, torch.nn.Module) else model_or_config
    get = flat_view(config).get
    if get("mode", "superpixel") == "pixel":
        parts = ["pixel grid"]
    else:
        graph = f"superpixel graph ({get('superpixels', 5500)} segments)"
        parts = [graph + (" + pixel refinement" if get("refine", True) else ", no refinement")]
    parts.append({"depth": "depth", "inverse": "inverse depth", "log": "log depth"}.get(get("variable", "depth"),
                                                                                          str(get("variable"))))
    parts.append("occlusion gate" if get("gate", False) else "no gate")
    potentials = list(get("potentials", POTENTIALS))
    if sorted(potentials) != sorted(POTENTIALS):
        parts.append("potentials " + ",".join(potentials))
    if get("head", False):
        parts.append("learned head")
    if get("prior", "nearest") != "nearest":
        parts.append(f"{get('prior')} prior")
    if get("uncertainty", "predictive") != "predictive":
        parts.append(f"{get('uncertainty')} std")
    return ", ".join(parts)


def save_weights(model: CRFDepth, path: str | os.PathLike, about: Mapping[str, Any] | None = None) -> Path:
    """Write ``model`` as a weights file (its configuration with the learned values), atomically.

    Args:
        model: a :class:`~crfdepth.model.CRFDepth`.
        path: the output ``.json`` file; its folder must exist. An existing file is replaced.
        about: JSON-serialisable record of how the weights were made (data, command,
            validation metrics ...).

    Returns:
        ``path`` as a :class:`~pathlib.Path`.

    Raises:
        InputError: ``model`` is not a CRFDepth, ``path`` is a folder, or ``about`` is not
            JSON-serialisable.
        FileNotFoundError: the folder of ``path`` does not exist.
    """
    if not isinstance(model, CRFDepth):
        raise InputError(f"model: expected a CRFDepth, got {type(model).__name__}")
    config, head = _with_weights(model)
    regimes = json_regimes({name: _with_weights(regime) for name, regime in model.regimes().items()})
    return write_weights(path, config, about, state=head, regimes=regimes)


def _with_weights(model: CRFDepth) -> tuple[dict[str, Any], dict[str, torch.Tensor]]:
    """``model``'s configuration with its current (learned) values in place of the initial ones, and the
    tensors that are not constructor arguments (its learned head's)."""
    learned = model.weights()
    if model.std_head is not None:
        learned["std_terms"] = model.std_head.terms()
    head = {k: v for k, v in model.state_dict().items() if k.startswith("head.")}
    return CRFConfig.build(model.settings, **learned).groups(), head


def save_model(model: CRFDepth, path: str | os.PathLike) -> Path:
    """Write ``model`` as a crfdepth model file (kind (b) of this module), atomically.

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
    regimes = {name: (regime.config, regime.state_dict()) for name, regime in model.regimes().items()}
    file = write_model_file(path, model.config, model.state_dict(), regimes)
    logger.info("saved CRFDepth (%s mode) to %s", model.settings.structure.mode, file)
    return file


def load_model(path: str | os.PathLike, *, map_location: str | torch.device = "cpu",
               overrides: Mapping[str, Any] | None = None) -> CRFDepth:
    """Rebuild a :class:`~crfdepth.model.CRFDepth` from a checkpoint file.

    Reads a Lightning ``.ckpt`` (configuration from ``hyper_parameters["crf"]``), a file of
    :func:`save_model` or a JSON weights file of :func:`save_weights`, as described in the
    module docstring; the model is built in the structure stored with the weights. A bare
    state dict (no configuration) is refused. Torch files are read with
    ``torch.load(path, weights_only=True, map_location=map_location)``: a file holding
    anything but tensors and plain containers is refused without running any of its code.

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
            bytes, a text file, a pickle of other objects); no state dict in it; a bare
            state dict without its configuration (``path: <file>: expected a complete
            model file, got a bare state dict ...``); a
            Lightning checkpoint without ``hyper_parameters["crf"]`` or without
            ``model.`` keys; a tensor that is not finite (``path: <file>: parameter
            raw_alpha: expected finite values, got nan``); an invalid configuration;
            tensors that do not fit the configured model (missing or unexpected keys,
            wrong shapes); a CUDA ``map_location`` without CUDA.
    """
    file = Path(path)
    config, state, kind = read_checkpoint(file, map_location)
    model = CRFDepth.from_stored(config, state, overrides=overrides, file=file, kind=kind)
    if not asks_one_model(overrides or {}):  # as from_pretrained: such overrides ask for one model
        for name, (regime_config, regime_state) in read_regimes(file, kind, check_device(map_location), REGIMES).items():
            setattr(model, name, CRFDepth.from_stored(regime_config, regime_state, file=file,
                                                      kind=f"{kind}'s regimes[{name!r}]").eval())
    logger.info("loaded CRFDepth (%s mode) from %s (%s)", model.settings.structure.mode, file, kind)
    return model.to(torch.device(map_location)).eval()


#: What :func:`read_trainer_checkpoint` expects, in its messages.
TRAINER_CHECKPOINT = "a checkpoint of the trainer (a Lightning .ckpt written by python -m train)"


def read_trainer_checkpoint(path: str | os.PathLike, *, name: str = "checkpoint", lightning: bool = False,
                            resume: bool = False) -> dict[str, Any]:
    """The whole checkpoint of the trainer in ``train/`` (a Lightning ``.ckpt``), read safely and checked.

    The file is read with ``torch.load(weights_only=True)`` (only tensors and plain containers are
    unpickled: a pickle that would run code is refused, never loaded), and must be what the trainer
    writes: a dict with ``hyper_parameters["crf"]`` and a ``state_dict`` whose ``model.`` tensors are
    finite and fit the model of that configuration (as :func:`load_model` checks them). ``python -m train`` checks ``--ckpt_path`` with it before Lightning
    starts, so that a bad file is one line rather than a traceback after the log folder is made.

    Args:
        path: the checkpoint file.
        name: the argument's name in messages, as the user gives it (``"--ckpt_path"``).
        lightning: also require what Lightning needs to restore from it (``pytorch-lightning_version``).
        resume: also require the training state a fit resumes from (``optimizer_states`` and ``loops``;
            a checkpoint saved with ``checkpoint.save_weights_only`` holds the model alone).

    Returns:
        The checkpoint as ``torch.load`` gives it, tensors on the CPU.

    Raises:
        InputError: one line, ``<name>: expected a checkpoint of the trainer ..., got <what the file is>``:
            no such file, a folder, a file ``torch.load(weights_only=True)`` does not read (random
            bytes, text, a truncated archive, a pickle of other objects), another kind of torch file
            (a bare state dict, a crfdepth model file, another LightningModule's checkpoint), tensors
            that are not finite or do not fit the stored configuration, or (``resume``) no training state.
    """
    file = Path(path)
    expected = f"{name}: expected {TRAINER_CHECKPOINT}"
    if not file.exists():
        raise InputError(f"{expected}, got {file}, which does not exist")
    if file.is_dir():
        raise InputError(f"{expected}, got the folder {file}")
    try:
        loaded = load_torch_file(file, torch.device("cpu"))
    except InputError as exc:  # "<file> is not a torch state dict ... (<why>)": keep the why
        raise InputError(f"{expected}, got {file}, {_unreadable(file, exc)}") from None
    if not isinstance(loaded, dict):
        raise InputError(f"{expected}, got {file}, a torch file holding a {type(loaded).__name__}")
    if loaded and all(isinstance(v, torch.Tensor) for v in loaded.values()):
        raise InputError(f"{expected}, got {file}, a bare state dict (parameter name -> tensor, "
                         f"{some_keys(sorted(map(str, loaded)), 3)})")
    if loaded.get("format") == MODEL_FORMAT:
        raise InputError(f"{expected}, got {file}, a crfdepth model file (crfdepth.save_model): it holds the weights "
                         "without the trainer's state")
    required = ("pytorch-lightning_version",) * (lightning or resume) + ("state_dict", "hyper_parameters")
    missing = [key for key in required if key not in loaded]
    if missing:
        keys = some_keys(sorted(map(str, loaded))) or "none"
        raise InputError(f"{expected}, got {file}, a torch file without {', '.join(repr(k) for k in missing)} "
                         f"(its keys: {keys})")
    hparams = loaded["hyper_parameters"]
    if not isinstance(hparams, Mapping) or not isinstance(hparams.get("crf"), Mapping):
        raise InputError(f"{expected}, got {file}, a Lightning checkpoint of another model: no "
                         "hyper_parameters['crf'] (the CRF's configuration)")
    try:
        config, state, kind = read_checkpoint(file)
        CRFDepth.from_stored(config, state, file=file, kind=kind)
    except InputError as exc:
        text = str(exc)
        for prefix in (f"path: {file}: ", f"{file}: "):
            text = text.removeprefix(prefix)
        raise InputError(f"{expected}, got {file}, whose weights do not load: {text}") from None
    if resume:
        absent = [key for key in ("optimizer_states", "loops") if key not in loaded]
        if absent:
            raise InputError(f"{expected} with the training state to resume from, got {file}, which holds the model's "
                             f"weights only (no {', '.join(absent)}: saved with checkpoint.save_weights_only)")
    return loaded


def _unreadable(file: Path, exc: InputError) -> str:
    """Why ``torch.load(weights_only=True)`` did not read ``file`` (``exc``: :func:`load_torch_file`'s
    ``<file> is not a torch state dict ... (<why>)``), for :func:`read_trainer_checkpoint`."""
    text = str(exc)
    why = text[text.index(" (") + 2:-1] if text.startswith(str(file)) and " (" in text else text
    with open(file, "rb") as handle:
        head = handle.read(4)
    if head == b"PK\x03\x04" and not zipfile.is_zipfile(file):
        return "a damaged or truncated torch.save archive (its zip directory is missing)"
    refused = "torch.load with weights_only=True refused it: "
    if why.startswith(refused):
        return (f"which torch.load(weights_only=True) refuses ({why[len(refused):]}): it holds other objects than "
                "tensors and plain containers, and nothing in it was run")
    return f"which torch.load(weights_only=True) does not read: {why}"

