"""LiDAR odometry of a recording's scans, every step checked (docs/design.md section 12).

- :func:`lidar_odometry`: scan-to-map registration with KISS-ICP (Vizzo et al. 2023, the
  optional extra ``pip install "crfdepth[odometry]"``), with a check of every step that
  reports failures by frame instead of accumulating them
  (:func:`crfdepth.sequences.pose_checks.check_poses`): speed, jumps, points, fitness, and
  the registration itself (:func:`crfdepth.sequences.registration.step_alignment`: the scan's
  structure, ground removed, must fit the previous scan best at the estimate).
- :func:`lidar_odometry_with_fallback` retries without the ground when the registration slid
  (a perfectly flat ground).

Poses given (KITTI ``poses.txt``, oxts) and the pose maths are in
:mod:`crfdepth.sequences.poses`, whose convention the poses here follow: ``T_world<-lidar(t)``
as (n, 4, 4) float64, the first scan's LiDAR frame the world.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from crfdepth.checks import check_rigid
from crfdepth.errors import InputError
from crfdepth.geometry.rigid import camera_relative_pose, invert_rigid
from crfdepth.sequences.pose_checks import check_poses, step_sizes
from crfdepth.sequences.registration import (
    ALIGN_ABOVE_GROUND_M,
    ALIGN_HINT_KEY,
    ALIGN_MAX_RANGE_M,
    MAX_ALIGN_OFFSET_DEG,
    MAX_ALIGN_OFFSET_M,
    ground_plane,
    scan_structure,
    step_alignment,
)

__all__ = [
    "Odometry",
    "lidar_odometry",
    "lidar_odometry_with_fallback",
]

EXTRA_HINT = 'pip install "crfdepth[odometry]"'


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
        failures: ``(frame, reason)`` pairs found by
            :func:`~crfdepth.sequences.pose_checks.check_poses`; empty when every step passed.
        rate: scans per second used for the speed checks.
        alignment: (n, 3) per step, the offset from the estimate at which scan t's structure
            fits scan t-1 best: x, y (metres), turn about z (degrees)
            (:func:`~crfdepth.sequences.registration.step_alignment`; zeros for the first scan);
            None when not computed.
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
        """``T_cam(s)<-cam(t)`` of scans s and t (:func:`~crfdepth.sequences.poses.camera_relative_pose`)."""
        return camera_relative_pose(self.poses[s], self.poses[t], T_cam_lidar)


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


def lidar_odometry(scans: Sequence, *, voxel_size: float | None = None, max_range: float = 100.0,
                   min_range: float = 3.0, rate: float = 10.0, max_speed: float = 40.0, max_yaw_rate: float = 60.0,
                   min_points: int = 1000, min_fitness: float = 0.5, min_z: float | None = None, initial_motion=None,
                   deskew: bool = False, threads: int = 0, check: bool = True, check_alignment: bool = True,
                   max_alignment_m: float = MAX_ALIGN_OFFSET_M, max_alignment_deg: float = MAX_ALIGN_OFFSET_DEG
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
        max_speed, max_yaw_rate, min_points, min_fitness: see :func:`~crfdepth.sequences.pose_checks.check_poses`.
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
            (:func:`~crfdepth.sequences.registration.step_alignment` on
            :func:`~crfdepth.sequences.registration.scan_structure` of the full scans, whatever
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
            correction[k] = float(np.linalg.norm((invert_rigid(predicted) @ poses[k])[:3, 3]))
            if len(map_before) and len(source):
                src = source @ poses[k][:3, :3].T + poses[k][:3, 3]
                dist, _ = cKDTree(map_before).query(src, k=1, distance_upper_bound=inlier_m, workers=1)
                inl = np.isfinite(dist)
                fitness[k] = float(inl.mean())
                residual[k] = float(np.median(dist[inl])) if inl.any() else np.inf
            else:
                fitness[k] = 0.0
    trans, rot = step_sizes(poses)
    aligned = offsets = shares = None
    if check_alignment:
        # the full scans (not min_z's): the ground plane is found and removed in each
        structure = [scan_structure(a, min_range=min_range, max_range=min(max_range, ALIGN_MAX_RANGE_M))
                     for a in full]
        aligned = [None] + [step_alignment(structure[k - 1], structure[k], invert_rigid(poses[k - 1]) @ poses[k])
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
    """:func:`lidar_odometry` of all the points; when its registration slid
    (:func:`~crfdepth.sequences.registration.step_alignment` failed), once more without the
    ground, and the better of the two.

    A perfectly flat ground returns the same rings in every scan and holds point-to-point ICP
    at zero motion (the synthetic street: about 1 m short per 1 m step, every step). The retry
    drops the points below ``ALIGN_ABOVE_GROUND_M`` above the first scan's ground plane
    (:func:`~crfdepth.sequences.registration.ground_plane`, as ``min_z``) and, since KISS-ICP
    then still starts from standstill, predicts the first step by the median step of a first pass without the ground
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
    initial = invert_rigid(ground_free.poses[median - 1]) @ ground_free.poses[median]
    retry = lidar_odometry(scans, check=False, min_z=min_z, initial_motion=initial, **kwargs)
    if retry.failures:
        return odo, ""
    return retry, (f"the full scans' registration slid, so points below z = {min_z:.2f} m (the ground) were dropped "
                   f"and the first step predicted as {retry.step_translation[1]:.2f} m")
