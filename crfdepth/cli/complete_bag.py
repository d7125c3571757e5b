"""``crfdepth complete --bag``: a ROS 1 / ROS 2 recording in, one depth PNG per camera image out.

::

    crfdepth complete --bag RUN.bag --image-topic /cam/image_raw --points-topic /lidar/points \\
        --out-dir depth/ [--out-std-dir std/] [--out-bag RUN_depth.bag] [--max-dt 0.05] \\
        [--camera-info-topic /cam/camera_info] [--calib rig.yaml] [--rectified] [--vis [DIR]]

What is read (docs/design.md section 11; :mod:`crfdepth.io.ros`):

- images: ``sensor_msgs/Image`` (rgb8, bgr8, mono8, rgba8, bgra8, Bayer ``bayer_*8``,
  YUV 4:2:2) or ``sensor_msgs/CompressedImage`` (JPEG, PNG);
- the camera: ``sensor_msgs/CameraInfo`` from ``--camera-info-topic`` (default: the
  ``camera_info`` topic beside the image topic), the message nearest in record time to
  each image; an image topic whose last name contains ``rect`` (or ``--rectified``) is
  taken as rectified: ``P``'s intrinsics, no distortion;
- clouds: ``sensor_msgs/PointCloud2`` with float32 (or float64) x, y, z; NaN points are
  dropped and counted;
- the LiDAR -> camera transform: ``/tf_static`` and ``/tf`` from the cloud's
  ``frame_id`` to the image's, composed along the tree, at the image's time; ``--calib
  FILE`` (rig YAML/JSON or KITTI) replaces both the transform and the CameraInfo.

Each image is paired with the cloud nearest in ``header.stamp`` time when at most
``--max-dt`` seconds away (default 0.05 s: half a sweep of a 10 Hz LiDAR); others are
counted as unpaired. A paired frame goes through :func:`crfdepth.api.complete_depth`
with the image, the finite points and the calibration: the same call as ``complete
--points``. Written per frame: ``<out-dir>/<image stamp ns>.png`` (KITTI depth PNG), the
std PNG into ``--out-std-dir``, pictures with ``--vis``; at the end ``<out-dir>/index.csv``
(one row per frame: stamps, topics, time gap, points, points in view, files) and, with
``--out-bag``, a bag with the depth (and std) as ``32FC1`` images and their CameraInfo on
``<image namespace>/crfdepth/{depth,std,camera_info}``, with the images' headers.

Everything the run needs is checked before anything is written: topics and their types,
every image encoding and cloud layout, the CameraInfo, the transform of every frame
pair, that some image pairs with a cloud, then (a second read of the bag) every paired
frame as it will be completed: its image decoded, its cloud read, its points projected
with its calibration (:func:`crfdepth.inputs.points_to_sparse`: points in the image, not
millimetres, transform not inverted). Bad input is one line and exit status 2; bad
frames are listed (the first on the error's first line) and nothing is written, unless
``--skip-bad`` leaves them out (``<out-dir>/skipped.csv``: frame stamp and reason; exit
status 0). A frame that still fails while completing (a non-finite model output) or
Ctrl-C stops the run: the frames before it stay (each file is written atomically), the
index lists exactly them, the message says how many, and no ``--out-bag`` is left.

The output folders are locked for the run (``.crfdepth.lock``,
:func:`crfdepth.runs.outputs.output_folders`): a second run into them is refused naming the
first. An ``--out-dir`` holding the ``index.csv`` of an earlier run is refused unless
``--overwrite``, so that ``index.csv`` lists exactly the PNGs of one run.
"""

from __future__ import annotations

import argparse
import contextlib
import csv
import io
import sys
import time
from pathlib import Path

import numpy as np
from tqdm import tqdm

from crfdepth import api
from crfdepth.cli.arguments import BAD_INPUT, add_topic_arguments, positive_number
from crfdepth.cli.completion import cli_error, frame_errors
from crfdepth.cli.file_errors import FileError
from crfdepth.cli.model_options import build_model
from crfdepth.cli.outputs import check_output_folders, output_folders
from crfdepth.errors import InputError
from crfdepth.geometry.projection import count_in_image
from crfdepth.inputs import points_to_sparse
from crfdepth.io.ros.bag import CLOUD_TYPE, IMAGE_TYPES, Recording, camera_info_topic
from crfdepth.io.ros.frames import DEFAULT_MAX_DT_S, Plan, decode_frame, paired_frames, plan_frames
from crfdepth.runs.outputs import check_writable_dir, same_file, write_files, write_frame
from crfdepth.runs.skip_bad import skipped_frames, write_skipped

__all__ = ["BAG_ONLY", "add_arguments", "check_bag", "run_bag"]

