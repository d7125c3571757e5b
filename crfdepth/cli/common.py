"""What the ``crfdepth`` sub-commands share: argument types, the model options, output paths.

- :func:`int_at_least`: an argparse type naming what was expected;
- :func:`add_model_arguments` / :func:`build_model`: the "model" options of ``complete``
  and ``evaluate`` (``--weights`` or ``--checkpoint``, structure overrides, device, dtype);
- :func:`check_output_file` / :func:`make_output_dir` / :func:`same_file`: output paths
  checked before any computation, named by their flag;
- :func:`write_rgb_png`: a picture, written atomically.
"""

from __future__ import annotations

import argparse
import logging
import os
from pathlib import Path

import cv2
import numpy as np
import torch

from crfdepth.errors import InputError
from crfdepth.io.files import atomic_write_bytes
from crfdepth.model import POTENTIALS, CRFDepth
from crfdepth.pictures import depth_picture, std_picture
from crfdepth.weights import DEFAULT_WEIGHTS, WEIGHTS, load_model, load_pretrained

logger = logging.getLogger(__name__)

__all__ = ["add_model_arguments", "build_model", "check_output_file", "int_at_least", "make_output_dir",
           "same_file", "vis_range_type", "write_pictures", "write_rgb_png"]


def _potentials(text: str) -> tuple[str, ...]:
    """``--potentials`` value: comma list, a subset of POTENTIALS containing 'colour'."""
    names = tuple(p.strip() for p in text.split(",") if p.strip())
    unknown = [p for p in names if p not in POTENTIALS]
    if unknown or "colour" not in names:
        raise argparse.ArgumentTypeError(
            f"expected a comma list of {', '.join(POTENTIALS)} that includes colour, got {text!r}")
    return names


def int_at_least(low: int):
    """An argparse ``type`` accepting integers >= ``low`` (shared by the sub-commands)."""

    def parse(text: str) -> int:
        try:
            value = int(text)
        except ValueError:
            value = low - 1
        if value < low:
            raise argparse.ArgumentTypeError(f"expected an integer >= {low}, got {text!r}")
        return value

    return parse


def add_model_arguments(parser: argparse.ArgumentParser) -> None:
    """The "model" option group (``--mode`` ... ``--checkpoint``, ``--device``, ``--dtype``),
    shared by ``complete`` and ``evaluate``; :func:`build_model` reads it."""
    model = parser.add_argument_group(
        "model", "With --checkpoint, the checkpoint's configuration defines the model and the "
                 "options --mode, --superpixels, --potentials and --no-refine, where given, override it.")
    model.add_argument("--mode", choices=("superpixel", "pixel"), default=None,
                       help="graph nodes (default: the checkpoint's, else superpixel)")
    model.add_argument("--superpixels", type=int_at_least(1), default=None, metavar="N",
                       help="SLIC segments for a 1216x352 image (default: the checkpoint's, else 5500)")
    model.add_argument("--potentials", type=_potentials, default=None, metavar="LIST",
                       help="comma list of colour,normal,distance; colour required (default: the "
                            "checkpoint's, else all)")
    model.add_argument("--no-refine", action="store_true",
                       help="superpixel mode: keep the piecewise-constant painting, no pixel refinement")
    model.add_argument("--weights", choices=WEIGHTS, default=None,
                       help=f"shipped weight set when no --checkpoint is given: kitti (learned on KITTI, "
                            f"crfdepth/weights/README.md) or paper (the hand-set initial values); "
                            f"default: {DEFAULT_WEIGHTS}")
    model.add_argument("--checkpoint", metavar="CKPT",
                       help="trained model instead of --weights: a Lightning .ckpt of train/ (configuration "
                            "in hyper_parameters['crf']), a crfdepth model file (crfdepth.checkpoint."
                            "save_model), a JSON weights file (crfdepth.weights) or a bare CRFDepth "
                            "state_dict (default configuration)")
    model.add_argument("--device", choices=("cpu", "cuda"), default="cpu", help="default: cpu")
    model.add_argument("--dtype", choices=("float32", "float64"), default="float32",
                       help="default: float32")


def _check_writable_dir(directory: Path, what: str) -> None:
    if not directory.is_dir():
        raise FileNotFoundError(f"{what}: output folder does not exist: {directory}")
    if not os.access(directory, os.W_OK | os.X_OK):
        raise PermissionError(f"{what}: output folder is not writable: {directory}")


