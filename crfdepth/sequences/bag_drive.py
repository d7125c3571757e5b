"""A ROS bag written as a KITTI raw drive, and the camera-view targets of that drive (docs/design.md section 14).

The bag is read as ``crfdepth complete --bag`` reads it (:mod:`crfdepth.io.ros.frames`: topics and
their types, the CameraInfo, the LiDAR -> camera transform from ``/tf_static`` + ``/tf`` or
``calib``, images paired with the cloud nearest in ``header.stamp`` within ``max_dt``).
A topic left out is the bag's only topic of its type. A cloud paired with several images
keeps the nearest one: one frame per scan. Frames are numbered in time order from 0; a time
gap between clouds of more than :data:`GAP_FACTOR` x the median period skips numbers (so
that no window and no training neighbour spans it) and is refused, naming the frame, unless
``frames`` (A, B) selects a gap-free range.

The frames the run uses (the selected ones +- k) are written as a KITTI raw drive,
``OUT/<date>/<bag name>_sync/{image_02,velodyne_points}/data/<10-digit frame>.{png,bin}``
(images undistorted with their own K when the camera has distortion; scans float32 x y z 0
in the LiDAR frame), with the day calibration ``OUT/<date>/calib_{cam_to_cam,velo_to_cam}.txt``
(``P_rect_02 = [K | 0]``, ``R_rect_00 = I``, velo_to_cam = ``T_cam<-lidar``: what
:func:`crfdepth.io.calibration.read_raw_calibration` reads back); ``<date>`` is the first
frame's image stamp, UTC, ``YYYY_MM_DD``. The targets are then made from that drive
(:func:`crfdepth.sequences.drive_targets.write_drive_targets`): ``OUT/<bag name>_sync/proj_depth/...``,
``poses.txt``, ``index_image_02.csv``. So ``SequenceFrames(OUT, targets_root=OUT)`` (layout
``"sequence"``, ``root`` and ``targets_root`` both OUT) reads it; several bags can go into one OUT.
The poses: :func:`crfdepth.sequences.pose_source.bag_pose_plan`.

Everything is checked before anything is written; the drive and its targets are made in a
hidden folder inside OUT and moved into place at the end, so a refused or interrupted run
leaves OUT as it was. An OUT that already holds this drive, or a day folder with another
recording's calibration, is refused. Errors name the options as ``crfdepth targets`` spells them.
"""

from __future__ import annotations

import datetime
import re
import shutil
import tempfile
from collections.abc import Callable
from pathlib import Path

import cv2
import numpy as np

from crfdepth.errors import BAD_INPUT, InputError
from crfdepth.io.calibration import RigCalibration
from crfdepth.io.ros.bag import CLOUD_TYPE, IMAGE_TYPES, Recording
from crfdepth.io.ros.frames import DEFAULT_MAX_DT_S, FrameTopics, Plan, decode_frame, paired_frames, plan_frames
from crfdepth.sequences.drive_targets import DriveTargets, select_frames, write_drive_targets
from crfdepth.sequences.pose_source import bag_pose_plan, matrix_text
from crfdepth.sequences.targets import Targets

__all__ = ["GAP_FACTOR", "write_bag_targets"]

GAP_FACTOR = 3.0
"""A time between consecutive clouds above this many median periods is a gap."""
_WIDTH = 10  # KITTI's frame stems
_CALIB_TOLERANCE = 1e-6  # K (pixels) and T_cam_lidar entries that may differ between frames


# --------------------------------------------------------------------------- the bag's frames


def _only_topic(bag: Recording, types: tuple[str, ...], flag: str, what: str) -> str:
    topics = bag.topics_of(types)
    if len(topics) != 1:
        got = "none" if not topics else f"{len(topics)} ({', '.join(topics)})"
        raise InputError(f"{flag}: expected the {what} topic of {bag.name} (needed when the bag has several or "
                         f"none), got {got}; {bag.listing()}")
    return topics[0]


