"""``crfdepth targets``: camera-view depth targets from a KITTI raw drive or a ROS bag (docs/design.md section 14).

The options and the choice between the two inputs: ``--drive`` (:mod:`crfdepth.cli.targets_drive`)
accumulates the scans ``t - k .. t + k`` of a KITTI raw drive into each frame's camera and
writes the targets under ``--out-dir`` in KITTI's depth-completion layout; ``--bag``
(:mod:`crfdepth.cli.targets_bag`) writes the bag's frames as a KITTI raw drive
``OUT/<date>/<bag name>_sync`` and then runs the drive code path on it, into ``OUT``. ``--rerun FILE.rrd``
records both (:func:`crfdepth.cli.outputs.rerun_recording`, checked before anything is read).
"""

from __future__ import annotations

import argparse

from crfdepth.cli import targets_bag, targets_drive
from crfdepth.cli.arguments import add_rerun_argument, int_at_least
from crfdepth.cli.outputs import rerun_recording
from crfdepth.errors import InputError

__all__ = ["DESCRIPTION", "HELP", "add_arguments", "parse_frames", "run"]


# --------------------------------------------------------------------------- arguments


def parse_frames(text: str) -> tuple[int, int]:
    """``--frames A:B``: two frame numbers, A <= B, both included."""
    head, sep, tail = text.partition(":")
    try:
        first, last = int(head), int(tail)
    except ValueError:
        first, last = -1, -1
    if not sep or first < 0 or last < first:
        raise argparse.ArgumentTypeError(f"expected A:B, two frame numbers with 0 <= A <= B (both included), "
                                         f"got {text!r}")
    return first, last


HELP = "camera-view depth targets from a KITTI raw drive or a ROS bag (registered scans, what the camera sees)"
DESCRIPTION = ("Accumulate the LiDAR scans t-k..t+k of a KITTI raw drive or a ROS bag (--bag: its frames are "
               "first written as a KITTI raw drive OUT/<date>/<bag name>_sync) into each frame's camera, keep only "
               "the returns the camera sees (returns of moving objects and occluded returns dropped, the "
               "frame's own scan first), and write KITTI depth PNGs (proj_depth/groundtruth), a per-pixel "
               "count of the scans that agree (proj_depth/support), the poses used and an index CSV.")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """The options of ``crfdepth targets``."""
    parser.add_argument("--drive", metavar="DIR",
                        help="KITTI raw drive folder (<day>/<drive>_sync with velodyne_points/data/*.bin and "
                             "image_0X/data/*.png); the calibration is read from the day folder above it. Give "
                             "--drive or --bag")
    parser.add_argument("--camera", type=int, choices=(2, 3), default=2, help="colour camera (default: 2, left)")
    parser.add_argument("--frames", type=parse_frames, default=None, metavar="A:B",
                        help="only frames A to B (both included; the windows still use the scans around them); "
                             "default: every frame of the drive, whose frame numbers must then be consecutive")
    parser.add_argument("-k", "--window", type=int_at_least(0), default=5, metavar="K",
                        help="scans on each side of a frame to accumulate (default 5; 0: the frame's own scan, "
                             "cleaned of what the camera cannot see)")
    parser.add_argument("--poses", default="auto", metavar="auto|tf|odometry|oxts|FILE",
                        help="auto (default): the drive's oxts/data (GPS/IMU) when present, a bag's odometry on /tf "
                             "when present, else LiDAR odometry; odometry: KISS-ICP over the scans the run uses "
                             "(pip install \"crfdepth[odometry]\"), a failed step is an error naming the frame; oxts "
                             "(a drive); tf (a bag: the transform from the top of the LiDAR frame's tf tree, e.g. "
                             "odom or map, to the LiDAR); or a KITTI odometry poses.txt (camera-0 poses, one line "
                             "per frame of the drive, or per paired frame of the bag)")
    parser.add_argument("--out-dir", metavar="OUT", required=True,
                        help="output folder (created if missing): OUT/<drive>/proj_depth/{groundtruth,support}/"
                             "image_0X/<frame>.png, OUT/<drive>/poses.txt, OUT/<drive>/index_image_0X.csv; with "
                             "--bag also the frames as a KITTI raw drive OUT/<date>/<bag name>_sync, so that "
                             "layout \"sequence\" reads OUT as both root and targets_root")
    parser.add_argument("--vis", nargs="?", const="", default=None, metavar="DIR",
                        help="also write a picture per frame, <drive>_image_0X_<frame>.png, into DIR (created if "
                             "missing; without DIR: <out-dir>_vis): the targets coloured by depth, dropped returns "
                             "by reason (occluded: magenta, moved: white)")
    parser.add_argument("--stereo-check", action="store_true",
                        help="--drive with both colour cameras: drop the target returns the stereo pair contradicts "
                             "(crfdepth.sequences.stereo; counted in index_image_0X.csv's stereo_dropped)")
    parser.add_argument("--quiet", action="store_true", help="no progress bar and no summary line")
    add_rerun_argument(parser, "the camera at its pose, its trajectory, the image, the frame's scan and its targets")
    targets_bag.add_arguments(parser)
    # the output-folder checks it shares with complete's folder and bag modes read --out-std-dir
    parser.set_defaults(out_std_dir=None)


def run(args: argparse.Namespace) -> int:
    """Write the targets of ``--drive`` or ``--bag`` as ``args`` asks; returns 0."""
    if (args.drive is None) == (args.bag is None):
        raise InputError(f"--drive / --bag: expected one of them (a KITTI raw drive folder or a ROS bag), got "
                         f"{'neither' if args.drive is None else 'both'}")
    if args.bag is not None and args.stereo_check:
        raise InputError("--stereo-check: expected a KITTI raw drive with both colour cameras (--drive), got a "
                         "bag (one camera)")
    if args.bag is None:
        targets_bag.check_drive_flags(args)
    with rerun_recording(args) as args.recorder:  # checked now, written when the run ends
        return targets_bag.run_bag(args) if args.bag is not None else targets_drive.run_drive(args)
