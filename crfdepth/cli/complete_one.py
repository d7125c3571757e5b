"""``crfdepth complete`` for one frame: ``--image`` with ``--sparse`` + ``--intrinsics``, or with ``--points``
+ ``--calib`` (see :mod:`crfdepth.cli.complete`): :func:`read_one` checks the outputs and reads the inputs,
``crfdepth.cli.complete.run`` completes the frame with :func:`crfdepth.api.complete_depth` and :func:`write_one`
writes it (docs/design.md section 8: the frame reaches the CG loop in 8 calls)."""

from __future__ import annotations

import argparse
import contextlib
import itertools
import logging
import os
import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from crfdepth.cli.completion import cli_advice
from crfdepth.cli.decoder_noise import quiet_decoders
from crfdepth.cli.file_errors import flagged
from crfdepth.cli.model_options import build_model
from crfdepth.errors import InputError
from crfdepth.io.calibration import load_any_calibration
from crfdepth.io.files import check_output_file
from crfdepth.io.kitti import read_depth_png, read_intrinsics, read_rgb
from crfdepth.io.pointcloud import read_points
from crfdepth.memory import check_image_file
from crfdepth.model import CRFDepth
from crfdepth.runs.outputs import check_output_folder, make_output_dir, same_file, write_frame

logger = logging.getLogger("crfdepth.cli.complete")  # the command's logger, whichever mode runs

__all__ = ["OneFrame", "check_outputs", "read_one", "write_one"]


@dataclass
class OneFrame:
    """One frame read and checked for :func:`crfdepth.api.complete_depth`: the (H, W, 3) uint8 RGB ``rgb``, the
    keyword ``inputs`` (``sparse`` in metres and ``K``, or ``points`` and ``calibration``), the model, where each
    argument came from (``where``: the API's names -> the user's flags), the ``--sparse-units`` it was read in
    (None: points), the checked outputs, and the time the completion started (``start``, seconds)."""

    rgb: np.ndarray
    inputs: dict
    model: CRFDepth
    where: dict[str, str]
    units: str | None
    out: Path
    out_std: Path | None
    start: float = 0.0


def check_outputs(args, inputs: dict[str, Path]) -> tuple[Path, Path | None]:
    """``--out`` / ``--out-std`` / ``--vis`` / ``--rerun`` checked before anything is read: PNG names in writable
    folders, none an input, no two naming the same file (the pictures of ``--vis`` included)."""
    with flagged("--out", args.out, "write"):  # a name too long, a path through a file ...
        out = check_output_file(args.out, "--out", suffix=".png")
    out_std = None
    if args.out_std is not None:
        with flagged("--out-std", args.out_std, "write"):
            out_std = check_output_file(args.out_std, "--out-std", suffix=".png")
    if out_std is not None and same_file(out, out_std):
        raise InputError(f"--out-std: must differ from --out, got {out_std} for both")
    for flag, path in ((f, p) for f, p in (("--out", out), ("--out-std", out_std)) if p is not None):
        for source, src_path in inputs.items():
            if same_file(path, src_path):
                raise InputError(f"{flag}: {path} is the {source} input; refusing to overwrite it")
    written = {"--out": out, "--out-std": out_std}
    if args.vis:  # created once the frame is completed; a folder that cannot be is refused now
        for flag, path in (*written.items(), *inputs.items()):
            if path is not None and same_file(args.vis, path):
                raise InputError(f"--vis: expected a folder for the pictures, got {args.vis}, the {flag} file")
        check_output_folder(args.vis, "--vis")
    if args.vis is not None:
        folder = Path(args.vis) if args.vis else out.parent
        for kind in ("depth", "std"):
            written[f"--vis ({kind} picture)"] = folder / f"{out.stem}_vis_{kind}.png"
    if args.rerun:
        written["--rerun"] = Path(args.rerun)
    outputs = [(f, p) for f, p in written.items() if p is not None]
    for (flag, path), (other, other_path) in [*itertools.product(inputs.items(), outputs),
                                              *itertools.combinations(outputs, 2)]:
        if same_file(path, other_path):
            raise InputError(f"{other}: {other_path} is also the {flag} {'input' if flag in inputs else 'output'}; "
                             f"expected different files")
    return out, out_std