BAG_ONLY = ("--image-topic", "--points-topic", "--camera-info-topic", "--max-dt", "--out-bag", "--rectified",
            "--overwrite")
INDEX_NAME = "index.csv"
INDEX_COLUMNS = ("timestamp_ns", "image_topic", "points_topic", "cloud_timestamp_ns", "dt_ms", "points",
                 "points_in_view", "depth_png", "std_png")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """The "a ROS bag" option group of ``complete``."""
    bag = parser.add_argument_group("a ROS bag", "ROS 1 .bag or ROS 2 (sqlite3, mcap) recordings; needs the "
                                                 "optional extra: pip install 'crfdepth[ros]'")
    add_topic_arguments(bag)
    bag.add_argument("--rectified", action="store_true",
                     help="the images are already rectified: use CameraInfo's P, no distortion (default for "
                          "topics named *rect*)")
    bag.add_argument("--max-dt", type=positive_number("seconds"), default=None, metavar="SECONDS",
                     help=f"largest time between an image and its cloud (default {DEFAULT_MAX_DT_S}: half a "
                          f"10 Hz LiDAR sweep)")
    bag.add_argument("--overwrite", action="store_true",
                     help="write into an --out-dir that holds the index.csv of an earlier run: its index.csv and "
                          "the PNGs of the same names are replaced (by default such a folder is refused, so that "
                          "index.csv always lists exactly the PNGs of one run)")
    bag.add_argument("--out-bag", metavar="OUT",
                     help="also write the depth (and std) as 32FC1 images with the images' headers: OUT.bag "
                          "(ROS 1) or a ROS 2 bag folder (the input's storage; mcap for a ROS 1 input)")


# --------------------------------------------------------------------------- checks


def _check_flags(args: argparse.Namespace) -> None:
    needed = {"--image-topic": args.image_topic, "--points-topic": args.points_topic, "--out-dir": args.out_dir}
    missing = [flag for flag, value in needed.items() if value is None]
    if missing:
        raise InputError(f"bag mode needs --bag, --image-topic, --points-topic and --out-dir; missing "
                         f"{', '.join(missing)}")
    stray = [flag for flag, value in (("--image", args.image), ("--sparse", args.sparse),
                                      ("--intrinsics", args.intrinsics), ("--points", args.points),
                                      ("--out", args.out), ("--out-std", args.out_std),
                                      ("--input-dir", args.input_dir)) if value is not None]
    stray += [flag for flag, value, default in (("--batch-size", args.batch_size, 1), ("--workers", args.workers, 0))
              if value != default]
    if stray:
        raise InputError(f"{', '.join(stray)}: cannot be combined with --bag (the frames come from the bag; outputs "
                         f"go to --out-dir / --out-std-dir / --out-bag)")
    if args.calib is not None and args.camera_info_topic is not None:
        raise InputError("--camera-info-topic / --calib: give one of them (--calib replaces the CameraInfo and "
                         "the transform)")


def _check_out_bag(args: argparse.Namespace) -> Path | None:
    if args.out_bag is None:
        return None
    out = Path(args.out_bag)
    if out.suffix in (".mcap", ".db3"):
        raise InputError(f"--out-bag: expected OUT.bag (ROS 1) or a folder name (ROS 2 bags are folders), got {out}")
    if out.exists() or out.is_symlink():
        raise InputError(f"--out-bag: expected a new bag, got {out}, which exists; remove it or choose another name")
    check_writable_dir(out.parent, "--out-bag")
    return out


def _output_topics(image_topic: str) -> dict[str, str]:
    """The ``--out-bag`` topics beside the image topic: ``/cam/image_raw`` -> ``/cam/crfdepth/depth`` ..."""
    namespace = camera_info_topic(image_topic).rsplit("/", 1)[0]
    return {role: f"{namespace}/crfdepth/{role}" for role in ("depth", "std", "camera_info")}


def _index_bytes(rows: list[dict]) -> bytes:
    text = io.StringIO()
    writer = csv.DictWriter(text, fieldnames=INDEX_COLUMNS, lineterminator="\n")
    writer.writeheader()
    writer.writerows(sorted(rows, key=lambda r: r["timestamp_ns"]))
    return text.getvalue().encode()


def _check_index(out_dir: str, overwrite: bool) -> None:
    """An ``--out-dir`` holding the ``index.csv`` of an earlier bag run is refused without ``--overwrite``:
    the index of this run would replace it, and its PNGs of the same names would be replaced."""
    index = Path(out_dir) / INDEX_NAME
    if index.exists() and not overwrite:
        raise InputError(f"--out-dir: {Path(out_dir)} already holds the {INDEX_NAME} of an earlier run; give "
                         f"--overwrite to replace it (and the PNGs of the same names), or choose another folder")


