"""``crfdepth project``: a Velodyne scan to a sparse KITTI depth PNG (docs/design.md section 1).

Example::

    crfdepth project --velodyne 0000000005.bin --calib raw/2011_09_26 \\
        --image image_02/data/0000000005.png --out sparse.png --keep-every-ring 4

Order of the checks, so that bad input fails at once and never leaves a file behind:
the options at parse time (``--keep-every-ring`` an integer >= 1, ``--keep-fraction`` a
number in (0, 1]); then ``--out`` (a ``.png`` name whose folder exists and accepts a new
file, not one of the inputs) before any input is read; then the inputs, each error
naming its flag (``--velodyne``, ``--calib``, ``--image``; a ``.pcd`` / ``.ply`` / ``.npy``
cloud or a rig YAML/JSON is pointed to ``crfdepth complete --points --calib``), the
calibration's transforms (rigid, the same check as ``complete``'s:
:func:`crfdepth.checks.check_rigid` in :mod:`crfdepth.io.calibration`'s readers) and K
against the image size (:func:`crfdepth.intrinsics.check_intrinsics`, field of view included). The scan is
read and checked by :func:`crfdepth.io.kitti.read_velodyne`, the reader of ``crfdepth complete --points
X.bin`` too (empty, truncated, float64 or N x 3 float32 files, non-finite values and coordinates not in
metres are refused). The projected map is refused, naming ``--velodyne``, when no point lands in the
image, when a depth lies below 1 mm or beyond 1000 m (:func:`crfdepth.checks.check_return_depths`) and
when a depth exceeds what a KITTI PNG holds (255.996 m: :func:`crfdepth.io.kitti.check_png_depth`),
never clipped. The PNG is written atomically and one line says what was written (``--quiet`` drops it).
"""

from __future__ import annotations

import argparse
import logging
import os
from pathlib import Path

import numpy as np

from crfdepth.checks import check_return_depths
from crfdepth.cli.arguments import MAX_RINGS, fraction, int_at_least, seed_type
from crfdepth.errors import InputError
from crfdepth.geometry.projection import keep_every_ring, keep_fraction, project_velodyne
from crfdepth.inputs import no_points_message
from crfdepth.intrinsics import check_intrinsics
from crfdepth.io.calibration import RIG_SUFFIXES, RigCalibration, is_rig_file, load_calibration
from crfdepth.io.files import check_output_file
from crfdepth.io.kitti import check_png_depth, read_rgb, read_velodyne, write_depth_png

logger = logging.getLogger(__name__)


HELP = "project a Velodyne scan into a camera as a sparse depth PNG"
DESCRIPTION = ("Project a KITTI Velodyne scan into a camera image and write the sparse "
               "z-depth map as a KITTI depth PNG (uint16, metres * 256, 0 = no point); "
               "the nearest point wins where several land on one pixel.")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """The options of ``crfdepth project``."""
    parser.add_argument("--velodyne", required=True, metavar="X.bin",
                        help="Velodyne scan (N x 4 float32), in the sensor's scan order")
    parser.add_argument("--calib", required=True, metavar="CALIB",
                        help="object-benchmark calibration file, or a raw-data day folder "
                             "holding calib_cam_to_cam.txt and calib_velo_to_cam.txt")
    parser.add_argument("--image", required=True, metavar="IMG.png",
                        help="the camera image; only its size is used")
    parser.add_argument("--out", required=True, metavar="SPARSE.png",
                        help="output depth PNG (its folder must exist)")
    parser.add_argument("--camera", type=int, default=2, choices=(0, 1, 2, 3),
                        help="KITTI camera index (default: 2, left colour)")
    parser.add_argument("--keep-every-ring", type=int_at_least(1, MAX_RINGS, meaning="keep one laser ring in K"), default=None, metavar="K",
                        help="keep one laser ring in K (rings recovered from the scan order)")
    parser.add_argument("--keep-fraction", type=fraction(include_one=True, meaning="the share of points kept"), default=None, metavar="F",
                        help="keep a random fraction F in (0, 1] of the points")
    parser.add_argument("--seed", type=seed_type(), default=None, metavar="S",
                        help="seed of --keep-fraction (default: 0)")
    parser.add_argument("--quiet", action="store_true",
                        help="do not print the line saying what was written")


