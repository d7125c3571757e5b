"""``crfdepth targets --bag``: camera-view targets and a training-ready drive from a ROS bag (docs/design.md section 14).

::

    crfdepth targets --bag RUN.bag --out-dir OUT [--image-topic T] [--points-topic T]
        [--camera-info-topic T] [--calib FILE] [--max-dt S] [--poses auto|tf|odometry|FILE]
        [-k K] [--frames A:B] [--vis [DIR]]

The bag is read as ``crfdepth complete --bag`` reads it (:mod:`crfdepth.cli.bag_frames`: topics and
their types, the CameraInfo, the LiDAR -> camera transform from ``/tf_static`` + ``/tf`` or
``--calib``, images paired with the cloud nearest in ``header.stamp`` within ``--max-dt``).
A topic left out is the bag's only topic of its type. A cloud paired with several images
keeps the nearest one: one frame per scan. Frames are numbered in time order from 0; a time
gap between clouds of more than :data:`GAP_FACTOR` x the median period skips numbers (so
that no window and no training neighbour spans it) and is refused, naming the frame, unless
``--frames A:B`` selects a gap-free range.

The frames the run uses (the selected ones +- k) are written as a KITTI raw drive,
``OUT/<date>/<bag name>_sync/{image_02,velodyne_points}/data/<10-digit frame>.{png,bin}``
(images undistorted with their own K when the camera has distortion; scans float32 x y z 0
in the LiDAR frame), with the day calibration ``OUT/<date>/calib_{cam_to_cam,velo_to_cam}.txt``
(``P_rect_02 = [K | 0]``, ``R_rect_00 = I``, velo_to_cam = ``T_cam<-lidar``: what
:func:`crfdepth.io.calibration.read_raw_calibration` reads back); ``<date>`` is the first
frame's image stamp, UTC, ``YYYY_MM_DD``. The targets are then made from that drive by the
drive code path (:func:`crfdepth.cli.targets_drive.run_drive`): ``OUT/<bag name>_sync/proj_depth/...``,
``poses.txt``, ``index_image_02.csv``. So ``SequenceFrames(OUT, targets_root=OUT)`` (layout
``"sequence"``, ``root`` and ``targets_root`` both OUT) reads it; several bags can go into one OUT.

Poses (``--poses``): ``tf``: the bag's odometry on /tf, the transform from the top of the
LiDAR frame's tree (``odom``, ``map`` ...) to the LiDAR frame at each cloud's stamp, checked
for jumps like LiDAR odometry (:func:`crfdepth.sequences.pose_checks.check_poses`, failures named by
frame); ``odometry``: KISS-ICP (the drive path); ``auto``: ``tf`` when the LiDAR frame's
tree changes over time, else ``odometry``; ``FILE``: camera poses, KITTI odometry format,
one line per paired frame of the bag.

Everything is checked before anything is written; the drive and its targets are made in a
hidden folder inside OUT and moved into place at the end, so a refused or interrupted run
leaves OUT as it was. An OUT that already holds this drive, or a day folder with another
recording's calibration, is refused.
"""

from __future__ import annotations

import argparse
import csv
import datetime
import re
import shutil
import tempfile
from pathlib import Path

import cv2
import numpy as np

from crfdepth.cli import targets_drive
from crfdepth.cli.arguments import BAD_INPUT, add_topic_arguments, positive_number
from crfdepth.cli.bag_frames import DEFAULT_MAX_DT_S, Plan, decode_frame, paired_frames, plan_frames
from crfdepth.cli.outputs import check_output_folders, output_folders
from crfdepth.errors import InputError
from crfdepth.io.calibration import RigCalibration
from crfdepth.io.ros.bag import CLOUD_TYPE, IMAGE_TYPES, Recording
from crfdepth.sequences import odometry
from crfdepth.sequences.pose_checks import check_poses
from crfdepth.sequences.poses import read_kitti_poses

__all__ = ["GAP_FACTOR", "add_arguments", "check_drive_flags", "run_bag"]

