"""The "model" options of ``complete`` and ``evaluate`` and the model they ask for.

:func:`add_model_arguments` registers ``--mode`` ... ``--checkpoint``, ``--device``,
``--dtype``; :func:`build_model` loads the shipped weights or the checkpoint in the structure
stored with them, the options given overriding it; :func:`model_line` is the one line a
command prints about the model it runs (``demo`` prints it too).
"""

from __future__ import annotations

import argparse
import copy
import functools
import logging
from collections.abc import Callable

import torch

from crfdepth.checkpoints import describe, load_model, load_pretrained, own_structure
from crfdepth.cli.arguments import int_at_least
from crfdepth.config import POTENTIALS
from crfdepth.errors import InputError
from crfdepth.model import CRFDepth
from crfdepth.weights import DEFAULT_WEIGHTS, WEIGHTS

logger = logging.getLogger(__name__)

__all__ = ["REGISTERED_DEPTH_NOTE", "add_model_arguments", "available_devices", "build_model", "check_device", "model_line", "model_maker"]

MAX_SUPERPIXELS = 1216 * 352
"""Largest ``--superpixels`` (segments for a 1216x352 image, scaled with the image): one per pixel."""


def _potentials(text: str) -> tuple[str, ...]:
    """``--potentials`` value: comma list, a subset of POTENTIALS containing 'colour'."""
    names = tuple(p.strip() for p in text.split(",") if p.strip())
    unknown = [p for p in names if p not in POTENTIALS]
    if unknown or "colour" not in names:
        raise argparse.ArgumentTypeError(
            f"expected a comma list of {', '.join(POTENTIALS)} that includes colour, got {text!r}")
    return names


def add_model_arguments(parser: argparse.ArgumentParser) -> None:
    """The "model" option group (``--mode`` ... ``--checkpoint``, ``--device``, ``--dtype``),
    shared by ``complete`` and ``evaluate``; :func:`build_model` reads it.

    The help texts of the structure options name the shipped sets' own values, read from the
    sets (:func:`crfdepth.checkpoints.own_structure`), so they say what a run without them does."""

    def own(key: str) -> str:  # e.g. "kitti: pixel, paper: superpixel" or "5500 for the shipped sets"
        values = {name: own_structure(name).get(key) for name in WEIGHTS}
        values = {name: ",".join(v) if isinstance(v, (list, tuple)) else str(v) for name, v in values.items()}
        if len(set(values.values())) == 1:
            return f"{next(iter(values.values()))} for the shipped sets"
        return ", ".join(f"{name}: {value}" for name, value in values.items())

    model = parser.add_argument_group(
        "model", "The model runs in the structure stored with its weights (the shipped set's, or the "
                 "checkpoint's); --mode, --superpixels, --potentials and --no-refine, where given, override "
                 "it. The structure run is printed as one line 'model: ...' (--quiet drops it).")
    model.add_argument("--mode", choices=("superpixel", "pixel"), default=None,
                       help=f"graph nodes (default: the weights' own structure ({own('mode')}), or the "
                            f"checkpoint's)")
    model.add_argument("--superpixels", type=int_at_least(1, MAX_SUPERPIXELS), default=None, metavar="N",
                       help=f"superpixel mode: SLIC segments for a 1216x352 image (default: the weights' own "
                            f"({own('superpixels')}), or the checkpoint's)")
    model.add_argument("--potentials", type=_potentials, default=None, metavar="LIST",
                       help=f"comma list of colour,normal,distance; colour required (default: the weights' own "
                            f"({own('potentials')}), or the checkpoint's)")
    model.add_argument("--no-refine", action="store_true",
                       help="superpixel mode: keep the piecewise-constant painting, no pixel refinement")
    model.add_argument("--weights", choices=WEIGHTS, default=None,
                       help=f"shipped weight set when no --checkpoint is given: kitti (learned on KITTI, "
                            f"crfdepth/weights/README.md; frames with few returns, such as 500 samples or 16 "
                            f"beams, go to its sparse regimes, and those of a room to the nyu weights, docs/design.md "
                            f"section 17), paper (the hand-set "
                            f"initial values) or nyu (learned on NYU Depth v2 frames, for sparse indoor depth); "
                            f"default: {DEFAULT_WEIGHTS}")
    model.add_argument("--checkpoint", metavar="CKPT",
                       help="trained model instead of --weights, run in the structure stored with it: a "
                            "Lightning .ckpt of train/ (configuration in hyper_parameters['crf']), a model file "
                            "of crfdepth.save_model(model, path), or a JSON weights file "
                            "(crfdepth.save_weights, python -m train.export); a bare state_dict is "
                            "refused (it holds no structure)")
    model.add_argument("--device", choices=("cpu", "cuda"), default="cpu", help="default: cpu")
    model.add_argument("--dtype", choices=("float32", "float64"), default="float32",
                       help="default: float32")


def available_devices() -> str:
    """The ``--device`` values this machine runs, as a message names them: ``cpu`` or ``cpu, cuda (2 GPUs)``."""
    if not torch.cuda.is_available():
        return "cpu"
    count = torch.cuda.device_count()
    return f"cpu, cuda ({count} GPU{'s' if count != 1 else ''})"


