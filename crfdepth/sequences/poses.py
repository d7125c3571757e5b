"""Poses given (docs/design.md section 12).

- :func:`read_kitti_poses`: KITTI odometry ``poses.txt`` (camera-0 poses, 12 numbers a line).
- :func:`read_oxts`: KITTI raw ``oxts/data/*.txt`` (GPS/IMU), the devkit's Mercator
  conversion (:func:`oxts_to_pose`); :func:`read_imu_to_velo` reads the day's ``calib_imu_to_velo.txt``.
- The rigid-transform maths every pose source shares (``invert_rigid``, ``camera_relative_pose``, ...)
  is :mod:`crfdepth.geometry.rigid`.

Convention, here and in LiDAR odometry (:mod:`crfdepth.sequences.odometry`): poses are LiDAR
poses ``T_world<-lidar(t)`` as (n, 4, 4) float64, ``p_world = T @ p_lidar``, with the world =
the LiDAR frame of the first scan (the first pose is the identity). LiDAR frame: KITTI
Velodyne axes (x forward, y left, z up, metres).
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from crfdepth.checks import check_rigid
from crfdepth.errors import InputError
from crfdepth.geometry.rigid import axis_rotation, invert_rigid
from crfdepth.io.files import check_input_file, read_text
from crfdepth.io.key_values import entry_array, read_key_values
from crfdepth.sequences.pose_checks import check_poses

__all__ = [
    "oxts_to_pose",
    "read_imu_to_velo",
    "read_kitti_poses",
    "read_oxts",
]

POSE_TOLERANCE = 1e-3
"""Largest |R^T R - I| accepted in a pose file (KITTI writes 6-7 significant digits)."""

MAX_POSE_STEP_M = 100.0
"""Largest step (metres) between consecutive poses of a file whose frame rate is not known: 2.5 s at the
40 m/s of :func:`~crfdepth.sequences.pose_checks.check_poses`; a longer one is a glitch or another unit."""


# --------------------------------------------------------------------------- poses given


def _numbers(line: str, path: Path, lineno: int, count: int, what: str) -> np.ndarray:
    tokens = line.split()
    if len(tokens) != count:
        raise InputError(f"{what}: expected {count} numbers per line in {path}, got {len(tokens)} on line {lineno}")
    try:
        return np.array([float(t) for t in tokens])
    except ValueError:
        raise InputError(f"{what}: expected numbers in {path}, got {line.strip()[:60]!r} on line {lineno}") from None


def _check_pose(T: np.ndarray, path: Path, lineno: int, what: str) -> None:
    if not np.isfinite(T).all():
        raise InputError(f"{what}: expected finite numbers in {path}, got a non-finite value on line {lineno}")
    dev = float(np.max(np.abs(T[:3, :3].T @ T[:3, :3] - np.eye(3))))
    if dev > POSE_TOLERANCE or np.linalg.det(T[:3, :3]) < 0:
        raise InputError(f"{what}: expected rigid poses (an orthonormal rotation) in {path}, got max "
                         f"|R^T R - I| = {dev:.3g}, det {np.linalg.det(T[:3, :3]):.3g} on line {lineno}")


def _check_steps(poses: np.ndarray, lines: list[int], path: Path, what: str, rate: float | None,
                 unit: str = "line") -> None:
    """Refuse an impossible step between consecutive poses (metres, degrees), as ``/tf`` odometry is refused
    (:func:`crfdepth.sequences.pose_checks.check_poses`, docs/design.md section 12): with ``rate`` (Hz; the
    poses are of consecutive frames at that rate) its speed, yaw-rate and jump checks; without, a step over
    :data:`MAX_POSE_STEP_M`. ``lines``: the line (or file) of each pose, for the message."""
    if rate is not None:
        failures = check_poses(poses, rate=rate)
    else:
        steps = np.linalg.norm(np.diff(poses[:, :3, 3], axis=0), axis=1)
        failures = [(k + 1, f"moved {steps[k]:.2f} m in one step (> {MAX_POSE_STEP_M:g} m between consecutive "
                            "poses)") for k in np.flatnonzero(steps > MAX_POSE_STEP_M)]
    if failures:
        listed = "; ".join(f"{unit} {lines[k]}: {why}" for k, why in failures[:3])
        more = f"; and {len(failures) - 3} more" if len(failures) > 3 else ""
        raise InputError(f"{what}: expected poses without impossible steps in {path}, got {len(failures)} "
                         f"failed step(s) ({listed}{more})")


def _check_count(poses: np.ndarray, n_frames: int | None, path: Path, what: str) -> np.ndarray:
    if n_frames is not None:
        if len(poses) < n_frames:
            raise InputError(f"{what}: expected at least {n_frames} poses (one per frame) in {path}, got {len(poses)}")
        poses = poses[:n_frames]
    return poses


def _to_lidar(poses_a: np.ndarray, T_a_lidar) -> np.ndarray:
    """World<-sensor-a poses to ``T_lidar(0)<-lidar(t) = T_a_lidar^-1 A(0)^-1 A(t) T_a_lidar``."""
    first = invert_rigid(poses_a[0])
    inv_ext = invert_rigid(T_a_lidar)
    return np.stack([inv_ext @ first @ P @ T_a_lidar for P in poses_a])


def read_kitti_poses(path, T_cam0_lidar=None, *, n_frames: int | None = None,
                     rate: float | None = None) -> np.ndarray:
    """Read a KITTI odometry ``poses.txt``: one ``[R | t]`` of camera 0 per line (12 numbers).

    Args:
        path: the text file.
        T_cam0_lidar: (4, 4) Velodyne -> rectified camera-0 transform (the odometry
            calibration's ``Tr``; for raw data ``R_rect_00 @ T_velo_to_cam``, i.e.
            :meth:`crfdepth.io.calibration.Calibration.velo_to_rect_cam`). None: return the
            camera-0 poses as written.
        n_frames: the number of frames the poses are for; more poses are cut, fewer raise.
        rate: frames per second when the lines are consecutive frames (KITTI: 10 Hz): each step is checked
            as ``/tf`` odometry is (:func:`crfdepth.sequences.pose_checks.check_poses`: speed, yaw rate,
            jumps). None (rate unknown): only a step over :data:`MAX_POSE_STEP_M` (100 m) is refused.

    Returns:
        (n, 4, 4) float64: with ``T_cam0_lidar`` the LiDAR poses
        ``T_lidar(0)<-lidar(t) = Tr^-1 P(0)^-1 P(t) Tr``; without, the camera-0 poses ``P(t)``.

    Raises:
        FileNotFoundError: no such file.
        InputError: a line without 12 numbers, a non-finite or non-rigid pose, an impossible step
            between consecutive poses, fewer than ``n_frames`` poses (the message names the file and line).
    """
    path = check_input_file(path, "poses")
    rows, linenos = [], []
    for lineno, line in enumerate(read_text(path, "poses", "12 numbers per line").splitlines(), 1):
        if not line.strip():
            continue
        T = np.eye(4)
        T[:3, :] = _numbers(line, path, lineno, 12, "poses").reshape(3, 4)
        _check_pose(T, path, lineno, "poses")
        rows.append(T)
        linenos.append(lineno)
    if not rows:
        raise InputError(f"poses: expected 12 numbers per line in {path}, got an empty file")
    poses = _check_count(np.stack(rows), n_frames, path, "poses")
    _check_steps(poses, linenos, path, "poses", rate)
    if T_cam0_lidar is None:
        return poses
    return _to_lidar(poses, check_rigid(T_cam0_lidar, "T_cam0_lidar"))


EARTH_RADIUS_M = 6378137.0
"""The KITTI devkit's earth radius for the Mercator projection of oxts positions."""
OXTS_VALUES = 30