GAP_FACTOR = 3.0
"""A time between consecutive clouds above this many median periods is a gap."""
_BAG_FLAGS = ("image_topic", "points_topic", "camera_info_topic", "calib", "max_dt")
_WIDTH = 10  # KITTI's frame stems
_CALIB_TOLERANCE = 1e-6  # K (pixels) and T_cam_lidar entries that may differ between frames


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """The "a ROS bag" option group of ``targets``."""
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


def check_drive_flags(args: argparse.Namespace) -> None:
    """The bag's options are refused with ``--drive``; ``--poses tf`` too."""
    stray = [f"--{name.replace('_', '-')}" for name in _BAG_FLAGS if getattr(args, name) is not None]
    if stray:
        raise InputError(f"{', '.join(stray)}: cannot be combined with --drive (options of --bag)")
    if args.poses == "tf":
        raise InputError("--poses tf: expected auto, odometry, oxts or a poses file with --drive, got tf (the "
                         "odometry on a bag's /tf, for --bag)")


# --------------------------------------------------------------------------- the bag's frames


def _only_topic(bag: Recording, types: tuple[str, ...], flag: str, what: str) -> str:
    topics = bag.topics_of(types)
    if len(topics) != 1:
        got = "none" if not topics else f"{len(topics)} ({', '.join(topics)})"
        raise InputError(f"{flag}: expected the {what} topic of {bag.name} (needed when the bag has several or "
                         f"none), got {got}; {bag.listing()}")
    return topics[0]


def _namespace(args, bag: Recording) -> argparse.Namespace:
    """What :func:`crfdepth.cli.bag_frames.plan_frames` reads, with the topics chosen."""
    image = args.image_topic or _only_topic(bag, IMAGE_TYPES, "--image-topic", "camera image")
    points = args.points_topic or _only_topic(bag, (CLOUD_TYPE,), "--points-topic", "point cloud")
    return argparse.Namespace(image_topic=image, points_topic=points, camera_info_topic=args.camera_info_topic,
                              calib=args.calib, camera=2, rectified=False)


def _one_per_cloud(plan: Plan) -> list[int]:
    """Paired image indices, one per cloud (the nearest image), in the clouds' time order."""
    best: dict[int, int] = {}
    for i in np.flatnonzero(plan.pairing.cloud >= 0):
        c = int(plan.pairing.cloud[i])
        if c not in best or plan.pairing.gap_ns[i] < plan.pairing.gap_ns[best[c]]:
            best[c] = int(i)
    return [best[c] for c in sorted(best, key=lambda c: int(plan.clouds.stamps_ns[c]))]


def _numbers(args, stamps: np.ndarray) -> tuple[list[int], float]:
    """Frame numbers (a gap skips numbers) and the median cloud period (s); a gap refused without --frames."""
    if len(stamps) < 2:
        return [0] * len(stamps), 0.1
    steps = np.diff(stamps).astype(np.float64)
    period = float(np.median(steps))
    numbers = [0]
    for step in steps:
        numbers.append(numbers[-1] + (1 if step <= GAP_FACTOR * period else max(2, round(step / period))))
    gaps = np.flatnonzero(steps > GAP_FACTOR * period)
    if len(gaps) and args.frames is None:
        k = int(gaps[0])
        raise InputError(f"--bag {args.bag}: expected clouds at a steady rate, got a gap of {steps[k] / 1e9:.3f} s "
                         f"after frame {numbers[k]:0{_WIDTH}d} (next: {numbers[k + 1]:0{_WIDTH}d}; more than "
                         f"{GAP_FACTOR:g}x the median period {period / 1e9:.3f} s; {len(gaps)} gap(s)); give "
                         f"--frames A:B for a gap-free range")
    return numbers, period / 1e9


def _calibration(plan: Plan, frames: list[int]) -> RigCalibration:
    """The one calibration of every frame (the camera and the transform must not change)."""
    first = plan.calibrations[frames[0]]
    for i in frames[1:]:
        other = plan.calibrations[i]
        if not (np.allclose(other.K, first.K, atol=_CALIB_TOLERANCE)
                and np.allclose(other.T_cam_lidar, first.T_cam_lidar, atol=_CALIB_TOLERANCE)):
            raise InputError(f"--camera-info-topic / --points-topic: expected one camera and one LiDAR -> camera "
                             f"transform for the whole bag, got a change at the image of {plan.images.stamps_ns[i]} "
                             f"ns ({other.source}); give one with --calib FILE")
    return first