def check_output_file(path: str, what: str) -> Path:
    """An output PNG path whose folder exists and is writable (nothing is created)."""
    out = Path(path)
    if out.suffix.lower() != ".png":
        raise InputError(f"{what}: expected a file name ending in .png, got {out}")
    if out.is_dir():
        raise IsADirectoryError(f"{what}: expected a file name, got a folder: {out}")
    _check_writable_dir(out.parent, what)
    return out


def make_output_dir(path: str | Path, what: str) -> Path:
    """An output folder, created (with parents) if missing; must be writable."""
    directory = Path(path)
    if directory.exists() and not directory.is_dir():
        raise InputError(f"{what}: expected a folder, got a file: {directory}")
    try:
        directory.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise PermissionError(f"{what}: cannot create output folder {directory}: {exc.strerror}") from None
    _check_writable_dir(directory, what)
    return directory


def same_file(a: Path, b: Path) -> bool:
    return os.path.realpath(a) == os.path.realpath(b)


def write_rgb_png(path: Path, rgb: np.ndarray) -> None:
    """Write an (H, W, 3) uint8 RGB picture as PNG, atomically (temporary file + rename)."""
    ok, encoded = cv2.imencode(".png", cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR))
    if not ok:  # pragma: no cover - cv2 encodes any uint8 HxWx3 array
        raise InputError(f"vis: could not encode a picture of shape {rgb.shape} as PNG")
    atomic_write_bytes(path, encoded.tobytes())


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


def build_model(args: argparse.Namespace) -> CRFDepth:
    """The :class:`CRFDepth` the options ask for, weights loaded, on ``--device`` / ``--dtype``.

    Without ``--checkpoint``: the shipped weight set ``--weights`` (default "kitti",
    :func:`crfdepth.weights.load_pretrained`) with the options given overriding its
    configuration. With it: :func:`crfdepth.weights.load_model` rebuilds the model
    from the checkpoint's configuration (the default one for a bare state dict), and the
    explicit options (``--mode``, ``--superpixels``, ``--potentials``, ``--no-refine``)
    override that configuration. Raises InputError for a CUDA request without CUDA and for
    a checkpoint that cannot be read or does not fit (file and problem named, prefixed
    ``--checkpoint:``); FileNotFoundError for a missing checkpoint.
    """
    if args.device == "cuda" and not torch.cuda.is_available():
        raise InputError("--device cuda: CUDA is not available in this PyTorch installation/machine; "
                         "use --device cpu")
    overrides = _model_overrides(args)
    if args.checkpoint is not None:
        if args.weights is not None:
            raise InputError(f"--weights {args.weights} / --checkpoint: give one of them, not both")
        try:
            model = load_model(args.checkpoint, overrides=overrides)
        except (InputError, FileNotFoundError) as exc:
            message = str(exc).removeprefix("path: ")  # the API names its argument "path"; the user gave --checkpoint
            raise type(exc)(f"--checkpoint: {message}") from None
    else:
        model = load_pretrained(args.weights or DEFAULT_WEIGHTS, **overrides)
    if model.mode == "pixel" and (args.superpixels is not None or args.no_refine):
        logger.warning("--superpixels and --no-refine only apply to --mode superpixel; ignored")
    dtype = torch.float64 if args.dtype == "float64" else torch.float32
    return model.to(device=args.device, dtype=dtype).eval()


def vis_range_type(text: str) -> float:
    """One bound of ``--vis-range``: a finite number of metres > 0."""
    try:
        value = float(text)
    except ValueError:
        value = float("nan")
    if not np.isfinite(value) or value <= 0:
        raise argparse.ArgumentTypeError(f"expected a finite number of metres > 0, got {text!r}")
    return value


def write_pictures(folder: Path, stem: str, depth: np.ndarray, std: np.ndarray | None,
                   vis_range: tuple[float, float] | None) -> list[Path]:
    """``<stem>_vis_depth.png`` and ``<stem>_vis_std.png`` with colour bars in metres (atomic writes).

    ``vis_range`` fixes the depth colour scale (metres) for every frame of a sequence.
    """
    if vis_range is not None and not vis_range[0] < vis_range[1]:
        raise InputError(f"--vis-range: expected MIN < MAX, got {vis_range[0]:g} {vis_range[1]:g}")
    written = [folder / f"{stem}_vis_depth.png"]
    write_rgb_png(written[0], depth_picture(depth, vis_range=vis_range))
    if std is not None:
        written.append(folder / f"{stem}_vis_std.png")
        write_rgb_png(written[1], std_picture(std))
    return written
