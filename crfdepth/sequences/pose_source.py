"""Where the poses of ``crfdepth targets`` come from: a drive's oxts, a bag's /tf, LiDAR odometry or a poses file
(docs/design.md sections 12 and 14).

``poses`` is ``auto``, ``tf``, ``odometry``, ``oxts`` or the path of a KITTI odometry ``poses.txt``:

- a KITTI raw drive (:func:`drive_poses`): ``auto`` is the drive's ``oxts/data`` (GPS/IMU) when present, else
  LiDAR odometry; ``odometry``: KISS-ICP over the scans the run uses
  (:func:`crfdepth.sequences.odometry.lidar_odometry_with_fallback`), a failed step an error naming the frame;
  ``oxts``; or a poses file (one camera-0 pose per frame of the drive, in frame order);
- a ROS bag (:func:`bag_pose_plan`): ``tf`` is the transform from the top of the LiDAR frame's tf tree (``odom``,
  ``map`` ...) to the LiDAR at each cloud's stamp, checked for jumps like LiDAR odometry
  (:func:`crfdepth.sequences.pose_checks.check_poses`); ``auto`` is ``tf`` when the LiDAR frame's tree changes
  over time, else ``odometry``; a poses file has one line per paired frame of the bag.

A poses file's and oxts' steps are checked as /tf's are (speed, yaw rate, jumps; at 10 Hz for a drive of
consecutive frames, at the clouds' rate for a bag), an impossible one an error naming the line or file.

Errors name the option as the command spells it (``--poses``, ``--frames``).
"""

from __future__ import annotations

import importlib.util
from pathlib import Path

import numpy as np

from crfdepth.errors import InputError
from crfdepth.io.ros.bag import Recording
from crfdepth.io.ros.frames import Plan
from crfdepth.sequences import odometry
from crfdepth.sequences.pose_checks import check_poses
from crfdepth.sequences.poses import read_imu_to_velo, read_kitti_poses, read_oxts

__all__ = ["bag_pose_plan", "drive_poses", "kiss_installed", "matrix_text"]

KITTI_RATE_HZ = 10.0
"""Frames per second of a KITTI raw drive (the Velodyne's rotation rate)."""


def kiss_installed() -> bool:
    """Whether the ``kiss_icp`` package (LiDAR odometry, ``pip install "crfdepth[odometry]"``) can be imported."""
    try:
        return importlib.util.find_spec("kiss_icp") is not None
    except (ImportError, ValueError):  # a module set to None (tests) or without a spec
        return False


def matrix_text(a) -> str:
    """The entries of ``a``, row by row, as KITTI's text files write them (``%.12e``, space-separated)."""
    return " ".join(f"{v:.12e}" for v in np.asarray(a, dtype=np.float64).ravel())


# --------------------------------------------------------------------------- a KITTI raw drive


def drive_poses(poses: str, drive: Path, frames: list[int], used: list[int], scans: list[np.ndarray], calib,
                width: int) -> tuple[np.ndarray, str]:
    """``T_lidar(first used)<-lidar(t)`` of every used scan (frame numbers ``used`` among the drive's ``frames``,
    ``scans`` their returns, ``calib`` the drive's :class:`~crfdepth.io.calibration.RigCalibration`, ``width`` the
    digits of a frame's file name), and how they were obtained."""
    mode = poses
    oxts = drive / "oxts" / "data"
    if mode == "auto":
        mode = "oxts" if oxts.is_dir() else "odometry"
    positions = [frames.index(f) for f in used]
    # KITTI raw records at 10 Hz: the steps of consecutive frames are checked as /tf odometry is; a drive of
    # every n-th frame only for an impossible step (crfdepth.sequences.poses.read_kitti_poses)
    rate = KITTI_RATE_HZ if all(b - a == 1 for a, b in zip(frames, frames[1:])) else None
    if mode == "odometry":
        if not kiss_installed():
            why = "the drive has no oxts/data, and " if poses == "auto" else ""
            raise InputError(f"--poses {poses}: {why}LiDAR odometry needs the kiss-icp package, not installed; "
                             f"{odometry.EXTRA_HINT}, or give --poses FILE")
        odo, note = odometry.lidar_odometry_with_fallback(scans)
        if odo.failures:
            listed = "; ".join(f"frame {used[k]:0{width}d}: {why}" for k, why in odo.failures[:5])
            more = f"; and {len(odo.failures) - 5} more" if len(odo.failures) > 5 else ""
            raise InputError(f"--poses {poses}: expected LiDAR odometry without failures, got "
                             f"{len(odo.failures)} failed step(s) ({listed}{more}); nothing written; choose "
                             f"--frames that avoid them or give --poses FILE")
        frames_used = f"over frames {used[0]:0{width}d}-{used[-1]:0{width}d}"
        return odo.poses, f"LiDAR odometry (KISS-ICP{'; ' + note if note else ''}) {frames_used}"
    if mode == "oxts":
        if not oxts.is_dir():
            raise InputError(f"--poses oxts: expected the drive's oxts/data folder, got no {oxts}")
        try:
            T_velo_imu = read_imu_to_velo(drive.parent)
            found = read_oxts(oxts.parent, T_velo_imu, rate=rate)
        except (InputError, FileNotFoundError) as exc:
            raise type(exc)(f"--poses {poses}: {exc}") from None
        if len(found) != len(frames):
            raise InputError(f"--poses {poses}: expected {len(frames)} oxts packets (one per frame) in {oxts}, "
                             f"got {len(found)}")
        source = "oxts (GPS/IMU)"
    else:
        if calib.kitti is None:  # pragma: no cover - the day folder is always a KITTI calibration
            raise InputError(f"--poses {mode}: expected a KITTI calibration to read camera-0 poses with")
        found = _read_poses_file(mode, "auto, odometry, oxts", calib.kitti.velo_to_rect_cam(), rate=rate)
        if len(found) != len(frames):
            raise InputError(f"--poses {mode}: expected {len(frames)} poses (one per frame of the drive, in frame "
                             f"order), got {len(found)}")
        source = f"poses file {mode}"
    chosen = found[positions]
    first_inv = np.linalg.inv(chosen[0])
    return np.stack([first_inv @ P for P in chosen]), source