def _matrix_text(a) -> str:
    return " ".join(f"{v:.12e}" for v in np.asarray(a, dtype=np.float64).ravel())


def _calib_texts(calib: RigCalibration, size: tuple[int, int]) -> dict[str, str]:
    """The KITTI raw day calibration of a pinhole camera ``K`` and the LiDAR -> camera transform."""
    height, width = size
    P = np.hstack([calib.K, np.zeros((3, 1))])
    T = calib.T_cam_lidar
    return {"calib_cam_to_cam.txt": f"S_rect_02: {width} {height}\nP_rect_02: {_matrix_text(P)}\n"
                                    f"R_rect_00: {_matrix_text(np.eye(3))}\n",
            "calib_velo_to_cam.txt": f"R: {_matrix_text(T[:3, :3])}\nT: {_matrix_text(T[:3, 3])}\n"}


# --------------------------------------------------------------------------- poses


def _tf_poses(args, bag: Recording, plan: Plan, clouds: list[int], rate: float, numbers: list[int],
              demanded: bool) -> tuple[np.ndarray, str] | None:
    """LiDAR poses ``T_lidar(first)<-lidar(t)`` from /tf at the clouds' stamps, checked; None (``auto``) when
    the LiDAR frame's tree does not change over time."""
    tree = plan.tree if plan.tree is not None else bag.transforms()
    lidar = plan.clouds.frame_ids[clouds[0]]
    root = tree.root(lidar) if lidar else lidar
    if not lidar or root == lidar or not tree.has_dynamic(root, lidar):
        if not demanded:
            return None
        chain = " <- ".join(tree.path(root, lidar)) if lidar and root != lidar else repr(lidar)
        raise InputError(f"--poses tf: expected odometry on /tf (a transform from a fixed frame such as odom or map "
                         f"to the LiDAR frame {lidar!r} that changes over time), got "
                         f"{'only /tf_static above it: ' + chain if root != lidar else 'no transform above it'}; "
                         f"use --poses odometry or --poses FILE")
    first, last = tree.dynamic_span(root, lidar)
    stamps = [int(plan.clouds.stamps_ns[c]) for c in clouds]
    outside = [k for k, s in enumerate(stamps) if not first <= s <= last]
    if outside:
        k = outside[0]
        raise InputError(f"--poses {args.poses}: expected /tf odometry {root!r} -> {lidar!r} at every cloud, got "
                         f"{len(outside)} cloud(s) outside its {first / 1e9:.3f}-{last / 1e9:.3f} s (the first: frame "
                         f"{numbers[k]:0{_WIDTH}d} at {stamps[k] / 1e9:.3f} s); choose --frames within it")
    world = np.stack([tree.lookup(root, lidar, s) for s in stamps])
    poses = np.linalg.inv(world[0]) @ world
    failures = check_poses(poses, rate=rate)
    if failures:
        listed = "; ".join(f"frame {numbers[k]:0{_WIDTH}d}: {why}" for k, why in failures[:5])
        more = f"; and {len(failures) - 5} more" if len(failures) > 5 else ""
        raise InputError(f"--poses {args.poses}: expected /tf odometry {root!r} -> {lidar!r} without failures, got "
                         f"{len(failures)} failed step(s) ({listed}{more}); nothing written; choose --frames that "
                         f"avoid them or give --poses odometry")
    return poses, f"/tf odometry {root} -> {lidar}"


def _poses_file_lines(args, count: int, positions: list[int]) -> list[str]:
    """``--poses FILE``: its lines for the frames used (one line per paired frame of the bag)."""
    try:
        read_kitti_poses(args.poses)
    except (InputError, FileNotFoundError, PermissionError, IsADirectoryError) as exc:
        raise type(exc)(f"--poses {args.poses}: {str(exc).removeprefix('poses: ')}") from None
    lines = [line for line in Path(args.poses).read_text().splitlines() if line.strip()]
    if len(lines) != count:
        raise InputError(f"--poses {args.poses}: expected {count} poses (one per paired frame of the bag, in time "
                         f"order), got {len(lines)}")
    return [lines[p] for p in positions]


