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
from pathlib import Path
from typing import Any, Mapping

import torch

from crfdepth.config import POTENTIALS, CRFConfig, flat_view, plain_data
from crfdepth.errors import InputError
from crfdepth.model import CRFDepth
from crfdepth.weights.files import DEFAULT_WEIGHTS, pretrained_state, read_checkpoint, write_weights
from crfdepth.weights.torch_files import write_model_file

__all__ = ["describe", "load_model", "load_pretrained", "own_structure", "save_model", "save_weights"]

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
    learned = model.weights()  # the current (learned) values replace the initial ones
    if model.std_head is not None:
        learned["std_terms"] = model.std_head.terms()
    config = CRFConfig.build(model.settings, **learned).groups()
    head = {k: v for k, v in model.state_dict().items() if k.startswith("head.")}
    return write_weights(path, config, about, state=head)


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
    file = write_model_file(path, model.config, model.state_dict())
    logger.info("saved CRFDepth (%s mode) to %s", model.mode, file)
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
    logger.info("loaded CRFDepth (%s mode) from %s (%s)", model.mode, file, kind)
    return model.to(torch.device(map_location)).eval()