def _topics(bag: Recording, image_topic: str | None, points_topic: str | None, camera_info_topic: str | None,
            calib: str | Path | None) -> FrameTopics:
    """What :func:`crfdepth.io.ros.frames.plan_frames` reads, with the topics chosen."""
    image = image_topic or _only_topic(bag, IMAGE_TYPES, "--image-topic", "camera image")
    points = points_topic or _only_topic(bag, (CLOUD_TYPE,), "--points-topic", "point cloud")
    return FrameTopics(image_topic=image, points_topic=points, camera_info_topic=camera_info_topic, calib=calib,
                       camera=2, rectified=False)


def _one_per_cloud(plan: Plan) -> list[int]:
    """Paired image indices, one per cloud (the nearest image), in the clouds' time order."""
    best: dict[int, int] = {}
    for i in np.flatnonzero(plan.pairing.cloud >= 0):
        c = int(plan.pairing.cloud[i])
        if c not in best or plan.pairing.gap_ns[i] < plan.pairing.gap_ns[best[c]]:
            best[c] = int(i)
    return [best[c] for c in sorted(best, key=lambda c: int(plan.clouds.stamps_ns[c]))]


def _numbers(bag: str | Path, selection: tuple[int, int] | None, stamps: np.ndarray) -> tuple[list[int], float]:
    """Frame numbers (a gap skips numbers) and the median cloud period (s); a gap refused without --frames."""
    if len(stamps) < 2:
        return [0] * len(stamps), 0.1
    steps = np.diff(stamps).astype(np.float64)
    period = float(np.median(steps))
    numbers = [0]
    for step in steps:
        numbers.append(numbers[-1] + (1 if step <= GAP_FACTOR * period else max(2, round(step / period))))
    gaps = np.flatnonzero(steps > GAP_FACTOR * period)
    if len(gaps) and selection is None:
        k = int(gaps[0])
        raise InputError(f"--bag {bag}: expected clouds at a steady rate, got a gap of {steps[k] / 1e9:.3f} s "
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


def _calib_texts(calib: RigCalibration, size: tuple[int, int]) -> dict[str, str]:
    """The KITTI raw day calibration of a pinhole camera ``K`` and the LiDAR -> camera transform."""
    height, width = size
    P = np.hstack([calib.K, np.zeros((3, 1))])
    T = calib.T_cam_lidar
    return {"calib_cam_to_cam.txt": f"S_rect_02: {width} {height}\nP_rect_02: {matrix_text(P)}\n"
                                    f"R_rect_00: {matrix_text(np.eye(3))}\n",
            "calib_velo_to_cam.txt": f"R: {matrix_text(T[:3, :3])}\nT: {matrix_text(T[:3, 3])}\n"}


# --------------------------------------------------------------------------- the drive


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


def _write_drive(bag: Recording, topics: FrameTopics, plan: Plan, frames: list[int], used_positions: list[int],
                 numbers: list[int], calib: RigCalibration, drive: Path) -> None:
    """The frames used as a KITTI raw drive: images (undistorted when the camera has distortion), scans."""
    images, scans = drive / "image_02" / "data", drive / "velodyne_points" / "data"
    images.mkdir(parents=True)
    scans.mkdir(parents=True)
    number_of = {frames[p]: numbers[p] for p in used_positions}
    skip = frozenset(int(i) for i in np.flatnonzero(plan.pairing.cloud >= 0)) - set(number_of)
    for i, image_msg, cloud_msg, c in paired_frames(bag, topics, plan, skip):
        if i not in number_of:  # an image whose cloud went to a nearer image
            continue
        rgb, xyz, _ = decode_frame(topics, plan, i, image_msg, cloud_msg, c)
        if calib.distortion is not None:
            rgb = cv2.undistort(rgb, calib.K, calib.distortion)
        stem = f"{number_of[i]:0{_WIDTH}d}"
        if not cv2.imwrite(str(images / f"{stem}.png"), cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR)):
            raise PermissionError(f"--out-dir: cannot write {images / f'{stem}.png'}")
        np.hstack([xyz, np.zeros((len(xyz), 1), np.float32)]).astype(np.float32).tofile(scans / f"{stem}.bin")


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