def _pose_plan(args, bag, plan, frames, used_positions, period, numbers) -> tuple[str, list[str] | None, str]:
    """How the drive path gets its poses: ``(--poses value or "FILE", lines of the file to write, source)``."""
    mode = args.poses
    if mode == "oxts":
        raise InputError("--poses oxts: expected auto, tf, odometry or a poses file with --bag (a bag has no oxts), "
                         "got oxts")
    if mode in ("auto", "tf"):
        clouds = [int(plan.pairing.cloud[frames[p]]) for p in used_positions]
        found = _tf_poses(args, bag, plan, clouds, 1.0 / period, [numbers[p] for p in used_positions], mode == "tf")
        if found is not None:
            poses, source = found
            T = plan.calibrations[frames[0]].T_cam_lidar
            cams = T @ poses @ np.linalg.inv(T)
            return "FILE", [_matrix_text(P[:3, :]) for P in cams], source
        mode = "odometry"
    if mode == "odometry":
        if not targets_drive.kiss_installed():
            why = "the bag has no odometry on /tf, and " if args.poses == "auto" else ""
            raise InputError(f"--poses {args.poses}: {why}LiDAR odometry needs the kiss-icp package, not installed; "
                             f"{odometry.EXTRA_HINT}, or give --poses FILE")
        return "odometry", None, "LiDAR odometry (KISS-ICP)"
    return "FILE", _poses_file_lines(args, len(frames), used_positions), f"poses file {mode}"


# --------------------------------------------------------------------------- the run


def _drive_name(path: Path) -> str:
    name = path.resolve().name
    for suffix in (".bag", ".mcap", ".db3"):
        name = name.removesuffix(suffix)
    return re.sub(r"[^A-Za-z0-9_.-]", "_", name) + "_sync"


def _check_out(out: Path, date: str, name: str, calib_texts: dict[str, str]) -> None:
    for held in (out / date / name, out / name):
        if held.exists():
            raise InputError(f"--out-dir: {out} already holds the drive {name} ({held}, from an earlier run); remove "
                             f"it or choose another --out-dir")
    for file, text in calib_texts.items():
        path = out / date / file
        if path.exists() and path.read_text() != text:
            raise InputError(f"--out-dir: {out / date} already holds another recording's calibration ({file} differs "
                             f"from this bag's camera and transform; one calibration per day folder); choose another "
                             f"--out-dir")


def _write_drive(bag, ns, plan, frames, used_positions, numbers, calib, drive: Path) -> None:
    """The frames used as a KITTI raw drive: images (undistorted when the camera has distortion), scans."""
    images, scans = drive / "image_02" / "data", drive / "velodyne_points" / "data"
    images.mkdir(parents=True)
    scans.mkdir(parents=True)
    number_of = {frames[p]: numbers[p] for p in used_positions}
    skip = frozenset(int(i) for i in np.flatnonzero(plan.pairing.cloud >= 0)) - set(number_of)
    for i, image_msg, cloud_msg, c in paired_frames(bag, ns, plan, skip):
        if i not in number_of:  # an image whose cloud went to a nearer image
            continue
        rgb, xyz, _ = decode_frame(ns, plan, i, image_msg, cloud_msg, c)
        if calib.distortion is not None:
            rgb = cv2.undistort(rgb, calib.K, calib.distortion)
        stem = f"{number_of[i]:0{_WIDTH}d}"
        if not cv2.imwrite(str(images / f"{stem}.png"), cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR)):
            raise PermissionError(f"--out-dir: cannot write {images / f'{stem}.png'}")
        np.hstack([xyz, np.zeros((len(xyz), 1), np.float32)]).astype(np.float32).tofile(scans / f"{stem}.bin")