def _check_pairs(bag: Recording, args, plan: Plan) -> list[tuple[int, type[BaseException], str]]:
    """Pass 1b: every paired frame decoded and checked as :func:`_one` will (image, cloud, projection with its
    calibration: :func:`crfdepth.inputs.points_to_sparse`), nothing kept: ``(image index, error type, message)``
    of each bad frame."""
    bad, checked = [], 0
    progress = tqdm(total=plan.pairing.paired, unit="frame", desc="check",
                    disable=args.quiet or not sys.stderr.isatty())
    try:
        for i, image_msg, cloud_msg, c in paired_frames(bag, args, plan):
            try:
                rgb, xyz, flags = decode_frame(args, plan, i, image_msg, cloud_msg, c)
                try:
                    points_to_sparse(xyz, plan.calibrations[i], rgb.shape[:2], trust_transform=args.trust_transform)
                except InputError as exc:
                    raise cli_error(exc, flags) from None
            except BAD_INPUT as exc:
                bad.append((i, type(exc), str(exc)))
            checked += 1
            progress.update(1)
    except KeyboardInterrupt:
        raise KeyboardInterrupt(f"while checking the frames ({checked} of {plan.pairing.paired} checked); "
                                f"nothing written") from None
    finally:
        progress.close()
    return bad


def _check_outputs(args: argparse.Namespace) -> tuple[Path | None, list[tuple[str, str | None]]]:
    """The options, ``--out-bag`` and the output folders checked (nothing created); returns them."""
    _check_flags(args)
    out_bag = _check_out_bag(args)
    targets = check_output_folders(args, [Path(args.bag)], "the --bag input")
    if out_bag is not None and any(value is not None and same_file(out_bag, value) for _, value in targets):
        raise InputError(f"--out-bag: {out_bag} is also an output folder (--out-dir, --out-std-dir or --vis); "
                         f"expected a bag of its own")
    _check_index(args.out_dir, args.overwrite)
    return out_bag, targets


def check_bag(args: argparse.Namespace) -> None:
    """What ``complete --bag`` checks before reading a frame, without writing anything: the options, the outputs,
    the recording opened and its topics of the right types (``--input-list`` checks every line so before it
    completes any)."""
    _check_outputs(args)
    with Recording(args.bag, f"--bag {args.bag}") as bag:
        bag.check_topic(args.image_topic, "--image-topic", IMAGE_TYPES, "camera image")
        bag.check_topic(args.points_topic, "--points-topic", (CLOUD_TYPE,), "point cloud")


def run_bag(args: argparse.Namespace) -> int:
    """``complete --bag``: see the module docstring. Bad input raises ``BAD_INPUT`` naming the flag."""
    from crfdepth.io.ros.writer import BagWriter

    max_dt = DEFAULT_MAX_DT_S if args.max_dt is None else args.max_dt
    out_bag, targets = _check_outputs(args)
    start = time.perf_counter()
    with Recording(args.bag, f"--bag {args.bag}") as bag:
        plan = plan_frames(bag, args, max_dt)
        model = build_model(args)
        bad = _check_pairs(bag, args, plan)
        total = plan.pairing.paired
        skip = skipped_frames(bad, total, f"--bag {args.bag}", args.skip_bad)
        with output_folders(targets) as folders:
            out_dir, std_dir = folders[0], folders[1]
            vis_dir = folders[2] if args.vis is not None else None
            _check_index(out_dir, args.overwrite)  # another run may have finished there since the first look
            skipped_csv = write_skipped(out_dir, [(str(int(plan.images.stamps_ns[i])), m) for i, m in skip.items()])
            rows = _complete_pairs(bag, args, plan, model, skip, out_dir, std_dir, vis_dir, out_bag, BagWriter)
    if not args.quiet:
        _summary(args, plan, len(rows), out_dir, std_dir, out_bag, max_dt, time.perf_counter() - start)
        if skip:
            print(f"skipped {len(skip)} bad frame(s) of {total} (--skip-bad), listed with the reasons in "
                  f"{skipped_csv}")
    return 0


