"""``crfdepth targets``: camera-view depth targets from a KITTI raw drive or a ROS bag (docs/design.md section 14).

::

    crfdepth targets (--drive DIR | --bag RUN.bag) --out-dir OUT [-k K] [--frames A:B]
        [--poses auto|tf|odometry|oxts|FILE] [--camera 2|3] [--stereo-check] [--vis [DIR]] [--rerun FILE.rrd]
        [--image-topic T] [--points-topic T] [--camera-info-topic T] [--calib FILE] [--max-dt S]

The options, read and handed to :func:`crfdepth.sequences.make_targets`, which does the work: ``--drive``
accumulates the scans ``t - k .. t + k`` of a KITTI raw drive into each frame's camera and writes the targets under
``--out-dir`` in KITTI's depth-completion layout; ``--bag`` first writes the bag's frames as a KITTI raw drive
``OUT/<date>/<bag name>_sync`` (:mod:`crfdepth.sequences.bag_drive`). The command checks the options first, then
``--rerun FILE.rrd`` (:func:`crfdepth.cli.outputs.rerun_recording`) and the output folders (created and locked for
the run), and draws the ``--vis`` pictures with :func:`crfdepth.pictures.figures.targets_picture`; it shows a
progress bar and prints a summary line.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from tqdm import tqdm

from crfdepth.cli.arguments import MAX_COUNT, add_rerun_argument, add_topic_arguments, int_at_least, positive_number
from crfdepth.cli.outputs import check_output_folders, output_folders, rerun_recording
from crfdepth.io.ros.frames import DEFAULT_MAX_DT_S
from crfdepth.pictures.figures import targets_picture
from crfdepth.sequences import DriveTargets, make_targets
from crfdepth.sequences.recording_targets import check_targets_options

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
    if last > MAX_COUNT:
        raise argparse.ArgumentTypeError(f"expected A:B, frame numbers in [0, {MAX_COUNT}], got {text!r}")
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
    bag = parser.add_argument_group(
        "a ROS bag", "ROS 1 .bag or ROS 2 (sqlite3, mcap) recordings, needs pip install 'crfdepth[ros]'. The frames "
                     "are also written as a KITTI raw drive OUT/<date>/<bag name>_sync (+ the day calibration), the "
                     "targets to OUT/<bag name>_sync: layout \"sequence\" reads OUT as root and targets_root")
    add_topic_arguments(bag, only_one_default=True, points_aliases=("--cloud-topic",))
    bag.add_argument("--calib", metavar="FILE",
                     help="rig YAML/JSON or KITTI calibration: replaces the CameraInfo and the /tf LiDAR -> camera "
                          "transform")
    bag.add_argument("--max-dt", type=positive_number("seconds"), default=None, metavar="SECONDS",
                     help=f"largest time between an image and its cloud (default {DEFAULT_MAX_DT_S})")
    # the output-folder checks it shares with complete's folder and bag modes read --out-std-dir
    parser.set_defaults(out_std_dir=None)


class _Progress:
    """The progress bar of a drive's frames (none with ``--quiet`` or when stderr is not a terminal)."""

    def __init__(self, quiet: bool) -> None:
        self.quiet, self.bar = quiet, None

    def __call__(self, written: int, total: int) -> None:
        if self.bar is None:
            self.bar = tqdm(total=total, unit="frame", desc="targets", disable=self.quiet or not sys.stderr.isatty())
        else:
            self.bar.update(1)

    def close(self) -> None:
        if self.bar is not None:
            self.bar.close()


def _summary(args: argparse.Namespace, done: DriveTargets) -> str:
    ratio = f" ({done.density / done.scan_density:.2f}x)" if done.scan_density > 0 else ""
    densities = f"mean density {done.density:.4f} against {done.scan_density:.4f} for the single scan{ratio}"
    if args.bag is not None:
        return (f"wrote {done.frames} frame(s) of {args.bag} as the drive {done.drive} and their targets to "
                f"{done.out} (image_02, k={args.window}, poses: {done.source}): {densities}")
    return (f"wrote targets of {done.frames} frame(s) of {done.drive.name} ({done.camera}, k={args.window}, poses: "
            f"{done.source}) to {done.out}: {densities}, in {done.seconds:.1f} s")


def run(args: argparse.Namespace) -> int:
    """Write the targets of ``--drive`` or ``--bag`` as ``args`` asks (:func:`crfdepth.sequences.make_targets`);
    returns 0."""
    options = {"drive": args.drive, "bag": args.bag, "camera": args.camera, "frames": args.frames,
               "window": args.window, "poses": args.poses, "stereo_check": args.stereo_check,
               "image_topic": args.image_topic, "points_topic": args.points_topic,
               "camera_info_topic": args.camera_info_topic, "calib": args.calib, "max_dt": args.max_dt}
    check_targets_options(args.out_dir, vis_dir=args.vis or None, **options)
    with rerun_recording(args) as recorder:  # checked now, written when the run ends
        source = Path(args.drive if args.bag is None else args.bag)
        outputs = check_output_folders(args, [source], "the --bag input" if args.bag else f"the input drive {source}")
        progress = _Progress(args.quiet)
        try:
            with output_folders(outputs) as folders:
                done = make_targets(folders[0], vis_dir=folders[2] if args.vis is not None else None,
                                    picture=targets_picture, recorder=recorder, progress=progress, **options)
        finally:
            progress.close()
    if not args.quiet:
        print(_summary(args, done))
    return 0
