"""What the ``crfdepth`` sub-commands share: argument types, the model options, output paths.

- :func:`int_at_least` / :func:`fraction` / :func:`positive_number`: argparse types naming what
  was expected;
- :func:`add_model_arguments` / :func:`build_model`: the "model" options of ``complete``
  and ``evaluate`` (``--weights`` or ``--checkpoint``, structure overrides, device, dtype);
- :func:`add_batch_arguments` / :func:`frame_batches` / :func:`complete_batch_with_cli_advice`: frames
  read by DataLoader workers, batched by size, completed by one model call per batch;
- :func:`make_output_dir` / :func:`same_file`: output paths checked before any computation,
  named by their flag (a file is actually created in the folder and removed,
  :func:`crfdepth.io.files.probe_folder`); output files are checked with
  :func:`crfdepth.io.files.check_output_file`;
- :func:`check_output_folders` / :func:`output_folders`: the output folders of the folder
  and bag modes, checked up front (another run writing there is refused at once), then
  created and locked for the run (:func:`crfdepth.io.files.lock_folder`);
- :func:`complete_frame` / :func:`write_frame` / :func:`flag_names`: one frame through
  :func:`crfdepth.api.complete_depth`, its PNGs written, errors under the user's flags
  (``complete``'s one-frame, point-cloud and bag modes);
- :func:`write_rgb_png`: a picture, written atomically.
"""

from __future__ import annotations

import argparse
import contextlib
import csv
import io
import logging
import math
import os
import sys
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import torch
from torch.utils.data import DataLoader, Dataset

from crfdepth import api
from crfdepth.cli.progress import FrameProgress
from crfdepth.data.sample import Batch, Sample, collate_samples
from crfdepth.errors import InputError
from crfdepth.io.files import atomic_write_bytes, check_not_locked, lock_folder, probe_folder
from crfdepth.io.kitti import write_depth_png
from crfdepth.memory import MemoryRefusal, cli_advice
from crfdepth.model import POTENTIALS, CRFDepth
from crfdepth.pictures.figures import depth_picture, std_picture
from crfdepth.weights import DEFAULT_WEIGHTS, WEIGHTS
from crfdepth.checkpoints import describe, load_model, load_pretrained, own_structure

logger = logging.getLogger(__name__)

__all__ = ["BAD_INPUT", "LISTED_BAD", "MAX_WORKERS", "SKIPPED_CSV", "add_batch_arguments", "bad_frames",
           "skipped_frames", "write_skipped", "add_model_arguments", "build_model",
           "check_output_folders", "check_writable_dir",
           "check_sample", "complete_batch_with_cli_advice", "complete_frame", "flag_names", "fraction",
           "frame_batches", "int_at_least", "make_output_dir", "output_folders", "positive_number", "same_file",
           "vis_range_type", "write_frame", "write_pictures", "write_rgb_png"]

_MIN_DEPTH = 1.0 / 256.0  # smallest non-zero code of a KITTI depth PNG, metres
# What ``crfdepth.cli.main`` reports as bad input (one line, exit status 2).
BAD_INPUT = (InputError, FileNotFoundError, PermissionError, IsADirectoryError)
# More reading processes than this cannot keep up better with a solve that takes seconds per
# frame; the cap turns a typo (--workers 400) into a usage error instead of 400 processes.
MAX_WORKERS = 64


def _potentials(text: str) -> tuple[str, ...]:
    """``--potentials`` value: comma list, a subset of POTENTIALS containing 'colour'."""
    names = tuple(p.strip() for p in text.split(",") if p.strip())
    unknown = [p for p in names if p not in POTENTIALS]
    if unknown or "colour" not in names:
        raise argparse.ArgumentTypeError(
            f"expected a comma list of {', '.join(POTENTIALS)} that includes colour, got {text!r}")
    return names


def int_at_least(low: int, high: int | None = None, meaning: str | None = None):
    """An argparse ``type`` accepting integers >= ``low`` (and <= ``high`` when given); ``meaning``,
    when given, says in the message what the number is."""
    bounds = f">= {low}" if high is None else f"in [{low}, {high}]"
    note = f" ({meaning})" if meaning else ""

    def parse(text: str) -> int:
        try:
            value = int(text)
        except ValueError:
            value = low - 1
        if value < low or (high is not None and value > high):
            raise argparse.ArgumentTypeError(f"expected an integer {bounds}{note}, got {text!r}")
        return value

    return parse