def _complete_pairs(bag: Recording, args, plan: Plan, model, skip, out_dir: Path, std_dir, vis_dir, out_bag,
                    BagWriter) -> list[dict]:
    """Pass 2: complete, write and index the paired frames not in ``skip``; ``index.csv`` written atomically at
    the end and, listing the frames written so far, when the run stops early (an error, Ctrl-C)."""
    with_std = std_dir is not None or vis_dir is not None
    topics = _output_topics(args.image_topic)
    storage = "sqlite3" if bag.storage == "sqlite3" else "mcap"  # of a ROS 2 output
    writer = None if out_bag is None else BagWriter(out_bag, storage=storage)
    todo = plan.pairing.paired - len(skip)
    rows = []
    progress = tqdm(total=todo, unit="frame", desc="complete", disable=args.quiet or not sys.stderr.isatty())
    try:
        for i, image_msg, cloud_msg, c in paired_frames(bag, args, plan, skip):
            _one(args, model, plan, i, image_msg, cloud_msg, c, out_dir, std_dir, vis_dir, writer, topics,
                 with_std, rows)
            progress.update(1)
    except BaseException as exc:
        if writer is not None:
            writer.abort()
        rows = [row for row in rows if (out_dir / row["depth_png"]).exists()]  # a frame cut short is not listed
        listed = False
        if rows:
            with contextlib.suppress(OSError):  # a full disk: the error that stopped the run is the one to tell
                write_files([("--out-dir", out_dir / INDEX_NAME, _index_bytes(rows))])
                listed = True
        where = (f"{len(rows)} of {todo} frame(s) written to {out_dir}"
                 + (f" and listed in its {INDEX_NAME}" if listed else "") + "; no --out-bag written")
        if isinstance(exc, (*BAD_INPUT, FileError)):
            raise type(exc)(f"{exc} [stopped after {where}]") from None
        if isinstance(exc, KeyboardInterrupt):
            raise KeyboardInterrupt(f"after {where}") from None
        raise
    finally:
        progress.close()
    write_files([("--out-dir", out_dir / INDEX_NAME, _index_bytes(rows))])
    if writer is not None:
        writer.commit()
    return rows


def _one(args, model, plan: Plan, i: int, image_msg, cloud_msg, c: int, out_dir: Path, std_dir, vis_dir, writer,
         topics, with_std: bool, rows: list[dict]) -> None:
    """Complete, write and index (append to ``rows`` before writing) one paired frame."""
    stamp = int(plan.images.stamps_ns[i])
    rgb, xyz, flags = decode_frame(args, plan, i, image_msg, cloud_msg, c)
    calibration = plan.calibrations[i]
    with frame_errors(args, model, rgb.shape[:2], flags):
        depth, std = api.complete_depth(rgb, points=xyz, calibration=calibration, model=model, device=args.device,
                                        return_std=with_std, trust_transform=args.trust_transform)
    name = f"{stamp}.png"
    in_view = count_in_image(xyz.astype(np.float64), calibration.T_cam_lidar, calibration.K, depth.shape)
    rows.append({"timestamp_ns": stamp, "image_topic": args.image_topic, "points_topic": args.points_topic,
                 "cloud_timestamp_ns": int(plan.clouds.stamps_ns[c]),
                 "dt_ms": f"{(int(plan.clouds.stamps_ns[c]) - stamp) / 1e6:.3f}", "points": xyz.shape[0],
                 "points_in_view": int(in_view), "depth_png": name, "std_png": name if std_dir is not None else ""})
    write_frame(depth, std, out_dir / name, std_dir / name if std_dir is not None else None, vis_dir, str(stamp),
                args.vis_range, ("--out-dir", "--out-std-dir", "--vis"))  # the frame's files: all of them or none
    if args.recorder is not None:
        args.recorder.complete_frame(rgb, depth, std, points=xyz, calibration=calibration, stamp_ns=stamp)
    if writer is not None:
        log_ns, frame_id = int(plan.images.log_ns[i]), plan.images.frame_ids[i]
        writer.write(topics["depth"], log_ns, writer.image(depth, stamp, frame_id, "32FC1"))
        if with_std:
            writer.write(topics["std"], log_ns, writer.image(std, stamp, frame_id, "32FC1"))
        writer.write(topics["camera_info"], log_ns, writer.camera_info(calibration.K, depth.shape, stamp, frame_id))


def _summary(args, plan: Plan, written: int, out_dir: Path, std_dir, out_bag, max_dt: float, seconds: float) -> None:
    unpaired = int(np.sum(plan.pairing.cloud < 0)) - plan.duplicates
    lines = [f"wrote {written} depth PNG(s) and index.csv to {out_dir}" + (f", std to {std_dir}" if std_dir else "")
             + (f", bag {out_bag}" if out_bag else "") + f" in {seconds:.1f} s"]
    if unpaired:
        gaps = plan.pairing.gap_ns[plan.pairing.cloud < 0]
        lines.append(f"{unpaired} of {len(plan.images)} image(s) unpaired: no cloud within --max-dt {max_dt:g} s "
                     f"(their gaps {gaps.min() / 1e9:.3g}-{gaps.max() / 1e9:.3g} s)")
    if plan.duplicates:
        lines.append(f"{plan.duplicates} image(s) skipped: header.stamp repeats an earlier image's")
    print("\n".join(lines))