def check_device(device: str | None) -> None:
    """Refuse ``--device cuda`` where PyTorch has no CUDA, naming the devices there are; ``crfdepth.cli.main`` calls
    it for every command before the command starts, :func:`build_model` again (the library's runs call that)."""
    if device == "cuda" and not torch.cuda.is_available():
        raise InputError(f"--device cuda: CUDA is not available in this PyTorch installation/machine (devices "
                         f"here: {available_devices()}); use --device cpu")


def _model_overrides(args: argparse.Namespace) -> dict:
    """CRFDepth keyword arguments given explicitly on the command line."""
    kwargs = {}
    if args.mode is not None:
        kwargs["mode"] = args.mode
    if args.superpixels is not None:
        kwargs["superpixels"] = args.superpixels
    if args.potentials is not None:
        kwargs["potentials"] = list(args.potentials)
    if args.no_refine:
        kwargs["refine"] = False
    return kwargs


REGISTERED_DEPTH_NOTE = "occlusion gate off: registered depth has no see-through returns"
"""What the model line adds when :func:`build_model` turns the gate off for registered depth."""

_OVERRIDE_FLAGS = {"mode": "--mode", "superpixels": "--superpixels", "potentials": "--potentials",
                   "refine": "--no-refine"}


def model_line(model: CRFDepth, source: str, overrides: dict, own: dict | None = None) -> str:
    """The one line a command prints about the model it runs: ``model: kitti weights, pixel grid,
    log depth, occlusion gate``; with structure options given, which ones and (``own``, where
    known) the weights' own structure."""
    line = f"model: {source}, {describe(model)}"
    if overrides:
        given = " ".join(_OVERRIDE_FLAGS[k] + ("" if k == "refine" else
                                               f" {','.join(v) if isinstance(v, list) else v}")
                         for k, v in overrides.items())
        line += f" (set by {given}" + (f"; the weights' own: {describe(own)})" if own is not None else ")")
    return line


def build_model(args: argparse.Namespace, registered_depth: bool = False) -> CRFDepth:
    """The :class:`CRFDepth` the options ask for, weights loaded, on ``--device`` / ``--dtype``.

    Without ``--checkpoint``: the shipped weight set ``--weights`` (default "kitti",
    :func:`crfdepth.load_pretrained`) in its own structure (kitti: pixel grid, log
    depth, occlusion gate), the options given overriding it. With it:
    :func:`crfdepth.load_model` rebuilds the model from the checkpoint's
    configuration (a bare state dict, which has none, is refused), and the explicit options
    (``--mode``, ``--superpixels``, ``--potentials``, ``--no-refine``) override that
    configuration. Prints the model line (:func:`model_line`) on stdout unless ``--quiet``.
    Raises InputError for a CUDA request without CUDA and for a checkpoint that cannot be
    read or does not fit (file and problem named, prefixed ``--checkpoint:``);
    FileNotFoundError for a missing checkpoint.

    ``registered_depth``: the input is a depth camera's image registered to the colour camera (``complete
    --depth``, the NYU layouts of ``evaluate``), which has no LiDAR return seen through a foreground edge: the
    shipped weights run with the occlusion gate off (``gate=False``, docs/design.md section 3b), and the model
    line says so. A ``--checkpoint`` runs as stored (its configuration is the user's choice).
    """
    check_device(args.device)
    overrides = _model_overrides(args)
    if args.checkpoint is not None:
        if args.weights is not None:
            raise InputError(f"--weights {args.weights} / --checkpoint: give one of them, not both")
        try:
            model = load_model(args.checkpoint, overrides=overrides)
        except (InputError, FileNotFoundError) as exc:
            message = str(exc).removeprefix("path: ")  # the API names its argument "path"; the user gave --checkpoint
            raise type(exc)(f"--checkpoint: {message}") from None
        line = model_line(model, f"checkpoint {args.checkpoint}", overrides)
    else:
        name = args.weights or DEFAULT_WEIGHTS
        model = load_pretrained(name, **overrides, **({"gate": False} if registered_depth else {}))
        line = model_line(model, f"{name} weights", overrides, own_structure(name) if overrides else None)
        if registered_depth:
            line += f" ({REGISTERED_DEPTH_NOTE})"
    if model.settings.structure.mode == "pixel" and (args.superpixels is not None or args.no_refine):
        logger.warning("--superpixels and --no-refine only apply to --mode superpixel; ignored")
    dtype = torch.float64 if args.dtype == "float64" else torch.float32
    model = model.to(device=args.device, dtype=dtype).eval()
    if not getattr(args, "quiet", False):
        print(line)
    return model


def model_maker(args: argparse.Namespace, registered_depth: bool = False) -> Callable[[bool], CRFDepth]:
    """:func:`build_model` of ``args`` (and ``registered_depth``) as the library's runs take it: ``make(quiet)``
    (quiet: no model line, as in the ``--devices`` processes and the other ranks, which build their own),
    picklable."""
    return functools.partial(_build_model, args, registered_depth=registered_depth)


def _build_model(args: argparse.Namespace, quiet: bool, registered_depth: bool = False) -> CRFDepth:
    told = copy.copy(args)
    told.quiet = quiet
    return build_model(told, registered_depth)