def fraction(*, include_one: bool, meaning: str | None = None):
    """An argparse ``type`` accepting a number in (0, 1] (``include_one``) or in (0, 1); ``meaning``,
    when given, says in the message what the number is."""
    bounds = "(0, 1]" if include_one else "(0, 1)"
    note = f" ({meaning})" if meaning else ""

    def parse(text: str) -> float:
        try:
            value = float(text)
        except ValueError:
            value = math.nan
        if not (0.0 < value <= 1.0 if include_one else 0.0 < value < 1.0):  # also refuses nan
            raise argparse.ArgumentTypeError(f"expected a number in {bounds}{note}, got {text!r}")
        return value

    return parse


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
    model.add_argument("--superpixels", type=int_at_least(1), default=None, metavar="N",
                       help=f"superpixel mode: SLIC segments for a 1216x352 image (default: the weights' own "
                            f"({own('superpixels')}), or the checkpoint's)")
    model.add_argument("--potentials", type=_potentials, default=None, metavar="LIST",
                       help=f"comma list of colour,normal,distance; colour required (default: the weights' own "
                            f"({own('potentials')}), or the checkpoint's)")
    model.add_argument("--no-refine", action="store_true",
                       help="superpixel mode: keep the piecewise-constant painting, no pixel refinement")
    model.add_argument("--weights", choices=WEIGHTS, default=None,
                       help=f"shipped weight set when no --checkpoint is given: kitti (learned on KITTI, "
                            f"crfdepth/weights/README.md) or paper (the hand-set initial values); "
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


def check_writable_dir(directory: Path, what: str) -> None:
    """An existing folder where a file can be created (named ``what`` in the error): a hidden file is
    created there and removed (:func:`crfdepth.io.files.probe_folder`), since permission bits do not
    bind root and ``/proc`` or ``/sys`` refuse new files whatever ``os.access`` says."""
    if not directory.is_dir():
        raise FileNotFoundError(f"{what}: output folder does not exist: {directory}")
    problem = probe_folder(directory)
    if problem is not None:
        raise PermissionError(f"{what}: output folder is not writable: {directory} (creating a file there "
                              f"fails: {problem})")


def make_output_dir(path: str | Path, what: str) -> Path:
    """An output folder, created (with parents) if missing; must be writable."""
    directory = Path(path)
    if directory.exists() and not directory.is_dir():
        raise InputError(f"{what}: expected a folder, got a file: {directory}")
    try:
        directory.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise PermissionError(f"{what}: cannot create output folder {directory}: {exc.strerror}") from None
    check_writable_dir(directory, what)
    return directory


def check_output_folders(args: argparse.Namespace, inputs: list[Path], source: str) -> list[tuple[str, str | None]]:
    """The ``--out-dir``, ``--out-std-dir`` and ``--vis`` folders of the folder and bag modes as ``(flag, folder)``
    (``--vis`` only when given; a bare ``--vis`` is ``<out-dir>_vis``), refused when one is among ``inputs``
    (named ``source`` in the message), two are the same folder, one is a file, the folder (or, for one to be
    created, the nearest existing folder above it) does not take new files, or another crfdepth run holds
    it locked. Nothing is created (a probe file is created and removed)."""
    targets = [("--out-dir", args.out_dir), ("--out-std-dir", args.out_std_dir)]
    if args.vis is not None:
        targets.append(("--vis", args.vis or f"{Path(args.out_dir).resolve()}_vis"))
    for flag, value in targets:
        if value is not None and any(same_file(value, p) for p in inputs):
            raise InputError(f"{flag}: {value} is {source}; refusing to write there")
    resolved = [os.path.realpath(v) for _, v in targets if v is not None]
    if len(set(resolved)) != len(resolved):
        raise InputError("--out-dir, --out-std-dir and --vis: expected different folders")
    for flag, value in targets:
        if value is None:
            continue
        folder = Path(value)
        if folder.exists() and not folder.is_dir():
            raise InputError(f"{flag}: expected a folder, got a file: {folder}")
        # the folder, or the nearest one above it that exists (the run creates the rest), must take new files
        existing = next((p for p in (folder, *folder.absolute().parents) if p.is_dir()), None)
        if existing is not None:
            check_writable_dir(existing, flag)
        check_not_locked(folder, flag)  # another run writes there: refused now, not after the checks
    return targets


@contextlib.contextmanager
def output_folders(targets: list[tuple[str, str | None]]) -> Iterator[list[Path | None]]:
    """The ``(flag, folder)`` targets of :func:`check_output_folders`, created (:func:`make_output_dir`) and
    locked (:func:`crfdepth.io.files.lock_folder`) for the ``with`` block; yields their paths (None where not
    given). On leaving the block the locks are released, and a folder this run created that is still
    empty (nothing was written: an error or Ctrl-C before the first frame) is removed again."""
    created: list[Path] = []
    with contextlib.ExitStack() as stack:
        try:
            folders: list[Path | None] = []
            for flag, value in targets:
                if value is None:
                    folders.append(None)
                    continue
                existed = Path(value).is_dir()
                folder = make_output_dir(value, flag)
                if not existed:
                    created.append(folder)
                stack.enter_context(lock_folder(folder, flag))
                folders.append(folder)
            yield folders
        finally:
            stack.close()  # the locks first, so that an empty folder is empty
            for folder in reversed(created):
                with contextlib.suppress(OSError):
                    folder.rmdir()  # only succeeds when empty


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


def build_model(args: argparse.Namespace) -> CRFDepth:
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
        line = model_line(model, f"checkpoint {args.checkpoint}", overrides)
    else:
        name = args.weights or DEFAULT_WEIGHTS
        model = load_pretrained(name, **overrides)
        line = model_line(model, f"{name} weights", overrides, own_structure(name) if overrides else None)
    if model.mode == "pixel" and (args.superpixels is not None or args.no_refine):
        logger.warning("--superpixels and --no-refine only apply to --mode superpixel; ignored")
    dtype = torch.float64 if args.dtype == "float64" else torch.float32
    model = model.to(device=args.device, dtype=dtype).eval()
    if not getattr(args, "quiet", False):
        print(line)
    return model


def positive_number(unit: str):
    """An argparse ``type`` accepting a finite number > 0 of ``unit`` (e.g. "metres", "seconds")."""
    def parse(text: str) -> float:
        try:
            value = float(text)
        except ValueError:
            value = float("nan")
        if not np.isfinite(value) or value <= 0:
            raise argparse.ArgumentTypeError(f"expected a finite number of {unit} > 0, got {text!r}")
        return value

    return parse


vis_range_type = positive_number("metres")  # one bound of --vis-range


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


# --------------------------------------------------------------------------- one frame


def flag_names(exc: InputError, flags: dict[str, str]) -> InputError:
    """The API's message with its argument name (``K``, ``sparse`` ...) replaced by the user's flag."""
    text = str(exc)
    head, sep, rest = text.partition(":")
    if sep and head.strip() in flags:
        return InputError(f"{flags[head.strip()]}:{rest}")
    if "*" in flags:  # a message about the inputs together (e.g. no point lands in the image)
        return InputError(f"{flags['*']}: {text}")
    return exc


def complete_frame(args: argparse.Namespace, model, image, where: dict[str, str], with_std: bool, **inputs):
    """One frame through :func:`crfdepth.api.complete_depth` (one-frame, point-cloud and bag modes; folder mode
    calls its batched form, :func:`complete_batch_with_cli_advice`); errors name ``where``'s flags. Returns
    float64 numpy (H, W) depth and std (None without ``with_std``), metres.

    A frame too large for the memory (refused up front, or an allocator failure in the forward) is an
    InputError naming the image's flag with the CLI's fix. Outside the bag mode and without ``--quiet``, a
    frame expected to take or taking more than a few seconds gets a status line of the model's stages on
    stderr when it is a terminal or with ``--verbose`` (:mod:`crfdepth.cli.progress`).
    """
    bag = getattr(args, "bag", None) is not None
    show = not getattr(args, "quiet", False) and not bag and (sys.stderr.isatty() or getattr(args, "verbose", False))
    height, width = np.shape(image)[:2]
    progress = FrameProgress(height, width, torch.device(args.device).type, enabled=show)
    hook = model.progress if isinstance(model, CRFDepth) else None
    if isinstance(model, CRFDepth) and show:
        model.progress = progress.stage
    try:
        with progress:
            depth, std = api.complete_depth(image, model=model, device=args.device, return_std=with_std,
                                            trust_transform=args.trust_transform, **inputs)
    except MemoryRefusal as exc:
        raise exc.retold(where.get("image", "image"), cli_advice(args.device)) from None
    except InputError as exc:
        raise flag_names(exc, where) from None
    finally:
        if isinstance(model, CRFDepth):
            model.progress = hook
    as_numpy = (lambda a: a.double().cpu().numpy()) if isinstance(depth, torch.Tensor) else \
        (lambda a: a.astype(np.float64))
    return as_numpy(depth), (None if std is None else as_numpy(std))


def write_frame(depth: np.ndarray, std: np.ndarray | None, out: Path, out_std: Path | None,
                vis_dir: Path | None, stem: str, vis_range) -> list[Path]:
    """A frame's depth PNG (and std PNG, and pictures into ``vis_dir``), each written atomically; returns the paths.
    PNG values are clipped below at 1/256 m so that no pixel reads as "no value"."""
    if not np.all(np.isfinite(depth)):
        raise InputError(f"{stem}: the model returned {int(np.sum(~np.isfinite(depth)))} non-finite "
                         f"depth value(s); nothing written")
    write_depth_png(out, np.maximum(depth, _MIN_DEPTH))
    written = [out]
    if out_std is not None:
        write_depth_png(out_std, np.maximum(np.nan_to_num(std, nan=_MIN_DEPTH), _MIN_DEPTH))
        written.append(out_std)
    if vis_dir is not None:
        written += write_pictures(vis_dir, stem, depth, std, vis_range)
    return written


# --------------------------------------------------------------------------- runs over many frames


SKIPPED_CSV = "skipped.csv"  # --skip-bad: the frames left out and why (folder and bag modes)
# How many bad frames the error of a run without --skip-bad lists (the first line names the first one).
LISTED_BAD = 20


def write_skipped(out_dir: Path, skipped: list[tuple[str, str]]) -> Path | None:
    """``<out-dir>/skipped.csv`` (columns ``frame``, ``reason``) of the frames ``--skip-bad`` left out,
    written atomically; with none, a ``skipped.csv`` of an earlier run is removed, so that the folder
    describes this run. Returns the file written, or None."""
    path = out_dir / SKIPPED_CSV
    if not skipped:
        path.unlink(missing_ok=True)
        return None
    text = io.StringIO()
    writer = csv.writer(text, lineterminator="\n")
    writer.writerow(("frame", "reason"))
    writer.writerows(skipped)
    atomic_write_bytes(path, text.getvalue().encode())
    return path


def skipped_frames(bad: list[tuple[int, type[BaseException], str]], total: int, what: str,
                   skip_bad: bool) -> dict[int, str]:
    """The frames a run over ``total`` frames leaves out, ``{index: message}``, after its check pass found
    ``bad`` ones (index, exception type, message naming the frame); ``what`` names the source
    (``--input-dir DIR``, ``--bag FILE``).

    Raises, so that nothing is written: without ``skip_bad``, the first bad frame's exception with the
    count on its first line and the further bad frames below it (up to ``LISTED_BAD`` in all); with it,
    an InputError when every frame is bad.
    """
    if bad and not skip_bad:
        _, error, first = bad[0]
        more = "" if len(bad) == 1 else ", listed below"
        lines = [f"{first} [{len(bad)} of {total} frame(s) of {what} bad{more}; nothing written; fix them, or give "
                 f"--skip-bad to complete the others]"]
        lines += [f"  {message}" for _, _, message in bad[1:LISTED_BAD]]
        if len(bad) > LISTED_BAD:
            lines.append(f"  ... and {len(bad) - LISTED_BAD} more")
        raise error("\n".join(lines))
    if bad and len(bad) == total:
        raise InputError(f"--skip-bad: all {total} {'paired ' if what.startswith('--bag') else ''}frame(s) of {what} "
                         f"are bad (the first: {bad[0][2]}); nothing written")
    return {index: message for index, _, message in bad}


# --------------------------------------------------------------------------- batched frames


def add_batch_arguments(group: argparse._ActionsContainer) -> None:
    """``--batch-size B`` and ``--workers N`` (read by :func:`frame_batches`), shared by
    ``complete --input-dir`` and ``evaluate``."""
    group.add_argument("--batch-size", type=int_at_least(1), default=1, metavar="B",
                       help="frames per model call (default 1, the fastest on CPU as measured; batches are "
                            "meant for --device cuda); consecutive frames of the same size go together, a size "
                            "change starts a new batch. Each frame's solve stops when it has converged, so "
                            "depths differ from batch 1 by the solver tolerance only (measured: at most 1/256 m, "
                            "one unit of a depth PNG)")
    group.add_argument("--workers", type=int_at_least(0, MAX_WORKERS), default=0, metavar="N",
                       help=f"processes that read and check frames ahead of the model (DataLoader "
                            f"num_workers, 0 to {MAX_WORKERS}; default 0: this process, enough for local KITTI "
                            f"frames, which read in about 20 ms; more help when reading is slow, e.g. from "
                            f"network storage)")


def check_sample(sample: Sample) -> None:
    """Refuse a frame that :func:`crfdepth.api.complete_depth` would refuse, with its checks and
    messages (:func:`crfdepth.api.check_frame`; names ``image``, ``sparse``, ``K``)."""
    api.check_frame(sample.image, sample.sparse, sample.K)


def complete_batch_with_cli_advice(model: CRFDepth, batch: Batch, return_std: bool
                                   ) -> tuple[torch.Tensor, torch.Tensor | None]:
    """:func:`crfdepth.api.complete_batch` of a batch of frames checked by :func:`check_sample`, on the
    model's device: (B, H, W) float32 depth and std (None without ``return_std``), metres. A memory refusal
    advises the CLI's options."""
    device = next(model.parameters()).device
    try:
        return api.complete_batch(batch.image, batch.sparse, batch.K, model=model, device=device,
                                  return_std=return_std)
    except MemoryRefusal as exc:
        raise exc.retold("image", cli_advice(device.type, len(batch))) from None


@dataclass(frozen=True)
class _Failure:
    """A frame that could not be read or checked: its exception's type and one-line message.

    Returned by the workers instead of raising: DataLoader re-raises a worker's exception
    with the worker's traceback in its message.
    """

    error: type[BaseException]
    message: str


class _CheckedFrames(Dataset):
    """The frames of ``dataset``, each passed through ``check(sample, index)``; picklable
    (workers started by spawn or forkserver receive it pickled) when both are. With
    ``keep=False`` a frame that passes gives None instead of the sample (:func:`bad_frames`:
    nothing is sent back from the workers, nothing held)."""

    def __init__(self, dataset: Dataset, check: Callable[[Sample, int], None], keep: bool = True) -> None:
        self.dataset, self.check, self.keep = dataset, check, keep

    def __len__(self) -> int:
        return len(self.dataset)

    def __getitem__(self, index: int) -> Sample | _Failure | None:
        try:
            sample = self.dataset[index]
            self.check(sample, index)
        except BAD_INPUT as exc:
            return _Failure(type(exc), str(exc))
        return sample if self.keep else None


def _check_any(sample: Sample, index: int) -> None:
    """The default check of :func:`frame_batches`: :func:`check_sample`."""
    check_sample(sample)


def _as_is(item):
    """``collate_fn`` of the one-frame loader: no conversion (batches are formed afterwards)."""
    return item


def bad_frames(dataset: Dataset, workers: int, check: Callable[[Sample, int], None] = _check_any,
               progress: Callable[[int], None] | None = None) -> list[tuple[int, type[BaseException], str]]:
    """Read and check every frame of ``dataset`` (``workers`` DataLoader processes, as :func:`frame_batches`)
    without keeping any: ``(index, exception type, one-line message)`` of each frame that fails (``BAD_INPUT``),
    in order. ``progress(i)`` is called after frame ``i``. The first pass of ``complete --input-dir``, so that a
    bad frame is found before anything is written; it costs one extra read of each frame (measured: 23-56 ms
    for a 1216x352 KITTI frame on a 2-core machine, under 10% of its completion; docs/design.md section 10)."""
    loader = DataLoader(_CheckedFrames(dataset, check, keep=False), batch_size=None, shuffle=False,
                        num_workers=workers, collate_fn=_as_is)
    bad = []
    for index, item in enumerate(loader):
        if isinstance(item, _Failure):
            bad.append((index, item.error, item.message))
        if progress is not None:
            progress(index)
    return bad


def frame_batches(dataset: Dataset, batch_size: int, workers: int,
                  check: Callable[[Sample, int], None] = _check_any) -> Iterator[Batch]:
    """The frames of ``dataset`` in order, as :class:`~crfdepth.data.sample.Batch` es of up
    to ``batch_size`` consecutive frames of one size (a size change starts a new batch).

    ``workers`` DataLoader processes (0: this process) read each frame and run ``check``
    on it (default :func:`check_sample`). A frame that fails (``BAD_INPUT``) ends the
    iteration: the frames before it are yielded first, then its exception is raised with
    the type and message it had where it was read, so the error reads the same for any
    ``workers`` and ``batch_size``. Results do not depend on how the frames are batched
    beyond :func:`complete_batch_with_cli_advice`'s solver tolerance.
    """
    loader = DataLoader(_CheckedFrames(dataset, check), batch_size=None, shuffle=False, num_workers=workers,
                        collate_fn=_as_is)
    pending: list[Sample] = []
    for item in loader:
        if isinstance(item, _Failure):
            if pending:
                yield collate_samples(pending)
            raise item.error(item.message)
        if pending and item.size != pending[0].size:
            yield collate_samples(pending)
            pending = []
        pending.append(item)
        if len(pending) == batch_size:
            yield collate_samples(pending)
            pending = []
    if pending:
        yield collate_samples(pending)