def oxts_to_pose(packet: np.ndarray, scale: float) -> np.ndarray:
    """(4, 4) world<-IMU pose of one oxts packet (lat, lon, alt, roll, pitch, yaw, ...).

    The KITTI devkit's ``convertOxtsToPose``: Mercator position ``x = scale lon pi er / 180``,
    ``y = scale er log(tan((90 + lat) pi / 360))``, ``z = alt``, with ``scale`` = cos of the
    first latitude and ``er`` = 6378137 m; rotation ``Rz(yaw) Ry(pitch) Rx(roll)`` (x east,
    y north, z up).
    """
    lat, lon, alt, roll, pitch, yaw = packet[:6]
    T = np.eye(4)
    T[0, 3] = scale * lon * math.pi * EARTH_RADIUS_M / 180.0
    T[1, 3] = scale * EARTH_RADIUS_M * math.log(math.tan((90.0 + lat) * math.pi / 360.0))
    T[2, 3] = alt
    T[:3, :3] = axis_rotation(2, yaw) @ axis_rotation(1, pitch) @ axis_rotation(0, roll)
    return T


def read_imu_to_velo(day_dir) -> np.ndarray:
    """(4, 4) ``T_velo_imu`` (IMU -> Velodyne) from a KITTI raw day's ``calib_imu_to_velo.txt``."""
    day_dir = Path(day_dir)
    path = check_input_file(day_dir / "calib_imu_to_velo.txt" if day_dir.is_dir() else day_dir, "calibration")
    entries = read_key_values(path, "calibration")
    T = np.eye(4)
    T[:3, :3] = entry_array(entries, "R", (3, 3), path)
    T[:3, 3] = entry_array(entries, "T", (3,), path)
    return check_rigid(T, f"calibration: keys 'R', 'T' in {path}")