# --------------------------------------------------------------------------- a ROS bag


def _tf_poses(poses: str, bag: Recording, plan: Plan, clouds: list[int], rate: float, numbers: list[int],
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
        raise InputError(f"--poses {poses}: expected /tf odometry {root!r} -> {lidar!r} at every cloud, got "
                         f"{len(outside)} cloud(s) outside its {first / 1e9:.3f}-{last / 1e9:.3f} s (the first: frame "
                         f"{numbers[k]:010d} at {stamps[k] / 1e9:.3f} s); choose --frames within it")
    world = np.stack([tree.lookup(root, lidar, s) for s in stamps])
    found = np.linalg.inv(world[0]) @ world
    failures = check_poses(found, rate=rate)
    if failures:
        listed = "; ".join(f"frame {numbers[k]:010d}: {why}" for k, why in failures[:5])
        more = f"; and {len(failures) - 5} more" if len(failures) > 5 else ""
        raise InputError(f"--poses {poses}: expected /tf odometry {root!r} -> {lidar!r} without failures, got "
                         f"{len(failures)} failed step(s) ({listed}{more}); nothing written; choose --frames that "
                         f"avoid them or give --poses odometry")
    return found, f"/tf odometry {root} -> {lidar}"


def _read_poses_file(poses: str, keywords: str, T_cam0_lidar=None, rate: float | None = None) -> np.ndarray:
    """The poses of the file ``--poses`` names, its errors naming the option; a value that is neither one of the
    ``keywords`` nor an existing path (a misspelt keyword) is told what the option takes. ``rate``: the frames'
    rate (Hz) when its lines are consecutive frames, for the check of each step (``read_kitti_poses``)."""
    if not Path(poses).exists():
        raise InputError(f"--poses {poses}: expected {keywords} or the path of a KITTI odometry poses.txt, got "
                         f"{poses!r}, which is neither (no such file)")
    try:
        return read_kitti_poses(poses, T_cam0_lidar, rate=rate)
    except (InputError, FileNotFoundError, PermissionError, IsADirectoryError) as exc:
        raise type(exc)(f"--poses {poses}: {str(exc).removeprefix('poses: ')}") from None


def _poses_file_lines(poses: str, count: int, positions: list[int], rate: float | None = None) -> list[str]:
    """A poses file's lines for the frames used (one line per paired frame of the bag, ``rate`` Hz)."""
    _read_poses_file(poses, "auto, tf, odometry", rate=rate)
    lines = [line for line in Path(poses).read_text().splitlines() if line.strip()]
    if len(lines) != count:
        raise InputError(f"--poses {poses}: expected {count} poses (one per paired frame of the bag, in time "
                         f"order), got {len(lines)}")
    return [lines[p] for p in positions]


def bag_pose_plan(poses: str, bag: Recording, plan: Plan, frames: list[int], used_positions: list[int],
                  period: float, numbers: list[int]) -> tuple[str, list[str] | None, str]:
    """How the drive written from a bag gets its poses: ``(poses value for the drive, or "FILE"; the lines of the
    poses file to write with it, or None; how they were obtained)``. ``frames``: the paired image indices, one
    per cloud in time order; ``used_positions``: the positions among them the run uses; ``period``: the clouds'
    median period (s); ``numbers``: the frame numbers."""
    mode = poses
    if mode == "oxts":
        raise InputError("--poses oxts: expected auto, tf, odometry or a poses file with --bag (a bag has no oxts), "
                         "got oxts")
    if mode in ("auto", "tf"):
        clouds = [int(plan.pairing.cloud[frames[p]]) for p in used_positions]
        found = _tf_poses(poses, bag, plan, clouds, 1.0 / period, [numbers[p] for p in used_positions], mode == "tf")
        if found is not None:
            lidar_poses, source = found
            T = plan.calibrations[frames[0]].T_cam_lidar
            cams = T @ lidar_poses @ np.linalg.inv(T)
            return "FILE", [matrix_text(P[:3, :]) for P in cams], source
        mode = "odometry"
    if mode == "odometry":
        if not kiss_installed():
            why = "the bag has no odometry on /tf, and " if poses == "auto" else ""
            raise InputError(f"--poses {poses}: {why}LiDAR odometry needs the kiss-icp package, not installed; "
                             f"{odometry.EXTRA_HINT}, or give --poses FILE")
        return "odometry", None, "LiDAR odometry (KISS-ICP)"
    return "FILE", _poses_file_lines(poses, len(frames), used_positions, 1.0 / period), f"poses file {mode}"