def read_one(args: argparse.Namespace) -> OneFrame:
    """One frame's outputs checked and inputs read and checked: ``--image`` with ``--sparse`` + ``--intrinsics``,
    or with ``--points`` + ``--calib``; then the model built."""
    points_mode = args.points is not None or args.calib is not None
    needed = ("--image", "--points", "--calib", "--out") if points_mode else ("--image", "--sparse", "--intrinsics",
                                                                              "--out")
    given = {"--image": args.image, "--sparse": args.sparse, "--intrinsics": args.intrinsics, "--points": args.points,
             "--calib": args.calib, "--out": args.out, "--out-dir": args.out_dir, "--out-std-dir": args.out_std_dir,
             "--batch-size": None if args.batch_size == 1 else args.batch_size,  # given other than the default
             "--workers": None if args.workers == 0 else args.workers}
    missing = [flag for flag in needed if given[flag] is None]
    if not points_mode and args.sparse is None and args.intrinsics is None:  # no LiDAR at all: both ways
        absent = [flag for flag in ("--image", "--out") if given[flag] is None] + ["the LiDAR"]
        raise InputError(f"one frame needs --image, --out and its LiDAR: --sparse DEPTH.png with --intrinsics K.txt, or "
                         f"--points CLOUD with --calib RIG.yaml (an RGB-D camera's depth image: --depth DEPTH.png "
                         f"with --intrinsics or --known-camera; many frames: --input-dir, --input-list or --bag); "
                         f"missing {', '.join(absent)}")
    if missing:
        mode = "point-cloud mode" if points_mode else "one-frame mode"
        raise InputError(f"{mode} needs {', '.join(needed[:-1])} and --out; missing {', '.join(missing)}")
    given["--sparse-units"] = args.sparse_units
    folder_flags = ("--out-dir", "--out-std-dir", "--batch-size", "--workers")
    stray_flags = ("--sparse", "--sparse-units", "--intrinsics", *folder_flags) if points_mode else folder_flags
    stray = [flag for flag in stray_flags if given[flag] is not None]
    if stray and points_mode:
        raise InputError(f"{', '.join(stray)}: cannot be combined with --points/--calib (the cloud and the "
                         f"calibration replace --sparse and --intrinsics; one frame only)")
    if stray:
        raise InputError(f"{', '.join(stray)}: folder options need --input-dir; for one frame use --out / --out-std")
    out, out_std = check_outputs(args, {flag: Path(given[flag]) for flag in needed[:-1]})
    # each file read under its flag (a reader's label, an OS error: the flag), decoders' C warnings held back
    with flagged("--image", args.image, labels=("image",)), quiet_decoders():
        check_image_file(args.image, f"--image {args.image}", device=args.device, dtype=args.dtype, mode=args.mode,
                         return_std=out_std is not None or args.vis is not None, advice=cli_advice(args.device))
        rgb = read_rgb(args.image)
    if points_mode:
        with flagged("--points", args.points, labels=("points",)):
            points = read_points(args.points)
        with flagged("--calib", args.calib, labels=("calibration",)):
            calibration = load_any_calibration(args.calib, camera=args.camera)
        inputs = dict(points=points, calibration=calibration)
        where = {"points": f"--points {args.points}", "calibration": f"--calib {args.calib}",
                 "K": f"--calib {args.calib}", "T_cam_lidar": f"--calib {args.calib}", "image": f"--image {args.image}",
                 f"K ({calibration.source})": f"--calib {args.calib}",
                 f"T_cam_lidar ({calibration.source})": f"--calib {args.calib}",
                 "*": f"--points {args.points} with --calib {args.calib}"}
    else:
        units = args.sparse_units or "kitti"
        with flagged("--sparse", args.sparse, labels=("depth png",)), quiet_decoders():
            sparse = read_depth_png(args.sparse, units=units)
        with flagged("--intrinsics", args.intrinsics, labels=("intrinsics",)):
            K = read_intrinsics(args.intrinsics)
        if rgb.shape[:2] != sparse.shape:
            raise InputError(f"--image: expected the size of --sparse, {sparse.shape[0]}x{sparse.shape[1]} (HxW), got "
                             f"{rgb.shape[0]}x{rgb.shape[1]}: image and sparse sizes differ (--image {args.image}, "
                             f"--sparse {args.sparse})")
        # an explicit --sparse-units overrules the guess about the rig (a camera more than 4 m up)
        inputs = dict(sparse=sparse, K=K, trust_units=args.sparse_units is not None)
        where = {"sparse": f"--sparse {args.sparse}", "K": f"--intrinsics {args.intrinsics}",
                 "image": f"--image {args.image}"}
    if np.array_equal(rgb[..., 0], rgb[..., 1]) and np.array_equal(rgb[..., 1], rgb[..., 2]):
        logger.warning("--image %s is greyscale; the colour potential sees intensity only", args.image)
    model = build_model(args)
    return OneFrame(rgb, inputs, model, where, None if points_mode else units, out, out_std, time.perf_counter())


@contextlib.contextmanager
def vis_folder(args: argparse.Namespace, out: Path) -> Iterator[Path | None]:
    """The folder of one frame's ``--vis`` pictures (None without ``--vis``; ``--vis`` alone: beside ``out``),
    made only now that the frame is completed; a folder this made is removed again, empty, if the writes in
    the ``with`` block fail."""
    vis_dir, created = None, False
    if args.vis is not None:
        created = bool(args.vis) and not os.path.isdir(args.vis)
        vis_dir = make_output_dir(args.vis, "--vis") if args.vis else out.parent
    try:
        yield vis_dir
    except BaseException:
        if created:
            with contextlib.suppress(OSError):
                vis_dir.rmdir()  # the --vis folder this run created, empty again
        raise


def write_one(args: argparse.Namespace, frame: OneFrame, depth: np.ndarray, std: np.ndarray | None) -> int:
    """The frame's files written (depth, std, pictures: all or none), logged with ``--rerun``; returns 0."""
    rgb, out, out_std = frame.rgb, frame.out, frame.out_std
    with vis_folder(args, out) as vis_dir:
        written = write_frame(depth, std, out, out_std, vis_dir, out.stem, args.vis_range)  # all files, or none
    if args.recorder is not None:  # --rerun
        lidar = {key: frame.inputs[key] for key in ("points", "calibration", "sparse", "K") if key in frame.inputs}
        args.recorder.complete_frame(rgb, depth, std, **lidar)
    if not args.quiet:
        spread = "" if std is None else f", std {float(std.min()):.2f}-{float(std.max()):.2f} m"
        print(f"wrote {', '.join(str(p) for p in written)}: {depth.shape[1]}x{depth.shape[0]} depth, "
              f"{float(depth.min()):.2f}-{float(depth.max()):.2f} m{spread}, in {time.perf_counter() - frame.start:.1f} s")
    return 0
