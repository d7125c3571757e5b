"""Poses of a recording: LiDAR odometry from the scans, or poses given (docs/design.md section 12).

- :func:`lidar_odometry`: scan-to-map registration with KISS-ICP (Vizzo et al. 2023, the
  optional extra ``pip install "crfdepth[odometry]"``), with a check of every step that
  reports failures by frame instead of accumulating them.
- :func:`read_kitti_poses`: KITTI odometry ``poses.txt`` (camera-0 poses, 12 numbers a line).
- :func:`read_oxts`: KITTI raw ``oxts/data/*.txt`` (GPS/IMU), the devkit's Mercator
  conversion; :func:`read_imu_to_velo` reads the day's ``calib_imu_to_velo.txt``.
- :func:`camera_relative_pose`: the camera's motion through the fixed extrinsic.

Convention: every function returns LiDAR poses ``T_world<-lidar(t)`` as (n, 4, 4) float64,
``p_world = T @ p_lidar``, with the world = the LiDAR frame of the first scan (the first
pose is the identity). LiDAR frame: KITTI Velodyne axes (x forward, y left, z up, metres).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from crfdepth.checks import check_rigid
from crfdepth.errors import InputError
from crfdepth.io.files import check_input_file, read_text

__all__ = [
    "Odometry",
    "camera_relative_pose",
    "check_poses",
    "lidar_odometry",
    "read_imu_to_velo",
    "read_kitti_poses",
    "read_oxts",
]

EXTRA_HINT = 'pip install "crfdepth[odometry]"'
POSE_TOLERANCE = 1e-3
"""Largest |R^T R - I| accepted in a pose file (KITTI writes 6-7 significant digits)."""


def _rotation_deg(R: np.ndarray) -> float:
    """Angle of a rotation matrix, degrees."""
    c = (np.trace(R) - 1.0) / 2.0
    return math.degrees(math.acos(min(1.0, max(-1.0, c))))


def _inv(T: np.ndarray) -> np.ndarray:
    """Inverse of a rigid (4, 4) transform."""
    out = np.eye(4)
    out[:3, :3] = T[:3, :3].T
    out[:3, 3] = -T[:3, :3].T @ T[:3, 3]
    return out


def camera_relative_pose(T_w_lidar_s, T_w_lidar_t, T_cam_lidar) -> np.ndarray:
    """``T_cam(s)<-cam(t) = T_cam_lidar T_lidar(s)<-lidar(t) T_cam_lidar^-1`` (design 3c).

    Args:
        T_w_lidar_s, T_w_lidar_t: (4, 4) world<-LiDAR poses at times s and t.
        T_cam_lidar: (4, 4) LiDAR-to-camera extrinsic (rigidly mounted).

    Returns:
        (4, 4) float64: maps points of camera frame t into camera frame s.
    """
    T_cam_lidar = check_rigid(T_cam_lidar, "T_cam_lidar")
    s = check_rigid(T_w_lidar_s, "T_w_lidar_s")
    t = check_rigid(T_w_lidar_t, "T_w_lidar_t")
    return T_cam_lidar @ _inv(s) @ t @ _inv(T_cam_lidar)


@dataclass(frozen=True)
class Odometry:
    """Poses of a sequence of scans with per-step diagnostics.

    Attributes:
        poses: (n, 4, 4) float64 ``T_world<-lidar(t)``; the first is the identity.
        step_translation: (n,) metres moved since the previous scan (0 for the first).
        step_rotation_deg: (n,) degrees turned since the previous scan (0 for the first).
        correction: (n,) metres between the constant-velocity prediction and the ICP
            result (how much the registration had to correct; 0 for the first).
        fitness: (n,) share of the scan's registration points within ``inlier_m`` of the
            map after registration (1 for the first; NaN where not computed).
        residual: (n,) metres, median distance of those inliers to the map (NaN: not computed).
        points: (n,) points of each scan within the range limits.
        failures: ``(frame, reason)`` pairs found by :func:`check_poses`; empty when
            every step passed.
        rate: scans per second used for the speed checks.
    """

    poses: np.ndarray
    step_translation: np.ndarray
    step_rotation_deg: np.ndarray
    correction: np.ndarray
    fitness: np.ndarray
    residual: np.ndarray
    points: np.ndarray
    failures: tuple[tuple[int, str], ...]
    rate: float

    def __len__(self) -> int:
        return len(self.poses)

    @property
    def speeds(self) -> np.ndarray:
        """(n - 1,) m/s between consecutive scans."""
        return self.step_translation[1:] * self.rate

    def camera_relative(self, s: int, t: int, T_cam_lidar) -> np.ndarray:
        """``T_cam(s)<-cam(t)`` of scans s and t (:func:`camera_relative_pose`)."""
        return camera_relative_pose(self.poses[s], self.poses[t], T_cam_lidar)


def _steps(poses: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    n = len(poses)
    trans, rot = np.zeros(n), np.zeros(n)
    for k in range(1, n):
        d = _inv(poses[k - 1]) @ poses[k]
        trans[k] = float(np.linalg.norm(d[:3, 3]))
        rot[k] = _rotation_deg(d[:3, :3])
    return trans, rot


def check_poses(
    poses,
    *,
    rate: float = 10.0,
    max_speed: float = 40.0,
    max_yaw_rate: float = 60.0,
    jump_m: float = 0.5,
    points=None,
    min_points: int = 1000,
    fitness=None,
    min_fitness: float = 0.5,
) -> list[tuple[int, str]]:
    """Failures of a pose sequence by frame (an empty list: every step is plausible).

    A frame ``k`` fails when the step from ``k - 1`` to ``k``

    - moves faster than ``max_speed`` m/s or turns faster than ``max_yaw_rate`` deg/s;
    - differs in length by more than ``max(jump_m, 30 %)`` from the median of its
      neighbours' steps (``k-2 .. k+2``; a vehicle cannot change speed that fast at 10 Hz);

    or when scan ``k`` has fewer than ``min_points`` points (``points`` given) or a
    registration fitness below ``min_fitness`` (``fitness`` given).

    Returns:
        ``[(frame, reason), ...]`` sorted by frame.
    """
    poses = np.asarray(poses, dtype=np.float64)
    trans, rot = _steps(poses)
    n = len(poses)
    found: dict[int, list[str]] = {}
    dt = 1.0 / rate
    for k in range(1, n):
        if trans[k] > max_speed * dt:
            found.setdefault(k, []).append(
                f"moved {trans[k]:.2f} m in one step (> {max_speed * dt:.2f} m at max_speed {max_speed:g} m/s)")
        if rot[k] > max_yaw_rate * dt:
            found.setdefault(k, []).append(
                f"turned {rot[k]:.2f} deg in one step (> {max_yaw_rate * dt:.2f} deg at max_yaw_rate "
                f"{max_yaw_rate:g} deg/s)")
        neighbours = [trans[j] for j in range(max(1, k - 2), min(n, k + 3)) if j != k]
        if neighbours:
            ref = float(np.median(neighbours))
            if abs(trans[k] - ref) > max(jump_m, 0.3 * ref):
                found.setdefault(k, []).append(
                    f"step of {trans[k]:.2f} m against {ref:.2f} m for its neighbours (a jump)")
    if points is not None:
        for k, count in enumerate(points):
            if count < min_points:
                found.setdefault(k, []).append(f"{int(count)} points (< min_points {min_points}): a degenerate scan")
    if fitness is not None:
        for k, f in enumerate(fitness):
            if np.isfinite(f) and f < min_fitness:
                found.setdefault(k, []).append(
                    f"only {100 * f:.0f} % of its points fit the map (< {100 * min_fitness:.0f} %)")
    return [(k, "; ".join(found[k])) for k in sorted(found)]


def _scan_array(scan, k: int) -> np.ndarray:
    a = np.asarray(scan)
    if a.ndim != 2 or a.shape[1] < 3 or not np.issubdtype(a.dtype, np.number):
        raise InputError(f"scans[{k}]: expected (N, 3) or (N, 4) points, got an array of shape {a.shape} "
                         f"({a.dtype})")
    pts = np.ascontiguousarray(a[:, :3], dtype=np.float64)
    return pts[np.isfinite(pts).all(axis=1)]


def _kiss():
    try:
        from kiss_icp.config import KISSConfig
        from kiss_icp.kiss_icp import KissICP
    except ImportError:
        raise InputError(f"lidar_odometry: expected the kiss-icp package (LiDAR odometry), got it not "
                         f"installed; {EXTRA_HINT}") from None
    return KISSConfig, KissICP


def lidar_odometry(
    scans: Sequence,
    *,
    voxel_size: float | None = None,
    max_range: float = 100.0,
    min_range: float = 3.0,
    rate: float = 10.0,
    max_speed: float = 40.0,
    max_yaw_rate: float = 60.0,
    min_points: int = 1000,
    min_fitness: float = 0.5,
    min_z: float | None = None,
    initial_motion=None,
    deskew: bool = False,
    threads: int = 0,
    check: bool = True,
) -> Odometry:
    """LiDAR odometry of consecutive scans with KISS-ICP, every step checked.

    Args:
        scans: sequence of (N, 3+) arrays in the LiDAR frame (x, y, z metres; further
            columns ignored), in time order, one scan per ``1 / rate`` seconds.
        voxel_size: the map's voxel size, metres; None: 1 % of the scans' range (the first
            scan's 99th percentile range, capped by ``max_range``), at least 0.1 m.
        max_range, min_range: points outside [min_range, max_range] metres are not used
            (the default ``min_range`` drops returns from the ego car's roof).
        rate: scans per second (10 for KITTI); used by the checks.
        max_speed, max_yaw_rate, min_points, min_fitness: see :func:`check_poses`.
        min_z: drop points below this height in the LiDAR frame (metres, z up), e.g. -1.5
            to drop a flat ground 1.73 m below KITTI's LiDAR. A perfectly flat ground
            returns the same rings in every scan and pulls point-to-point ICP towards zero
            motion (the synthetic street); real ground is rough enough. None: keep all.
        initial_motion: (4, 4) expected motion of the first step ``T_lidar(0)<-lidar(1)``
            (e.g. from wheel speed, or the last step of the previous part of a split
            sequence); KISS-ICP predicts every step from the previous one, and the first
            from standstill. None: the identity.
        deskew: let KISS-ICP correct the motion during a sweep (per-point timestamps taken
            from the azimuth, as KISS-ICP does for KITTI); off by default.
        threads: threads of the registration (0: all cores).
        check: raise :class:`InputError` naming the failing frames (True), or only list them
            in ``failures`` (False).

    Returns:
        :class:`Odometry`, poses ``T_world<-lidar(t)`` with the first scan's frame as the world.

    Raises:
        InputError: kiss-icp is not installed (the message names the extra), fewer than two
            scans, a scan is not (N, 3+), or (``check``) a step failed.
    """
    KISSConfig, KissICP = _kiss()
    scans = list(scans)
    if len(scans) < 2:
        raise InputError(f"scans: expected at least 2 scans for odometry, got {len(scans)}")
    if not (max_range > min_range >= 0):
        raise InputError(f"max_range: expected a value > min_range ({min_range:g}) >= 0, got {max_range!r}")
    arrays = [_scan_array(s, k) for k, s in enumerate(scans)]
    if min_z is not None:
        arrays = [a[a[:, 2] >= min_z] for a in arrays]
    ranges = [np.linalg.norm(a, axis=1) for a in arrays]
    counts = np.array([int(((r >= min_range) & (r <= max_range)).sum()) for r in ranges])
    if voxel_size is None:
        r0 = ranges[0][(ranges[0] >= min_range)]
        reach = min(max_range, float(np.percentile(r0, 99))) if r0.size else max_range
        voxel_size = max(0.1, reach / 100.0)
    if not (isinstance(voxel_size, (int, float)) and 0 < voxel_size < max_range):
        raise InputError(f"voxel_size: expected metres in (0, max_range), got {voxel_size!r}")

    config = KISSConfig()
    config.data.max_range = float(max_range)
    config.data.min_range = float(min_range)
    config.data.deskew = bool(deskew)
    config.mapping.voxel_size = float(voxel_size)
    config.registration.max_num_threads = int(threads)
    icp = KissICP(config)

    from scipy.spatial import cKDTree

    n = len(arrays)
    poses = np.zeros((n, 4, 4))
    correction, fitness, residual = np.zeros(n), np.full(n, np.nan), np.full(n, np.nan)
    fitness[0] = 1.0
    inlier_m = 3.0 * float(voxel_size)
    for k, pts in enumerate(arrays):
        predicted = icp.last_pose @ icp.last_delta
        if deskew:
            stamps = 0.5 * (-np.arctan2(pts[:, 1], pts[:, 0]) / np.pi + 1.0)
        else:
            stamps = np.zeros(0)
        map_before = icp.local_map.point_cloud() if k > 0 else None
        _, source = icp.register_frame(pts, stamps)
        poses[k] = icp.last_pose
        if k == 0 and initial_motion is not None:
            icp.last_delta = check_rigid(initial_motion, "initial_motion")
        if k > 0:
            correction[k] = float(np.linalg.norm((_inv(predicted) @ poses[k])[:3, 3]))
            if len(map_before) and len(source):
                src = source @ poses[k][:3, :3].T + poses[k][:3, 3]
                dist, _ = cKDTree(map_before).query(src, k=1, distance_upper_bound=inlier_m, workers=1)
                inl = np.isfinite(dist)
                fitness[k] = float(inl.mean())
                residual[k] = float(np.median(dist[inl])) if inl.any() else np.inf
            else:
                fitness[k] = 0.0
    trans, rot = _steps(poses)
    failures = check_poses(poses, rate=rate, max_speed=max_speed, max_yaw_rate=max_yaw_rate,
                           points=counts, min_points=min_points, fitness=fitness, min_fitness=min_fitness)
    odo = Odometry(poses=poses, step_translation=trans, step_rotation_deg=rot, correction=correction,
                   fitness=fitness, residual=residual, points=counts, failures=tuple(failures),
                   rate=float(rate))
    if check and failures:
        listed = ", ".join(f"{k} ({why})" for k, why in failures[:5])
        more = f" and {len(failures) - 5} more" if len(failures) > 5 else ""
        raise InputError(f"scans: expected LiDAR odometry without failures, got a failure at frame(s) "
                         f"{listed}{more}; split the sequence there or drop those scans")
    return odo


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


def _check_count(poses: np.ndarray, n_frames: int | None, path: Path, what: str) -> np.ndarray:
    if n_frames is not None:
        if len(poses) < n_frames:
            raise InputError(f"{what}: expected at least {n_frames} poses (one per frame) in {path}, got {len(poses)}")
        poses = poses[:n_frames]
    return poses


def _to_lidar(poses_a: np.ndarray, T_a_lidar) -> np.ndarray:
    """World<-sensor-a poses to ``T_lidar(0)<-lidar(t) = T_a_lidar^-1 A(0)^-1 A(t) T_a_lidar``."""
    first = _inv(poses_a[0])
    inv_ext = _inv(T_a_lidar)
    return np.stack([inv_ext @ first @ P @ T_a_lidar for P in poses_a])


def read_kitti_poses(path, T_cam0_lidar=None, *, n_frames: int | None = None) -> np.ndarray:
    """Read a KITTI odometry ``poses.txt``: one ``[R | t]`` of camera 0 per line (12 numbers).

    Args:
        path: the text file.
        T_cam0_lidar: (4, 4) Velodyne -> rectified camera-0 transform (the odometry
            calibration's ``Tr``; for raw data ``R_rect_00 @ T_velo_to_cam``, i.e.
            :meth:`crfdepth.io.calibration.Calibration.velo_to_rect_cam`). None: return the
            camera-0 poses as written.
        n_frames: the number of frames the poses are for; more poses are cut, fewer raise.

    Returns:
        (n, 4, 4) float64: with ``T_cam0_lidar`` the LiDAR poses
        ``T_lidar(0)<-lidar(t) = Tr^-1 P(0)^-1 P(t) Tr``; without, the camera-0 poses ``P(t)``.

    Raises:
        FileNotFoundError: no such file.
        InputError: a line without 12 numbers, a non-rigid pose, fewer than ``n_frames``
            poses (the message names the file and line).
    """
    path = check_input_file(path, "poses")
    rows = []
    for lineno, line in enumerate(read_text(path, "poses", "12 numbers per line").splitlines(), 1):
        if not line.strip():
            continue
        T = np.eye(4)
        T[:3, :] = _numbers(line, path, lineno, 12, "poses").reshape(3, 4)
        _check_pose(T, path, lineno, "poses")
        rows.append(T)
    if not rows:
        raise InputError(f"poses: expected 12 numbers per line in {path}, got an empty file")
    poses = _check_count(np.stack(rows), n_frames, path, "poses")
    if T_cam0_lidar is None:
        return poses
    return _to_lidar(poses, check_rigid(T_cam0_lidar, "T_cam0_lidar"))


EARTH_RADIUS_M = 6378137.0
"""The KITTI devkit's earth radius for the Mercator projection of oxts positions."""
OXTS_VALUES = 30


def _rot(axis: int, a: float) -> np.ndarray:
    c, s = math.cos(a), math.sin(a)
    i, j = [(1, 2), (2, 0), (0, 1)][axis]
    R = np.eye(3)
    R[i, i], R[i, j], R[j, i], R[j, j] = c, -s, s, c
    return R


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
    T[:3, :3] = _rot(2, yaw) @ _rot(1, pitch) @ _rot(0, roll)
    return T


def read_imu_to_velo(day_dir) -> np.ndarray:
    """(4, 4) ``T_velo_imu`` (IMU -> Velodyne) from a KITTI raw day's ``calib_imu_to_velo.txt``."""
    from crfdepth.io.calibration import _matrix, _read_key_values

    day_dir = Path(day_dir)
    path = check_input_file(day_dir / "calib_imu_to_velo.txt" if day_dir.is_dir() else day_dir, "calibration")
    entries = _read_key_values(path, "calibration")
    T = np.eye(4)
    T[:3, :3] = _matrix(entries, "R", (3, 3), path)
    T[:3, 3] = _matrix(entries, "T", (3,), path)
    return check_rigid(T, f"calibration: keys 'R', 'T' in {path}")


def read_oxts(folder, T_velo_imu=None, *, n_frames: int | None = None) -> np.ndarray:
    """Read a KITTI raw drive's GPS/IMU poses (``oxts/data/0000000000.txt`` ...).

    Args:
        folder: the ``oxts`` folder (holding ``data/``) or its ``data`` folder.
        T_velo_imu: (4, 4) IMU -> Velodyne (:func:`read_imu_to_velo`). None: return the
            IMU poses relative to the first, ``T_imu(0)<-imu(t)``.
        n_frames: the number of frames; more packets are cut, fewer raise.

    Returns:
        (n, 4, 4) float64: with ``T_velo_imu``, ``T_lidar(0)<-lidar(t) =
        T_velo_imu T_imu(0)<-imu(t) T_velo_imu^-1``.

    Raises:
        FileNotFoundError: no such folder, or no ``.txt`` files in it.
        InputError: a file without 30 numbers on its first line, a latitude outside
            (-90, 90), fewer than ``n_frames`` packets (the message names the file).
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
    if T_velo_imu is None:
        first = _inv(poses[0])
        return np.stack([first @ P for P in poses])
    return _to_lidar(poses, _inv(check_rigid(T_velo_imu, "T_velo_imu")))