def run_bag(args: argparse.Namespace) -> int:
    """``targets --bag``: see the module docstring. Bad input raises ``BAD_INPUT`` naming the flag."""
    if args.camera != 2:
        raise InputError(f"--camera {args.camera}: cannot be combined with --bag (a bag's camera is written as "
                         f"image_02)")
    max_dt = DEFAULT_MAX_DT_S if args.max_dt is None else args.max_dt
    outputs = check_output_folders(args, [Path(args.bag)], "the --bag input")
    with Recording(args.bag, f"--bag {args.bag}") as bag:
        ns = _namespace(args, bag)
        plan = plan_frames(bag, ns, max_dt)
        frames = _one_per_cloud(plan)
        stamps = np.array([plan.clouds.stamps_ns[plan.pairing.cloud[i]] for i in frames], dtype=np.int64)
        numbers, period = _numbers(args, stamps)
        chosen, used = targets_drive.select_frames(args, numbers, _WIDTH, f"--bag {args.bag}")
        position = {n: p for p, n in enumerate(numbers)}
        used_positions = [position[n] for n in used]
        calib = _calibration(plan, frames)
        poses_mode, pose_lines, source = _pose_plan(args, bag, plan, frames, used_positions, period, numbers)
        first_stamp = int(plan.images.stamps_ns[frames[0]])
        date = datetime.datetime.fromtimestamp(first_stamp / 1e9, tz=datetime.timezone.utc).strftime("%Y_%m_%d")
        name = _drive_name(Path(args.bag))
        calib_texts = _calib_texts(calib, plan.calibrations[frames[0]].image_size)
        out_dir = Path(args.out_dir)
        _check_out(out_dir, date, name, calib_texts)
        with output_folders(outputs) as folders:
            out, vis_dir = folders[0], folders[2] if args.vis is not None else None
            _check_out(out, date, name, calib_texts)  # another run may have finished there since the first look
            staging = Path(tempfile.mkdtemp(prefix=".crfdepth-targets-", dir=out))
            try:
                drive = staging / date / name
                _write_drive(bag, ns, plan, frames, used_positions, numbers, calib, drive)
                for file, text in calib_texts.items():
                    (staging / date / file).write_text(text)
                poses = poses_mode
                if pose_lines is not None:
                    poses = str(staging / "poses.txt")
                    Path(poses).write_text("\n".join(pose_lines) + "\n")
                run = argparse.Namespace(
                    drive=str(drive), bag=None, camera=2, frames=args.frames, window=args.window, poses=poses,
                    out_dir=str(staging / "targets"), vis=None if vis_dir is None else str(staging / "vis"),
                    quiet=True, out_std_dir=None, stereo_check=False, recorder=args.recorder,
                    **{key: None for key in _BAG_FLAGS})
                try:
                    targets_drive.run_drive(run)
                except BAD_INPUT as exc:
                    text = str(exc).replace(f"--drive {drive}", f"--bag {args.bag}")
                    raise type(exc)(text.replace(f"--poses {poses}", f"--poses {args.poses}")) from None
                _move_into_place(staging, out, date, name, vis_dir)
            except KeyboardInterrupt:
                raise KeyboardInterrupt(f"before the drive was moved into {out}; nothing written") from None
            finally:
                shutil.rmtree(staging, ignore_errors=True)
    if not args.quiet:
        _summary(args, out, date, name, len(chosen), source)
    return 0


def _move_into_place(staging: Path, out: Path, date: str, name: str, vis_dir: Path | None) -> None:
    (out / date).mkdir(exist_ok=True)
    for file in ("calib_cam_to_cam.txt", "calib_velo_to_cam.txt"):
        if not (out / date / file).exists():
            (staging / date / file).replace(out / date / file)
    (staging / date / name).replace(out / date / name)
    (staging / "targets" / name).replace(out / name)
    if vis_dir is not None:
        for picture in sorted((staging / "vis").iterdir()):
            picture.replace(vis_dir / picture.name)


def _summary(args, out: Path, date: str, name: str, frames: int, source: str) -> None:
    with (out / name / "index_image_02.csv").open(newline="") as handle:
        rows = list(csv.DictReader(handle))
    density = float(np.mean([float(r["density"]) for r in rows]))
    single = float(np.mean([float(r["scan_density"]) for r in rows]))
    ratio = f" ({density / single:.2f}x)" if single > 0 else ""
    print(f"wrote {frames} frame(s) of {args.bag} as the drive {out / date / name} and their targets to "
          f"{out / name} (image_02, k={args.window}, poses: {source}): mean density {density:.4f} against "
          f"{single:.4f} for the single scan{ratio}")