def _check_out(args: argparse.Namespace) -> Path:
    """``--out``, checked before any input is read: a .png name, creatable, not an input."""
    out = check_output_file(args.out, "--out", suffix=".png")
    for flag in ("--velodyne", "--calib", "--image"):
        source = getattr(args, flag[2:])
        if os.path.realpath(source) == os.path.realpath(out):
            raise InputError(f"--out: expected a new file, got {out}, the {flag} input; refusing to overwrite it")
    return out


def _named(flag: str, prefix: str, exc: Exception) -> Exception:
    """``exc`` with its message led by ``flag`` instead of the reader's own ``prefix:``."""
    message = str(exc)
    if message.startswith(f"{prefix}: "):
        message = message[len(prefix) + 2:]
    return type(exc)(f"{flag}: {message}")


# Inputs of ``crfdepth complete --points ... --calib ...`` that this command does not read.
_CLOUD_SUFFIXES = (".pcd", ".ply", ".npy")


def _check_kitti_inputs(args: argparse.Namespace) -> None:
    """A point-cloud file or a rig calibration given to this KITTI-only command: point to the
    command that reads them, before any reader fails on them with a less useful message."""
    suffix = Path(args.velodyne).suffix.lower()
    if suffix in _CLOUD_SUFFIXES:
        raise InputError(f"--velodyne: expected a KITTI Velodyne scan (.bin, N x 4 float32), got a {suffix} point "
                         f"cloud {args.velodyne}; for other point clouds and rig calibrations use crfdepth complete "
                         f"--points CLOUD --calib CALIB")
    if Path(args.calib).suffix.lower() in RIG_SUFFIXES or is_rig_file(args.calib):
        raise InputError(f"--calib: expected a KITTI calibration (object-benchmark file or raw-data day folder), got "
                         f"a rig calibration {args.calib}; for a rig calibration (K, T_cam_lidar) use crfdepth "
                         f"complete --points CLOUD --calib {args.calib}")


def run(args: argparse.Namespace) -> int:
    """Project ``args.velodyne`` into ``args.image``'s camera and write ``args.out``.

    Ring subsampling (on the full scan, whose order defines the rings) comes before the
    random fraction. Returns 0; bad input raises InputError / FileNotFoundError /
    PermissionError naming the flag, which ``crfdepth.cli.main`` turns into exit status 2
    with nothing written.
    """
    out = _check_out(args)
    _check_kitti_inputs(args)
    if args.seed is not None and args.keep_fraction is None:
        logger.warning("--seed is ignored without --keep-fraction (it seeds the random choice of the points kept)")
    try:
        points = read_velodyne(args.velodyne)
    except (InputError, FileNotFoundError, IsADirectoryError) as exc:
        raise _named("--velodyne", "velodyne", exc) from None
    try:
        calib = load_calibration(args.calib, camera=args.camera)
    except (InputError, FileNotFoundError, IsADirectoryError) as exc:
        raise _named("--calib", "calibration", exc) from None
    try:
        height, width = read_rgb(args.image).shape[:2]
    except (InputError, FileNotFoundError, IsADirectoryError) as exc:
        raise _named("--image", "image", exc) from None
    check_intrinsics(calib.K, "--calib", (height, width))
    if calib.image_size is not None and calib.image_size != (height, width):
        logger.warning("--image %s is %dx%d but --calib says %dx%d; using the image's size",
                       args.image, width, height, calib.image_size[1], calib.image_size[0])

    total = points.shape[0]
    if args.keep_every_ring is not None:
        points = keep_every_ring(points, args.keep_every_ring)
    if args.keep_fraction is not None:
        points = keep_fraction(points, args.keep_fraction, seed=0 if args.seed is None else args.seed)
    if points.shape[0] == 0 and total:
        raise InputError("--keep-every-ring / --keep-fraction: expected to keep some of the scan's points, got 0 "
                         "of them; use a smaller --keep-every-ring or a larger --keep-fraction")

    depth = project_velodyne(points, calib, (height, width))
    if not np.any(depth > 0):
        rig = RigCalibration.from_kitti(calib, source=str(args.calib))
        raise InputError(f"--velodyne: {no_points_message(points[:, :3], rig, depth.shape)}")
    check_return_depths("--velodyne", depth)
    check_png_depth("--velodyne", depth)
    write_depth_png(out, depth)
    pixels = int((depth > 0).sum())
    logger.info("kept %d of %d points", points.shape[0], total)
    if not args.quiet:
        print(f"wrote {out}: {pixels} LiDAR pixels, {height}x{width}")
    return 0