def read_oxts(folder, T_velo_imu=None, *, n_frames: int | None = None, rate: float | None = None) -> np.ndarray:
    """Read a KITTI raw drive's GPS/IMU poses (``oxts/data/0000000000.txt`` ...).

    Args:
        folder: the ``oxts`` folder (holding ``data/``) or its ``data`` folder.
        T_velo_imu: (4, 4) IMU -> Velodyne (:func:`read_imu_to_velo`). None: return the
            IMU poses relative to the first, ``T_imu(0)<-imu(t)``.
        n_frames: the number of frames; more packets are cut, fewer raise.
        rate: packets per second (KITTI: 10 Hz), each step then checked as ``/tf`` odometry is; None: only a
            step over :data:`MAX_POSE_STEP_M` is refused (:func:`read_kitti_poses`).

    Returns:
        (n, 4, 4) float64: with ``T_velo_imu``, ``T_lidar(0)<-lidar(t) =
        T_velo_imu T_imu(0)<-imu(t) T_velo_imu^-1``.

    Raises:
        FileNotFoundError: no such folder, or no ``.txt`` files in it.
        InputError: a file without 30 numbers on its first line, a latitude outside
            (-90, 90), an impossible step between consecutive packets, fewer than ``n_frames`` packets (the
            message names the file).
    """
    folder = Path(folder)
    data = folder / "data" if (folder / "data").is_dir() else folder
    if not data.is_dir():
        raise FileNotFoundError(f"oxts: no such directory: {folder}")
    files = sorted(data.glob("*.txt"))
    if not files:
        raise FileNotFoundError(f"oxts: no .txt files in {data}")
    packets = []
    for f in files:
        lines = [ln for ln in read_text(f, "oxts", f"{OXTS_VALUES} numbers").splitlines() if ln.strip()]
        if not lines:
            raise InputError(f"oxts: expected {OXTS_VALUES} numbers per line in {f}, got an empty file")
        p = _numbers(lines[0], f, 1, OXTS_VALUES, "oxts")
        if not np.isfinite(p[:6]).all() or not -90.0 < p[0] < 90.0:
            raise InputError(f"oxts: expected a latitude in (-90, 90) degrees and finite values in {f}, "
                             f"got lat {p[0]!r} on line 1")
        packets.append(p)
    packets = np.stack(packets)
    if n_frames is not None and len(packets) < n_frames:
        raise InputError(f"oxts: expected at least {n_frames} packets (one per frame) in {data}, got {len(packets)}")
    if n_frames is not None:
        packets = packets[:n_frames]
    scale = math.cos(math.radians(packets[0, 0]))
    poses = np.stack([oxts_to_pose(p, scale) for p in packets])
    _check_steps(poses, [f.name for f in files[:len(poses)]], data, "oxts", rate, unit="file")
    if T_velo_imu is None:
        first = invert_rigid(poses[0])
        return np.stack([first @ P for P in poses])
    return _to_lidar(poses, invert_rigid(check_rigid(T_velo_imu, "T_velo_imu")))