def write_bag_targets(bag: str | Path, out_dir: str | Path, *, frames: tuple[int, int] | None = None,
                      window: int = 5, poses: str = "auto", vis_dir: str | Path | None = None,
                      picture: Callable[[np.ndarray, Targets], np.ndarray] | None = None, recorder=None,
                      image_topic: str | None = None, points_topic: str | None = None,
                      camera_info_topic: str | None = None, calib: str | Path | None = None,
                      max_dt: float | None = None) -> DriveTargets:
    """Write the bag ``bag`` as a KITTI raw drive under ``out_dir`` and the targets of that drive (see the module
    docstring); returns what was written, ``drive`` being the drive written. The arguments are those of
    :func:`crfdepth.sequences.make_targets`, which checks them."""
    max_dt = DEFAULT_MAX_DT_S if max_dt is None else max_dt
    with Recording(bag, f"--bag {bag}") as recording:
        topics = _topics(recording, image_topic, points_topic, camera_info_topic, calib)
        plan = plan_frames(recording, topics, max_dt)
        paired = _one_per_cloud(plan)
        stamps = np.array([plan.clouds.stamps_ns[plan.pairing.cloud[i]] for i in paired], dtype=np.int64)
        numbers, period = _numbers(bag, frames, stamps)
        chosen, used = select_frames(frames, window, numbers, _WIDTH, f"--bag {bag}")
        position = {n: p for p, n in enumerate(numbers)}
        used_positions = [position[n] for n in used]
        calibration = _calibration(plan, paired)
        poses_mode, pose_lines, source = bag_pose_plan(poses, recording, plan, paired, used_positions, period,
                                                       numbers)
        first_stamp = int(plan.images.stamps_ns[paired[0]])
        date = datetime.datetime.fromtimestamp(first_stamp / 1e9, tz=datetime.timezone.utc).strftime("%Y_%m_%d")
        name = _drive_name(Path(bag))
        calib_texts = _calib_texts(calibration, plan.calibrations[paired[0]].image_size)
        out = Path(out_dir)
        _check_out(out, date, name, calib_texts)
        vis = None if vis_dir is None else Path(vis_dir)
        for folder in (out, vis):
            if folder is not None:
                folder.mkdir(parents=True, exist_ok=True)
        staging = Path(tempfile.mkdtemp(prefix=".crfdepth-targets-", dir=out))
        try:
            drive = staging / date / name
            _write_drive(recording, topics, plan, paired, used_positions, numbers, calibration, drive)
            for file, text in calib_texts.items():
                (staging / date / file).write_text(text)
            drive_poses = poses_mode
            if pose_lines is not None:
                drive_poses = str(staging / "poses.txt")
                Path(drive_poses).write_text("\n".join(pose_lines) + "\n")
            try:
                written = write_drive_targets(drive, staging / "targets", camera=2, frames=frames, window=window,
                                              poses=drive_poses, vis_dir=None if vis is None else staging / "vis",
                                              picture=picture, recorder=recorder)
            except BAD_INPUT as exc:
                text = str(exc).replace(f"--drive {drive}", f"--bag {bag}")
                raise type(exc)(text.replace(f"--poses {drive_poses}", f"--poses {poses}")) from None
            _move_into_place(staging, out, date, name, vis)
        except KeyboardInterrupt:
            raise KeyboardInterrupt(f"before the drive was moved into {out}; nothing written") from None
        finally:
            shutil.rmtree(staging, ignore_errors=True)
    return DriveTargets(drive=out / date / name, out=out / name, camera="image_02", frames=len(chosen), source=source,
                        density=written.density, scan_density=written.scan_density, seconds=written.seconds)
