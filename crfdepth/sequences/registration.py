"""The registration check of LiDAR odometry: does each estimated step lay scan t's structure
where it fits scan t-1 best (docs/design.md section 12, "Registration check").

- :func:`scan_structure`: the returns of a scan above its ground plane (:func:`ground_plane`),
  within range: what constrains its motion along the road;
- :func:`step_alignment`: the offset from the estimated step at which scan t's structure fits
  scan t-1's best, as an :class:`Alignment`, whose :meth:`~Alignment.failure` says when the
  registration slid.

:func:`crfdepth.sequences.odometry.lidar_odometry` checks every step with it and
:func:`crfdepth.sequences.pose_checks.check_poses` names the frames that slid. Frames and poses
follow :mod:`crfdepth.sequences.poses`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from crfdepth.geometry.rigid import axis_rotation

__all__ = [
    "Alignment",
    "ground_plane",
    "scan_structure",
    "step_alignment",
]


# Constants of :func:`step_alignment` (docs/design.md section 12, "Registration check"). Measured
# with these values (tests/sequences/test_odometry.py): on drive 2011_09_26_drive_0060 (all 77 steps,
# the KISS-ICP poses) the best offset is at most 0.17 m along x, 0.02 m along y, 0.09 deg about z
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
        R = axis_rotation(2, math.radians(a))
        turned = pts @ R.T  # about scan t's own vertical, then the estimated step
        values.append(mean_distance(turned @ T[:3, :3].T + T[:3, 3])[0])
    best = min(best, min(values))
    offsets.append(_refined(yaws, np.array(values)))
    return Alignment(offset=np.array(offsets), residual=residual, best=best, share=share)
