"""LiDAR points to a sparse camera depth map (paper Sec. 3.1, docs/design.md section 1).

All projection math lives here: the z-buffer (:func:`project_to_depth`), the exact
KITTI chain (:func:`project_velodyne`), either calibration type
(:func:`project_points`), the in-image count (:func:`count_in_image`) and the scan's
ground plane used to spot an inverted transform (:func:`ground_normal`,
:func:`ground_tilt_deg`). Calibrations come from :mod:`crfdepth.io.calibration`, above this
module: it reads them by their fields (``P_rect``, ``R_rect`` ... ; ``K``, ``T_cam_lidar``, ``kitti``).

Also the subsampling transforms used to simulate sparser LiDAR: keeping every k-th
laser ring of a raw scan (rings recovered from the scan order) or a random fraction of
the points. Each has a ``*_mask`` twin returning the boolean mask of kept points, whose
complement is the held-out set.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from crfdepth.errors import InputError

__all__ = [
    "count_in_image",
    "ground_normal",
    "ground_tilt_deg",
    "fraction_mask",
    "keep_every_ring",
    "keep_fraction",
    "project_points",
    "project_to_depth",
    "project_velodyne",
    "recover_rings",
    "ring_mask",
]


def _check_points(points: np.ndarray, name: str, min_columns: int) -> np.ndarray:
    """``points`` as an array of shape (N, C >= min_columns), or InputError."""
    array = np.asarray(points)
    if array.ndim != 2 or array.shape[1] < min_columns:
        raise InputError(f"{name}: expected an (N, {min_columns}+) array of points, got shape {array.shape}")
    if not np.issubdtype(array.dtype, np.number) or np.issubdtype(array.dtype, np.complexfloating):
        raise InputError(f"{name}: expected real-valued coordinates, got dtype {array.dtype}")
    return array


def check_image_size(image_size) -> tuple[int, int]:
    try:
        height, width = (int(n) for n in image_size)
        valid = height > 0 and width > 0 and tuple(image_size) == (height, width)
    except (TypeError, ValueError):
        valid = False
    if not valid:
        raise InputError(f"image_size: expected (height, width) of positive integers, got {image_size!r}")
    return height, width


def project_to_depth(points_cam: np.ndarray, P: np.ndarray, image_size: tuple[int, int]) -> np.ndarray:
    """Z-buffer projection of camera-frame points into a sparse depth map.

    Args:
        points_cam: (N, 3) points in the (rectified) camera frame, metres, z forward.
        P: (3, 4) projection matrix of the target camera (KITTI ``P_rect_0X``); a (3, 3)
            K is accepted and treated as ``[K | 0]``.
        image_size: (height, width) of the image, pixels.

    Returns:
        (H, W) float32 sparse depth: camera z-depth in metres of the nearest point that
        lands in each pixel (pixel = rounded projection), 0 where no point lands. Points
        with z <= 0 (behind the camera) are dropped. The stored value is the z of the
        point in the frame of ``P``'s camera, i.e. ``(P @ [x, y, z, 1])[2]``.
    """
    height, width = check_image_size(image_size)
    P = np.asarray(P, dtype=np.float64)
    if P.shape == (3, 3):
        P = np.concatenate([P, np.zeros((3, 1))], axis=1)
    if P.shape != (3, 4):
        raise InputError(f"P: expected a (3, 4) projection matrix or a (3, 3) K, got shape {P.shape}")
    pts = _check_points(points_cam, "points_cam", 3).astype(np.float64)[:, :3]
    uvw = pts @ P[:, :3].T + P[:, 3]
    z = uvw[:, 2]
    front = z > 0
    uvw, z = uvw[front], z[front]
    u = np.round(uvw[:, 0] / z).astype(np.int64)
    v = np.round(uvw[:, 1] / z).astype(np.int64)
    inside = (u >= 0) & (u < width) & (v >= 0) & (v < height)
    u, v, z = u[inside], v[inside], z[inside]
    # Nearest point wins: sort by (pixel, z) and keep the first entry of each pixel.
    flat = v * width + u
    order = np.lexsort((z, flat))
    flat, z = flat[order], z[order]
    first = np.ones(flat.shape[0], dtype=bool)
    first[1:] = flat[1:] != flat[:-1]
    depth = np.zeros(height * width, dtype=np.float32)
    depth[flat[first]] = z[first]
    return depth.reshape(height, width)


def project_velodyne(points: np.ndarray, calib: Any,
                     image_size: tuple[int, int] | None = None) -> np.ndarray:
    """Sparse depth map of a Velodyne scan in one camera (docs/design.md section 1).

    Computes ``y = P_rect R_rect T_velo_to_cam x`` for every point, drops points behind
    the camera (z <= 0) or outside the image, rounds to the nearest pixel and keeps the
    nearest point per pixel (z-buffer, :func:`project_to_depth`).

    Args:
        points: (N, 3) or (N, 4) Velodyne points, x, y, z in metres in the Velodyne frame
            (a fourth column, reflectance, is ignored).
        calib: :class:`crfdepth.io.calibration.Calibration` of the target camera.
        image_size: (height, width) of the image, pixels; defaults to
            ``calib.image_size`` (known for raw-data calibration, not for object files).

    Returns:
        (H, W) float32 sparse depth in metres, 0 where no point lands. The stored value is
        z-depth, not Euclidean range: the third row of ``P_rect R_rect T_velo_to_cam x``,
        which is the rectified camera-0 z plus ``P_rect[2, 3]`` (2.7 mm for KITTI camera 2).
    """
    if image_size is None:
        if calib.image_size is None:
            raise InputError("image_size: required when calib.image_size is None "
                             "(object-benchmark calibration); pass the image's (height, width)")
        image_size = calib.image_size
    points = _check_points(points, "points", 3)
    homogeneous = np.concatenate([points[:, :3].astype(np.float64), np.ones((points.shape[0], 1))], axis=1)
    points_cam = homogeneous @ calib.velo_to_rect_cam()[:3].T
    return project_to_depth(points_cam, calib.P_rect, image_size)


def project_points(points: np.ndarray, calibration: Any,
                   image_size: tuple[int, int]) -> np.ndarray:
    """Z-buffer projection of LiDAR points with either calibration type.

    Args:
        points: (N, 3+) points in the LiDAR frame, metres; further columns are ignored.
        calibration: a :class:`~crfdepth.io.calibration.RigCalibration` (projected with
            ``K [I | 0] T_cam_lidar``) or a KITTI :class:`~crfdepth.io.calibration.Calibration`.
            A KITTI calibration, or a rig one read from KITTI files (``.kitti`` set), uses
            :func:`project_velodyne` exactly.
        image_size: (height, width) of the image, pixels.

    Returns:
        (H, W) float32 sparse z-depth in metres, 0 where no point lands.
    """
    kind = type(calibration).__name__
    if kind == "Calibration":
        return project_velodyne(points, calibration, image_size)
    if kind != "RigCalibration":
        raise InputError(f"calibration: expected a RigCalibration or a KITTI Calibration "
                         f"(crfdepth.io.calibration), got {kind}")
    if calibration.kitti is not None:
        return project_velodyne(points, calibration.kitti, image_size)
    T = calibration.T_cam_lidar
    xyz = _check_points(points, "points", 3)[:, :3].astype(np.float64)
    return project_to_depth(xyz @ T[:3, :3].T + T[:3, 3], calibration.K, image_size)


def count_in_image(points: np.ndarray, T_cam_lidar: np.ndarray, K: np.ndarray,
                   image_size: tuple[int, int]) -> int:
    """How many points ``K [I | 0] T_cam_lidar`` puts in front of the camera and inside the image.

    Counted before the z-buffer (several points may share a pixel), with the same
    rounding as :func:`project_to_depth` (``crfdepth complete --bag``'s index.csv). Counts do
    not tell an inverted transform (:func:`ground_tilt_deg` does).

    Args:
        points: (N, 3+) points in the LiDAR frame, metres.
        T_cam_lidar: (4, 4) LiDAR -> camera transform; K: (3, 3) intrinsics, pixels.
        image_size: (height, width), pixels.
    """
    height, width = check_image_size(image_size)
    xyz = _check_points(points, "points", 3)[:, :3].astype(np.float64)
    T, K = np.asarray(T_cam_lidar, dtype=np.float64), np.asarray(K, dtype=np.float64)
    cam = xyz @ T[:3, :3].T + T[:3, 3]
    front = cam[:, 2] > 0
    z = np.where(front, cam[:, 2], 1.0)
    u = np.round((K[0, 0] * cam[:, 0] + K[0, 1] * cam[:, 1]) / z + K[0, 2])
    v = np.round(K[1, 1] * cam[:, 1] / z + K[1, 2])
    return int(np.sum(front & (u >= 0) & (u < width) & (v >= 0) & (v < height)))

# Ground-plane search of :func:`ground_normal` (docs/design.md section 1).
GROUND_MAX_TILT_DEG = 30.0  # the ground's normal within this of the LiDAR's +z
GROUND_TOLERANCE_M = 0.10  # a point within this of the plane supports it
GROUND_MIN_SUPPORT = 0.05  # share of the (subsampled) scan a ground plane needs
_GROUND_ITERATIONS = 200
_GROUND_SAMPLE = 20000


def ground_normal(points: np.ndarray) -> np.ndarray | None:
    """Unit normal (pointing up) of the ground plane of a LiDAR scan, in the LiDAR frame, or None.

    LiDAR drivers publish z up (REP 103: x forward, y left, z up); the ground is then the
    plane below the sensor whose normal is within ``GROUND_MAX_TILT_DEG`` (30 deg) of +z
    and which holds the most returns (RANSAC, 200 tries, a point within
    ``GROUND_TOLERANCE_M`` = 0.1 m supports a plane; a fixed seed, so the same scan gives the
    same plane). None when no such plane holds ``GROUND_MIN_SUPPORT`` (5 %) of the returns
    (no ground in view of the LiDAR, or a LiDAR mounted tilted by more than 30 deg). On
    the shared KITTI scans (64 and 16 beams), the synthetic street and the docs/example
    scan it finds a plane within 4 degrees of level (docs/design.md section 1).

    Args:
        points: (N, 3+) points in the LiDAR frame, metres, finite.
    """
    xyz = _check_points(points, "points", 3)[:, :3].astype(np.float64)
    rng = np.random.default_rng(0)
    if xyz.shape[0] > _GROUND_SAMPLE:
        xyz = xyz[rng.choice(xyz.shape[0], _GROUND_SAMPLE, replace=False)]
    below = xyz[xyz[:, 2] < 0]
    if below.shape[0] < 3:
        return None
    cos_max = np.cos(np.radians(GROUND_MAX_TILT_DEG))
    best, best_normal = 0, None
    triples = rng.integers(0, below.shape[0], size=(_GROUND_ITERATIONS, 3))
    for triple in triples:
        a, b, c = below[triple]
        normal = np.cross(b - a, c - a)
        length = np.linalg.norm(normal)
        if length < 1e-9:
            continue
        normal = normal / length
        if normal[2] < 0:
            normal = -normal
        offset = -normal @ a  # plane: normal . x + offset = 0; the sensor (origin) is offset above it
        if normal[2] < cos_max or offset <= 0:
            continue
        count = int(np.count_nonzero(np.abs(xyz @ normal + offset) < GROUND_TOLERANCE_M))
        if count > best:
            best, best_normal = count, normal
    if best_normal is None or best < GROUND_MIN_SUPPORT * xyz.shape[0]:
        return None
    return best_normal


def ground_tilt_deg(normal: np.ndarray, T_cam_lidar: np.ndarray) -> float:
    """Angle, degrees, between the ground's up-normal mapped into the camera by ``T_cam_lidar``'s
    rotation and the camera's up (-y; camera x right, y down, z forward): 0 for a level camera."""
    up = np.asarray(T_cam_lidar, dtype=np.float64)[:3, :3] @ np.asarray(normal, dtype=np.float64)
    return float(np.degrees(np.arccos(np.clip(-up[1] / np.linalg.norm(up), -1.0, 1.0))))


def recover_rings(points: np.ndarray, min_jump: float = np.pi) -> np.ndarray:
    """Laser ring index of every point of a raw Velodyne scan, from its scan order.

    A KITTI scan (HDL-64E) is stored ring after ring, each ring one sweep of increasing
    azimuth that starts and ends straight ahead of the car. Measuring the azimuth from
    the rear, ``atan2(-y, -x)``, each ring runs from about -pi to +pi, so the start of a
    new ring is a drop in azimuth of nearly 2 pi. Only drops larger than ``min_jump``
    count, so the small backward steps of azimuth jitter (measured: < 0.03 rad on the
    shared scans) never split a ring. On the shared KITTI scans this finds 64 rings.

    Args:
        points: (N, 2+) points in the scan order of the ``.bin`` file (x, y in metres in
            the Velodyne frame; further columns are ignored). Do not reorder or subsample
            the scan before calling this.
        min_jump: smallest azimuth drop, radians, that starts a new ring.

    Returns:
        (N,) int64 ring index, 0 for the first ring of the file and increasing by one at
        each ring start (on KITTI the first ring is the top laser; 0 does not mean
        missing).
    """
    points = _check_points(points, "points", 2)
    if not 0 < min_jump < 2 * np.pi:
        raise InputError(f"min_jump: expected an azimuth drop in (0, 2 pi) radians, got {min_jump}")
    xy = points[:, :2].astype(np.float64)
    azimuth = np.arctan2(-xy[:, 1], -xy[:, 0])
    ring_start = np.diff(azimuth) < -min_jump
    rings = np.zeros(points.shape[0], dtype=np.int64)
    rings[1:] = np.cumsum(ring_start)
    return rings


def ring_mask(points: np.ndarray, k: int, rings: np.ndarray | None = None, offset: int = 0) -> np.ndarray:
    """Boolean mask of the points on every ``k``-th laser ring (``ring % k == offset``).

    Args:
        points: (N, 2+) Velodyne points in scan order (x, y, z in metres, ...).
        k: keep one ring in ``k``, ``k >= 1`` (k = 4 turns 64 rings into 16).
        rings: (N,) ring index per point; recovered with :func:`recover_rings` when None.
        offset: which ring of each group of ``k`` to keep, ``0 <= offset < k``.

    Returns:
        (N,) bool, True for kept points; ``~mask`` selects the held-out points.
    """
    points = _check_points(points, "points", 2)
    if isinstance(k, bool) or not isinstance(k, (int, np.integer)) or k < 1:
        raise InputError(f"k: expected an integer >= 1 (keep one ring in k), got {k!r}")
    if isinstance(offset, bool) or not isinstance(offset, (int, np.integer)) or not 0 <= offset < k:
        raise InputError(f"offset: expected an integer in [0, {k}) for k = {k}, got {offset!r}")
    if rings is None:
        rings = recover_rings(points)
    rings = np.asarray(rings)
    if rings.shape != (points.shape[0],) or not np.issubdtype(rings.dtype, np.integer):
        raise InputError(f"rings: expected an integer array of shape ({points.shape[0]},) (one ring "
                         f"per point), got {rings.dtype} array of shape {rings.shape}")
    return rings % k == offset


def keep_every_ring(points: np.ndarray, k: int, rings: np.ndarray | None = None, offset: int = 0) -> np.ndarray:
    """The points on every ``k``-th laser ring, in scan order (a sparser LiDAR).

    Args and mask semantics as :func:`ring_mask`.

    Returns:
        (M, C) copy of the kept rows of ``points`` (the input is not modified).
    """
    return np.asarray(points)[ring_mask(points, k, rings=rings, offset=offset)]


def fraction_mask(points: np.ndarray, fraction: float,
                  seed: int | np.random.Generator | None = None) -> np.ndarray:
    """Boolean mask of a uniformly random subset of ``round(fraction * N)`` points.

    Args:
        points: (N, C) points (only N is used).
        fraction: share of points to keep, ``0 < fraction <= 1``.
        seed: an int seed or a ``numpy.random.Generator`` (used as is, and advanced);
            None draws fresh entropy (not reproducible).

    Returns:
        (N,) bool, True for kept points; ``~mask`` selects the held-out points.
    """
    points = np.asarray(points)
    if points.ndim < 1:
        raise InputError(f"points: expected an (N, C) array, got a scalar of shape {points.shape}")
    try:
        valid = 0 < float(fraction) <= 1
    except (TypeError, ValueError):
        valid = False
    if not valid:
        raise InputError(f"fraction: expected a number in (0, 1], got {fraction!r}")
    rng = np.random.default_rng(seed)
    count = points.shape[0]
    mask = np.zeros(count, dtype=bool)
    mask[rng.choice(count, size=int(round(float(fraction) * count)), replace=False)] = True
    return mask


def keep_fraction(points: np.ndarray, fraction: float,
                  seed: int | np.random.Generator | None = None) -> np.ndarray:
    """A uniformly random ``fraction`` of the points, in their original order.

    Args and mask semantics as :func:`fraction_mask`.

    Returns:
        (round(fraction * N), C) copy of the kept rows of ``points``.
    """
    return np.asarray(points)[fraction_mask(points, fraction, seed=seed)]
