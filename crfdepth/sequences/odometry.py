"""Poses of a recording: LiDAR odometry from the scans, or poses given (docs/design.md section 12).

- :func:`lidar_odometry`: scan-to-map registration with KISS-ICP (Vizzo et al. 2023, the
  optional extra ``pip install "crfdepth[odometry]"``), with a check of every step that
  reports failures by frame instead of accumulating them: speed, jumps, points, fitness, and
  the registration itself (:func:`step_alignment`: the scan's structure, ground removed,
  must fit the previous scan best at the estimate); :func:`lidar_odometry_with_fallback`
  retries without the ground when the registration slid (a perfectly flat ground).
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
from crfdepth.io.key_values import entry_array, read_key_values

__all__ = [
    "Alignment",
    "Odometry",
    "camera_relative_pose",
    "check_poses",
    "ground_plane",
    "lidar_odometry",
    "lidar_odometry_with_fallback",
    "read_imu_to_velo",
    "read_kitti_poses",
    "read_oxts",
    "scan_structure",
    "step_alignment",
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
        alignment: (n, 3) per step, the offset from the estimate at which scan t's structure
            fits scan t-1 best: x, y (metres), turn about z (degrees) (:func:`step_alignment`;
            zeros for the first scan); None when not computed.
        alignment_share: (n,) share of scan t's compared structure points near scan t-1's at
            the estimate (1 for the first scan; NaN: too little structure); None when not computed.
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
    alignment: np.ndarray | None = None
    alignment_share: np.ndarray | None = None

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
    alignment=None,
    max_alignment_m: float | None = None,
    max_alignment_deg: float | None = None,
) -> list[tuple[int, str]]:
    """Failures of a pose sequence by frame (an empty list: every step is plausible).

    A frame ``k`` fails when the step from ``k - 1`` to ``k``

    - moves faster than ``max_speed`` m/s or turns faster than ``max_yaw_rate`` deg/s;
    - differs in length by more than ``max(jump_m, 30 %)`` from the median of its
      neighbours' steps (``k-2 .. k+2``; a vehicle cannot change speed that fast at 10 Hz);

    or when scan ``k`` has fewer than ``min_points`` points (``points`` given), a
    registration fitness below ``min_fitness`` (``fitness`` given), or (``alignment`` given:
    one :class:`Alignment` or None per frame, :func:`step_alignment`) its structure fits scan
    ``k - 1`` best more than ``max_alignment_m`` (default ``MAX_ALIGN_OFFSET_M``, 0.3 m) along
    x or y or ``max_alignment_deg`` (default ``MAX_ALIGN_OFFSET_DEG``, 0.5 deg) about z away from
    the estimated step: a registration that slid, which the speed and jump checks miss when
    every step slides alike (the flat synthetic street with the command's defaults).

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
    if alignment is not None:
        max_m = MAX_ALIGN_OFFSET_M if max_alignment_m is None else max_alignment_m
        max_deg = MAX_ALIGN_OFFSET_DEG if max_alignment_deg is None else max_alignment_deg
        for k, a in enumerate(alignment):
            why = a.failure(max_m, max_deg) if a is not None and k > 0 else None
            if why:
                found.setdefault(k, []).append(why)
    return [(k, "; ".join(found[k])) for k in sorted(found)]


# --------------------------------------------------------------------------- registration quality

# Constants of :func:`step_alignment` (docs/design.md section 12, "Registration check"). Measured
# with these values (tests/test_odometry.py): on drive 2011_09_26_drive_0060 (all 77 steps, the
# KISS-ICP poses) the best offset is at most 0.17 m along x, 0.02 m along y, 0.09 deg about z
# (medians 0.06 m, 0.004 m, 0.02 deg); on the flat synthetic street its true poses give at most
# 0.05 m and 0.01 deg, the command's defaults' failed poses (1 m short per 1 m step at 10 m/s)
# 1 m (the edge of the search), an injected 1 m / 5 deg error 1 m / 2 deg (the edges).
ALIGN_HINT_KEY = "fits the previous scan best"
"""Part of the reason :meth:`Alignment.failure` gives (callers pick their advice by it)."""
ALIGN_ABOVE_GROUND_M = 0.3
"""Structure = returns more than this above the scan's ground plane (curbs are ~0.15 m)."""
ALIGN_MAX_RANGE_M = 50.0
"""Only returns within this range are compared (beyond, a scan's rings are sparse)."""
ALIGN_SAMPLE = 500
"""Structure points of scan t compared (a fixed-seed subsample: the same scans give the same result)."""
ALIGN_CAP_M = 1.0
"""Distances to the previous scan are capped here (outliers, movers and new structure count as 1 m)."""
ALIGN_SHIFTS_M = tuple(np.round(np.arange(-1.0, 1.0001, 0.25), 2))
"""Shifts tried along the previous scan's x and y axes, metres."""
ALIGN_YAWS_DEG = tuple(np.round(np.arange(-2.0, 2.0001, 0.5), 2))
"""Turns about the scan's vertical tried, degrees."""
MAX_ALIGN_OFFSET_M = 0.3
"""Largest accepted distance from the estimate to the best shift along x or y: 1.7x the real drive's
largest (0.17 m), 6x the synthetic true poses' (0.05 m). Smaller errors pass (the synthetic
defaults at 2 m/s, 0.2 m short per step, are not caught)."""
MAX_ALIGN_OFFSET_DEG = 0.5
"""Largest accepted angle from the estimate to the best turn: 5x the real drive's largest (0.09 deg)."""


def scan_structure(points, *, min_range: float = 3.0, max_range: float = ALIGN_MAX_RANGE_M) -> np.ndarray:
    """The returns of a scan that constrain its motion along the road: more than
    ``ALIGN_ABOVE_GROUND_M`` (0.3 m) above the scan's ground plane, within [min_range, max_range].

    The ground plane is :func:`ground_plane`'s (within the range limits). A scan without a ground
    plane keeps all its returns in range.

    Args:
        points: (N, 3+) finite points in the LiDAR frame, metres, z up.

    Returns:
        (M, 3) float64.
    """
    pts = np.asarray(points, dtype=np.float64)[:, :3]
    r = np.linalg.norm(pts, axis=1)
    pts = pts[(r >= min_range) & (r <= max_range)]
    plane = ground_plane(pts)
    if plane is None:
        return pts
    normal, ground = plane
    return pts[pts @ normal > ground + ALIGN_ABOVE_GROUND_M]


def ground_plane(points) -> tuple[np.ndarray, float] | None:
    """The ground of a scan as ``(normal, height)``: points ``p`` on it have ``p @ normal ~ height``
    (negative: below the sensor), or None (no ground plane found).

    The normal is :func:`crfdepth.geometry.projection.ground_normal`'s (RANSAC, on at most 5000 returns of
    a fixed-seed subsample); the height is the 0.1 m bin of ``p @ normal`` below
    ``-ALIGN_ABOVE_GROUND_M`` holding the most returns; both are then refined by a least-squares
    plane through the returns within 0.15 m of it. Measured: -1.71 to -1.77 m on drive
    2011_09_26_drive_0060 (KITTI's LiDAR sits 1.73 m up), -1.64 to -1.73 m on the synthetic street.

    Args:
        points: (N, 3+) finite points in the LiDAR frame, metres, z up.
    """
    from crfdepth.geometry.projection import ground_normal

    pts = np.asarray(points, dtype=np.float64)[:, :3]
    if len(pts) < 3:
        return None
    rng = np.random.default_rng(0)
    sub = pts[rng.choice(len(pts), 5000, replace=False)] if len(pts) > 5000 else pts
    normal = ground_normal(sub)
    if normal is None:
        return None
    height = pts @ normal
    below = height[height < -ALIGN_ABOVE_GROUND_M]
    if below.size == 0:
        return None
    counts, edges = np.histogram(below, bins=np.arange(below.min(), 0.0, 0.1))
    if counts.size == 0:
        return None
    ground = float(edges[int(np.argmax(counts))] + 0.05)
    # refined by least squares on the returns within 0.15 m of that plane (RANSAC's plane through
    # three returns is tilted by up to ~1 deg on the synthetic street, 0.25 m at 15 m to the side)
    near = pts[np.abs(height - ground) < 0.15]
    if len(near) >= 3:
        near = near[rng.choice(len(near), 20000, replace=False)] if len(near) > 20000 else near
        centre = near.mean(axis=0)
        refined = np.linalg.svd(near - centre, full_matrices=False)[2][2]
        refined = refined if refined @ normal > 0 else -refined
        if refined @ normal > math.cos(math.radians(5.0)):
            normal, ground = refined, float(centre @ refined)
    return normal, ground


@dataclass(frozen=True)
class Alignment:
    """How well one odometry step lays scan t's structure on scan t-1's (:func:`step_alignment`).

    Attributes:
        offset: (3,) the best shift along x, y (metres) and turn about z (degrees) of scan t
            from the estimated pose, each searched on its own around the estimate.
        residual: mean capped distance (metres) of the structure at the estimated pose.
        best: the lowest mean capped distance found (metres).
        share: share of the compared points within ``0.05 m + 1 %`` of their range of scan t-1's
            structure at the estimated pose (reported, not checked: it does not separate; see
            docs/design.md section 12).
    """

    offset: np.ndarray
    residual: float
    best: float
    share: float

    def failure(self, max_offset_m: float = MAX_ALIGN_OFFSET_M,
                max_offset_deg: float = MAX_ALIGN_OFFSET_DEG) -> str | None:
        """A reason when the estimate is not where the scans align best, else None."""
        dx, dy, dyaw = (float(v) for v in self.offset)
        parts = []
        for name, v in (("x", dx), ("y", dy)):
            if abs(v) > max_offset_m:
                edge = "at least " if abs(v) >= ALIGN_SHIFTS_M[-1] else ""
                parts.append(f"{edge}{v:+.2f} m along {name}")
        if abs(dyaw) > max_offset_deg:
            edge = "at least " if abs(dyaw) >= ALIGN_YAWS_DEG[-1] else ""
            parts.append(f"{edge}{dyaw:+.2f} deg about z")
        if not parts:
            return None
        return (f"the registration slid: the scan's structure {ALIGN_HINT_KEY} {' and '.join(parts)} from "
                f"the estimate (limit {max_offset_m:g} m, {max_offset_deg:g} deg; mean distance {self.residual:.3f} m "
                f"at the estimate, {self.best:.3f} m at the best)")


def _refined(grid: np.ndarray, values: np.ndarray) -> float:
    """The minimum of sampled values: a parabola through the lowest sample and its neighbours."""
    i = int(np.argmin(values))
    if i == 0 or i == len(values) - 1:
        return float(grid[i])
    a, b, c = values[i - 1], values[i], values[i + 1]
    den = a + c - 2.0 * b
    step = float(grid[i + 1] - grid[i])
    return float(grid[i]) + (0.5 * step * (a - c) / den if den > 0 else 0.0)


def step_alignment(previous, current, relative, *, sample: int = ALIGN_SAMPLE, tree=None) -> Alignment:
    """Where scan ``current`` lies best on scan ``previous`` around the estimated step ``relative``.

    The registration's own fitness is measured against the map it converged into and passes a
    slid registration: along a straight road the ground and the façades look the same after any
    shift along it. This check uses the structure only (:func:`scan_structure`, the ground
    removed) and the previous scan itself (not the map the estimate built): ``sample`` structure
    points of ``current`` are mapped by ``relative`` and, separately, shifted along x and y by
    ``ALIGN_SHIFTS_M`` (-1 to 1 m) and turned about z by ``ALIGN_YAWS_DEG`` (-2 to 2 deg); the mean
    of their distances to ``previous``, capped at ``ALIGN_CAP_M``, is lowest at the best offset
    (a parabola through the lowest sample and its neighbours). A correct estimate is the best.

    Args:
        previous, current: (N, 3) structure of scans t-1 and t (:func:`scan_structure`).
        relative: (4, 4) estimated ``T_lidar(t-1)<-lidar(t)``.
        sample: points of ``current`` compared (a fixed-seed subsample).
        tree: a ``scipy.spatial.cKDTree`` of ``previous`` (built when None).

    Returns:
        :class:`Alignment`; offsets 0 and NaN distances when either scan has fewer than 20
        structure points (too little to compare: the point-count check covers such scans).
    """
    from scipy.spatial import cKDTree

    previous = np.asarray(previous, dtype=np.float64)
    current = np.asarray(current, dtype=np.float64)
    if len(previous) < 20 or len(current) < 20:
        return Alignment(offset=np.zeros(3), residual=float("nan"), best=float("nan"), share=float("nan"))
    tree = cKDTree(previous) if tree is None else tree
    rng = np.random.default_rng(0)
    pts = current[rng.choice(len(current), sample, replace=False)] if len(current) > sample else current
    T = np.asarray(relative, dtype=np.float64)

    def mean_distance(q: np.ndarray) -> tuple[float, np.ndarray]:
        d, _ = tree.query(q, k=1, distance_upper_bound=ALIGN_CAP_M, workers=1)
        d = np.minimum(d, ALIGN_CAP_M)
        return float(d.mean()), d

    q0 = pts @ T[:3, :3].T + T[:3, 3]
    residual, d0 = mean_distance(q0)
    share = float(np.mean(d0 <= 0.05 + 0.01 * np.linalg.norm(q0, axis=1)))
    shifts = np.array(ALIGN_SHIFTS_M)
    best = residual
    offsets = []
    for axis in (0, 1):
        values = []
        for s in shifts:
            v = residual if s == 0 else mean_distance(q0 + s * np.eye(3)[axis])[0]
            values.append(v)
        best = min(best, min(values))
        offsets.append(_refined(shifts, np.array(values)))
    yaws = np.array(ALIGN_YAWS_DEG)
    values = []
    for a in yaws:
        if a == 0:
            values.append(residual)
            continue
        R = _rot(2, math.radians(a))
        turned = pts @ R.T  # about scan t's own vertical, then the estimated step
        values.append(mean_distance(turned @ T[:3, :3].T + T[:3, 3])[0])
    best = min(best, min(values))
    offsets.append(_refined(yaws, np.array(values)))
    return Alignment(offset=np.array(offsets), residual=residual, best=best, share=share)


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
    check_alignment: bool = True,
    max_alignment_m: float = MAX_ALIGN_OFFSET_M,
    max_alignment_deg: float = MAX_ALIGN_OFFSET_DEG,
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
        check_alignment: check every step's registration against the previous scan itself
            (:func:`step_alignment` on :func:`scan_structure` of the full scans, whatever
            ``min_z``): the estimate must be where scan t's structure fits scan t-1 best, within
            ``max_alignment_m`` along x and y and ``max_alignment_deg`` about z. Adds about
            3 s to the 78 scans of a KITTI drive (2 cores).

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
    full = arrays
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
    aligned = offsets = shares = None
    if check_alignment:
        # the full scans (not min_z's): the ground plane is found and removed in each
        structure = [scan_structure(a, min_range=min_range, max_range=min(max_range, ALIGN_MAX_RANGE_M))
                     for a in full]
        aligned = [None] + [step_alignment(structure[k - 1], structure[k], _inv(poses[k - 1]) @ poses[k])
                            for k in range(1, n)]
        offsets = np.zeros((n, 3))
        shares = np.ones(n)
        for k in range(1, n):
            offsets[k], shares[k] = aligned[k].offset, aligned[k].share
    failures = check_poses(poses, rate=rate, max_speed=max_speed, max_yaw_rate=max_yaw_rate,
                           points=counts, min_points=min_points, fitness=fitness, min_fitness=min_fitness,
                           alignment=aligned, max_alignment_m=max_alignment_m,
                           max_alignment_deg=max_alignment_deg)
    odo = Odometry(poses=poses, step_translation=trans, step_rotation_deg=rot, correction=correction,
                   fitness=fitness, residual=residual, points=counts, failures=tuple(failures),
                   rate=float(rate), alignment=offsets, alignment_share=shares)
    if check and failures:
        listed = ", ".join(f"{k} ({why})" for k, why in failures[:5])
        more = f" and {len(failures) - 5} more" if len(failures) > 5 else ""
        hint = ("split the sequence there or drop those scans" if not any(ALIGN_HINT_KEY in why for _, why in failures)
                else "for a flat ground give min_z (drop it) and initial_motion, or give the poses")
        raise InputError(f"scans: expected LiDAR odometry without failures, got a failure at frame(s) "
                         f"{listed}{more}; {hint}")
    return odo


def lidar_odometry_with_fallback(scans: Sequence, **kwargs) -> tuple[Odometry, str]:
    """:func:`lidar_odometry` of all the points; when its registration slid (:func:`step_alignment`
    failed), once more without the ground, and the better of the two.

    A perfectly flat ground returns the same rings in every scan and holds point-to-point ICP
    at zero motion (the synthetic street: about 1 m short per 1 m step, every step). The retry
    drops the points below ``ALIGN_ABOVE_GROUND_M`` above the first scan's ground plane
    (:func:`ground_plane`, as ``min_z``) and, since KISS-ICP then still starts from standstill,
    predicts the first step by the median step of a first pass without the ground
    (``initial_motion``). The retry is kept only when every step of it passes the checks;
    otherwise the first run is returned with its failures. Measured: the synthetic street at
    10 m/s passes after the retry (20 frames: step error at most 11 cm, median 2.4 cm; at 4 m/s
    the retry slides too, 0.3-0.4 m per step, and the failures are reported); KITTI drive 2011_09_26_drive_0060
    passes the first run (no retry: its poses are those of :func:`lidar_odometry`).

    Args:
        scans: as :func:`lidar_odometry`.
        **kwargs: passed to :func:`lidar_odometry` (``check``, ``min_z`` and ``initial_motion``
            are set here and may not be given).

    Returns:
        ``(odometry, note)``: ``note`` is "" for the first run, else says what the retry dropped.
    """
    for name in ("check", "min_z", "initial_motion"):
        if name in kwargs:
            raise InputError(f"{name}: expected to be left to lidar_odometry_with_fallback, got {kwargs[name]!r}")
    scans = list(scans)
    odo = lidar_odometry(scans, check=False, **kwargs)
    if not any(ALIGN_HINT_KEY in why for _, why in odo.failures):
        return odo, ""
    first = _scan_array(scans[0], 0)
    plane = ground_plane(first)
    if plane is None:
        return odo, ""
    normal, height = plane
    min_z = (height + ALIGN_ABOVE_GROUND_M) / max(float(normal[2]), 0.5)
    ground_free = lidar_odometry(scans, check=False, min_z=min_z, **kwargs)
    median = int(np.argsort(ground_free.step_translation[1:])[(len(ground_free) - 1) // 2]) + 1
    initial = _inv(ground_free.poses[median - 1]) @ ground_free.poses[median]
    retry = lidar_odometry(scans, check=False, min_z=min_z, initial_motion=initial, **kwargs)
    if retry.failures:
        return odo, ""
    return retry, (f"the full scans' registration slid, so points below z = {min_z:.2f} m (the ground) were dropped "
                   f"and the first step predicted as {retry.step_translation[1]:.2f} m")


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
    day_dir = Path(day_dir)
    path = check_input_file(day_dir / "calib_imu_to_velo.txt" if day_dir.is_dir() else day_dir, "calibration")
    entries = read_key_values(path, "calibration")
    T = np.eye(4)
    T[:3, :3] = entry_array(entries, "R", (3, 3), path)
    T[:3, 3] = entry_array(entries, "T", (3,), path)
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
