"""``crfdepth project``: a Velodyne scan to a sparse KITTI depth PNG (DESIGN.md section 1).

Example::

    crfdepth project --velodyne 0000000005.bin --calib raw/2011_09_26 \\
        --image image_02/data/0000000005.png --out sparse.png --keep-every-ring 4
"""

from __future__ import annotations

import argparse
import logging

from crfdepth.errors import InputError
from crfdepth.io.kitti import load_calibration, read_rgb, read_velodyne, write_depth_png
from crfdepth.projection import keep_every_ring, keep_fraction, project_velodyne

logger = logging.getLogger(__name__)


def add_parser(subparsers: argparse._SubParsersAction) -> argparse.ArgumentParser:
    """Register the ``project`` sub-command on ``subparsers`` (sets ``func=run``)."""
    parser = subparsers.add_parser(
        "project",
        help="project a Velodyne scan into a camera as a sparse depth PNG",
        description="Project a KITTI Velodyne scan into a camera image and write the sparse "
                    "z-depth map as a KITTI depth PNG (uint16, metres * 256, 0 = no point); "
                    "the nearest point wins where several land on one pixel.",
    )
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
    parser.add_argument("--keep-every-ring", type=int, default=None, metavar="K",
                        help="keep one laser ring in K (rings recovered from the scan order)")
    parser.add_argument("--keep-fraction", type=float, default=None, metavar="F",
                        help="keep a random fraction F in (0, 1] of the points")
    parser.add_argument("--seed", type=int, default=0, metavar="S",
                        help="seed of --keep-fraction (default: 0)")
    parser.set_defaults(func=run)
    return parser


def run(args: argparse.Namespace) -> int:
    """Project ``args.velodyne`` into ``args.image``'s camera and write ``args.out``.

    Ring subsampling (on the full scan, whose order defines the rings) comes before the
    random fraction. Returns 0; bad input raises InputError / FileNotFoundError, which
    ``crfdepth.cli.main`` turns into exit status 2 without writing ``args.out``.
    """
    points = read_velodyne(args.velodyne)
    calib = load_calibration(args.calib, camera=args.camera)
    height, width = read_rgb(args.image).shape[:2]
    if calib.image_size is not None and calib.image_size != (height, width):
        logger.warning("image %s is %dx%d but the calibration says %dx%d; using the image's size",
                       args.image, width, height, calib.image_size[1], calib.image_size[0])

    total = points.shape[0]
    if args.keep_every_ring is not None:
        points = keep_every_ring(points, args.keep_every_ring)
    if args.keep_fraction is not None:
        points = keep_fraction(points, args.keep_fraction, seed=args.seed)
    if points.shape[0] == 0 and total:
        raise InputError("subsampling: kept 0 of the scan's points; use a smaller --keep-every-ring "
                         "or a larger --keep-fraction")

    depth = project_velodyne(points, calib, (height, width))
    write_depth_png(args.out, depth)
    logger.info("kept %d of %d points; %d pixels with depth written to %s",
                points.shape[0], total, int((depth > 0).sum()), args.out)
    return 0
