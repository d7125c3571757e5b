"""The failure check of a pose sequence: which frames moved implausibly (docs/design.md section 12).

:func:`check_poses` names the failing frames of any pose sequence, those of LiDAR odometry
(:func:`crfdepth.sequences.odometry.lidar_odometry` checks every step with it) as those of a
bag's ``/tf`` (``crfdepth targets --bag``), so that a failed step is reported by frame instead
of accumulated into every later pose: speed, yaw rate, jumps against the neighbouring steps,
and, where given, the points of each scan, its registration fitness and the registration check
of :mod:`crfdepth.sequences.registration`. Poses follow :mod:`crfdepth.sequences.poses`.
"""

from __future__ import annotations

import numpy as np

from crfdepth.geometry.rigid import invert_rigid, rotation_deg
from crfdepth.sequences.registration import MAX_ALIGN_OFFSET_DEG, MAX_ALIGN_OFFSET_M

__all__ = ["check_poses", "step_sizes"]


def step_sizes(poses: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(n,) metres moved and (n,) degrees turned from each pose to the next (0 for the first)."""
    n = len(poses)
    trans, rot = np.zeros(n), np.zeros(n)
    for k in range(1, n):
        d = invert_rigid(poses[k - 1]) @ poses[k]
        trans[k] = float(np.linalg.norm(d[:3, 3]))
        rot[k] = rotation_deg(d[:3, :3])
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
    one :class:`~crfdepth.sequences.registration.Alignment` or None per frame,
    :func:`~crfdepth.sequences.registration.step_alignment`) its structure fits scan ``k - 1``
    best more than ``max_alignment_m`` (default ``MAX_ALIGN_OFFSET_M``, 0.3 m) along x or y or
    ``max_alignment_deg`` (default ``MAX_ALIGN_OFFSET_DEG``, 0.5 deg) about z away from the
    estimated step: a registration that slid, which the speed and jump checks miss when
    every step slides alike (the flat synthetic street with the command's defaults).

    Returns:
        ``[(frame, reason), ...]`` sorted by frame.
    """
    poses = np.asarray(poses, dtype=np.float64)
    trans, rot = step_sizes(poses)
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
