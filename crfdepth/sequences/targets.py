"""Camera-view targets: registered LiDAR scans accumulated into one camera frame, keeping
only the returns the camera sees (docs/design.md section 14).

:func:`camera_view_targets` accumulates the scans ``index - k .. index + k`` of a recording
(each in its own LiDAR frame, with a world<-LiDAR pose per scan) into frame ``index``'s
camera and drops, per return:

- **outside**: behind the camera or outside the image;
- **moved** (rule b): a return of another scan ``s != index`` through which the frame's own
  scan sees: compared in the LiDAR's range image of scan ``index`` (azimuth x elevation
  bins), the beams of scan ``index`` just above and below its direction both reach well
  beyond it, so the space was empty at the frame's time (a moving object was there at time ``s``). Returns of
  the frame's own scan pass trivially;
- **occluded** (rule a): a return behind the surface the camera sees. The remaining returns
  are rendered as splats whose pixel radius is ``f * surfel_m / z`` (a surface element of
  ``surfel_m`` metres), the nearest splat depth per pixel is the visible surface, and a
  return is kept only within the band ``tau(z_s) = band_rel * z_s + band_m`` of it.

The target of a pixel is the nearest kept return of the frame's own scan where it has one
(rule c: the own scan has priority where it is consistent), else the nearest kept return of
the other scans. :class:`Targets` carries the depth, a per-pixel support count (how many
scans have a kept return within the band of the target) and the reason code of every
dropped return; :func:`crfdepth.pictures.figures.targets_picture` paints them.

Pure numpy (and OpenCV for the min filters); no torch, no Lightning.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np

from crfdepth.checks import check_number, check_rigid
from crfdepth.errors import InputError
from crfdepth.geometry.projection import check_image_size
from crfdepth.intrinsics import check_intrinsics
from crfdepth.sequences.free_space import seen_through

__all__ = [
    "KEPT",
    "MOVED",
    "OCCLUDED",
    "OUTSIDE",
    "REASONS",
    "REASON_COLOURS",
    "Targets",
    "accumulate",
    "camera_view_targets",
]

# Reason codes of a return (Targets.point_reason) and of a pixel (Targets.reason).
KEPT, OUTSIDE, OCCLUDED, MOVED = 0, 1, 2, 3
REASONS = {KEPT: "kept", OUTSIDE: "outside the image", OCCLUDED: "occluded", MOVED: "moved"}
# RGB of dropped returns in targets_picture.
REASON_COLOURS = {OCCLUDED: (255, 0, 255), MOVED: (255, 255, 255)}

_FAR = np.float32(1e9)  # "no surface" in the splat buffers
_MIN_Z = 0.1  # returns nearer than this (metres, camera z) count as outside


@dataclass(frozen=True)
class Targets:
    """Camera-view targets of one frame (:func:`camera_view_targets`).

    Attributes:
        depth: (H, W) float32 camera z-depth in metres, 0 = no target.
        support: (H, W) uint16, how many scans of the window have a kept return in the pixel
            within the depth band of the target (0 where there is no target).
        own: (H, W) bool, the target comes from the frame's own scan.
        reason: (H, W) uint8, for pixels without a target where dropped returns land: the
            reason of the dropped return (:data:`MOVED` wins over :data:`OCCLUDED`); 0
            (:data:`KEPT`) elsewhere.
        point_reason: one (N_s,) uint8 array per scan of the window, the reason code of
            each return (:data:`KEPT`, :data:`OUTSIDE`, :data:`OCCLUDED`, :data:`MOVED`).
        window: the scan indices accumulated, in order.
        index: the frame the targets belong to.
    """

    depth: np.ndarray
    support: np.ndarray
    own: np.ndarray
    reason: np.ndarray
    point_reason: list
    window: tuple
    index: int

    @property
    def density(self) -> float:
        """Share of the image's pixels with a target."""
        return float(np.mean(self.depth > 0))

    def counts(self) -> dict[str, int]:
        """Number of returns of the window per reason, by name (:data:`REASONS`)."""
        codes = np.concatenate(self.point_reason) if self.point_reason else np.zeros(0, np.uint8)
        return {name: int(np.sum(codes == code)) for code, name in REASONS.items()}


# --------------------------------------------------------------------------- checks


def _check_scan(name: str, scan) -> np.ndarray:
    array = np.asarray(scan)
    if array.ndim != 2 or array.shape[1] < 3:
        raise InputError(f"{name}: expected an (N, 3+) array of points (x, y, z in the LiDAR frame, metres), "
                         f"got shape {array.shape}")
    if not np.issubdtype(array.dtype, np.number) or np.issubdtype(array.dtype, np.complexfloating):
        raise InputError(f"{name}: expected real-valued coordinates, got dtype {array.dtype}")
    if array.shape[0] == 0:
        raise InputError(f"{name}: expected a scan with at least one return, got an empty scan (0 points); "
                         f"leave the frame out of the sequence or shorten the window")
    xyz = array[:, :3].astype(np.float64)
    if not np.isfinite(xyz).all():
        raise InputError(f"{name}: expected finite coordinates, got {int(np.sum(~np.isfinite(xyz).all(axis=1)))} "
                         f"points with NaN or inf")
    return xyz


def _check_window(scans, poses, index, k) -> tuple[list, np.ndarray, int, int]:
    if isinstance(scans, np.ndarray) or not hasattr(scans, "__len__") or len(scans) == 0:
        got = f"shape {scans.shape}" if isinstance(scans, np.ndarray) else (
            "0 scans" if hasattr(scans, "__len__") else type(scans).__name__)
        raise InputError(f"scans: expected a non-empty list of (N, 3+) point arrays, one per frame, got {got}")
    n = len(scans)
    k = int(k) if isinstance(k, np.integer) else k
    index = int(index) if isinstance(index, np.integer) else index
    k = check_number("k", k, low=0, low_open=False, integer=True)
    index = check_number("index", index, low=0, high=n - 1, low_open=False, high_open=False, integer=True)
    try:
        P = np.asarray(poses, dtype=np.float64)
    except (TypeError, ValueError):
        raise InputError(f"poses: expected an (n, 4, 4) array of world<-LiDAR poses, got "
                         f"{type(poses).__name__}") from None
    if P.ndim != 3 or P.shape[1:] != (4, 4):
        raise InputError(f"poses: expected an (n, 4, 4) array of world<-LiDAR poses, got shape {P.shape}")
    if P.shape[0] < n:
        raise InputError(f"poses: expected a pose for every scan ({n}), got {P.shape[0]}")
    window = list(range(max(0, index - k), min(n, index + k + 1)))
    for s in window:
        check_rigid(P[s], f"poses[{s}]")
    return window, P, int(index), int(k)


# --------------------------------------------------------------------------- accumulation


def accumulate(scans, poses, T_cam_lidar, index: int, *, k: int = 5) -> tuple[np.ndarray, np.ndarray, list]:
    """The returns of scans ``index - k .. index + k`` in frame ``index``'s camera frame.

    Args:
        scans: sequence of (N_s, 3+) arrays, x, y, z of each return in its scan's LiDAR
            frame (metres); further columns (reflectance) are ignored.
        poses: (n, 4, 4) world<-LiDAR pose of each scan (at least one per scan; KITTI
            odometry's convention, any world frame).
        T_cam_lidar: (4, 4) LiDAR-to-camera extrinsic (``p_cam = T @ p_lidar``).
        index: the frame, 0 <= index < len(scans).
        k: half window, >= 0 (the window is cut at the ends of the sequence).

    Returns:
        ``(points_cam, scan_of, window)``: (M, 3) float64 points in the camera of frame
        ``index``, (M,) int64 the scan index of each, and the window's scan indices. The
        points are the window's scans concatenated in window order.

    Raises:
        InputError: see :func:`camera_view_targets`.
    """
    window, P, index, k = _check_window(scans, poses, index, k)
    T_cam_lidar = check_rigid(T_cam_lidar, "T_cam_lidar")
    points, owners = _accumulate(scans, P, T_cam_lidar, index, window)
    return np.concatenate(points), np.concatenate(owners), window


def _accumulate(scans, P, T_cam_lidar, index, window):
    """Per scan of the window: its points in the LiDAR frame of ``index`` (then the camera)."""
    inv_t = np.linalg.inv(P[index])
    points, owners = [], []
    for s in window:
        xyz = _check_scan(f"scans[{s}]", scans[s])
        T = T_cam_lidar @ inv_t @ P[s]
        points.append(xyz @ T[:3, :3].T + T[:3, 3])
        owners.append(np.full(len(xyz), s, dtype=np.int64))
    return points, owners


# --------------------------------------------------------------------------- rule (a): visibility


def _disk(radius: int) -> np.ndarray:
    return cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * radius + 1, 2 * radius + 1))


def _splat_surface(flat, z, radius_px, shape) -> np.ndarray:
    """(H, W) float32 nearest splat depth: each point covers a disk of its radius (pixels)."""
    height, width = shape
    surface = np.full(height * width, _FAR, dtype=np.float32)
    for radius in np.unique(radius_px):
        sel = radius_px == radius
        buffer = np.full(height * width, _FAR, dtype=np.float32)
        np.minimum.at(buffer, flat[sel], z[sel].astype(np.float32))
        if radius > 0:
            buffer = cv2.erode(buffer.reshape(shape), _disk(int(radius)), borderType=cv2.BORDER_CONSTANT,
                               borderValue=float(_FAR)).ravel()
        np.minimum(surface, buffer, out=surface)
    return surface


# --------------------------------------------------------------------------- targets


def camera_view_targets(scans, poses, T_cam_lidar, K, image_size, index: int, *, k: int = 5,
                        surfel_m: float = 0.05, max_splat_px: int = 12, band_rel: float = 0.05,
                        band_m: float = 0.1, free_rel: float = 0.02, free_m: float = 0.2,
                        azimuth_bin_deg: float = 0.2, elevation_bin_deg: float = 0.1,
                        beam_gap_deg: float = 1.0) -> Targets:
    """Camera-view depth targets of frame ``index`` from the scans ``index - k .. index + k``.

    Args:
        scans: sequence of (N_s, 3+) arrays, one per frame: x, y, z of each return in that
            scan's LiDAR frame, metres (KITTI Velodyne axes or any; further columns ignored).
        poses: (n >= len(scans), 4, 4) world<-LiDAR pose of each scan (rigid, metres).
        T_cam_lidar: (4, 4) LiDAR-to-camera extrinsic, ``p_cam = T @ p_lidar``.
        K: (3, 3) camera intrinsics of the image (pixels).
        image_size: (height, width) of the image, pixels.
        index: the frame, 0 <= index < len(scans).
        k: half window, >= 0; the window is cut at the ends of the sequence. ``k = 0`` (or a
            one-frame sequence) works: the frame's own scan after rule (a), which removes the
            returns the LiDAR sees behind foreground edges that the camera cannot.
        surfel_m: size of the surface element each return stands for (rule a): its splat's
            pixel radius is ``round(fx * surfel_m / z)``, at most ``max_splat_px``. It must
            bridge the gaps between neighbouring returns of a near surface so that nothing
            behind shows through; larger values also hide true surfaces just beside a
            foreground edge and make slanted surfaces (the ground) hide themselves (see
            ``band_rel``).
        max_splat_px: largest splat radius, pixels (a return a metre from the camera would
            otherwise cover much of the image).
        band_rel, band_m: a return is occluded when it lies beyond ``z_s (1 + band_rel) +
            band_m``, ``z_s`` the nearest splat depth at its pixel. ``band_m`` covers the
            range noise (a few centimetres), ``band_rel`` the depth change across a splat on
            a slanted surface (``surfel_m / h`` on a ground seen from a height ``h``) and
            pose error that grows with range.
        free_rel, free_m: rule (b): a return of another scan is moved when the own scan's
            nearest beams above and below its direction (nearest return over +-1 azimuth
            bin) both lie beyond ``r (1 + free_rel) + free_m`` (``r`` its range from the
            frame's LiDAR).
        azimuth_bin_deg, elevation_bin_deg: bins of the own scan's range image (rule b):
            about the LiDAR's azimuth step, and finer than its beam spacing.
        beam_gap_deg: rule (b) looks for the bracketing beams at most this far above and
            below the query's direction (degrees); without both, the return stays.

    Returns:
        :class:`Targets`.

    Raises:
        InputError: ``scans`` empty or a scan of the window empty or not (N, 3+);
            ``index`` outside the sequence; ``k`` negative or not an integer; fewer
            ``poses`` than scans or a pose of the window not rigid; a bad ``T_cam_lidar``,
            ``K`` or ``image_size``; a parameter out of range.
    """
    window, P, index, k = _check_window(scans, poses, index, k)
    T_cam_lidar = check_rigid(T_cam_lidar, "T_cam_lidar")
    height, width = check_image_size(image_size)
    K = check_intrinsics(K, "K", (height, width))
    surfel_m = check_number("surfel_m", surfel_m, low=0, low_open=False)
    max_splat_px = check_number("max_splat_px", max_splat_px, low=0, high=64, low_open=False,
                                high_open=False, integer=True)
    band_rel = check_number("band_rel", band_rel, low=0, low_open=False)
    band_m = check_number("band_m", band_m, low=0, low_open=False)
    free_rel = check_number("free_rel", free_rel, low=0, low_open=False)
    free_m = check_number("free_m", free_m, low=0, low_open=False)
    az_step = math.radians(check_number("azimuth_bin_deg", azimuth_bin_deg, low=0, high=10, high_open=False))
    el_step = math.radians(check_number("elevation_bin_deg", elevation_bin_deg, low=0, high=10, high_open=False))
    beam_gap = math.radians(check_number("beam_gap_deg", beam_gap_deg, low=0, high=30, low_open=False,
                                         high_open=False))

    points, owners = _accumulate(scans, P, T_cam_lidar, index, window)
    cam = np.concatenate(points)
    scan_of = np.concatenate(owners)
    reason = np.full(len(cam), KEPT, dtype=np.uint8)

    # Outside: behind the camera or off the image (pixel = rounded projection).
    z = cam[:, 2]
    front = z > _MIN_Z
    zs = np.where(front, z, 1.0)
    u = np.rint(K[0, 0] * cam[:, 0] / zs + K[0, 2]).astype(np.int64)
    v = np.rint(K[1, 1] * cam[:, 1] / zs + K[1, 2]).astype(np.int64)
    inside = front & (u >= 0) & (u < width) & (v >= 0) & (v < height)
    reason[~inside] = OUTSIDE

    # (b) Movers: other scans' returns that the own scan sees through.
    own = scan_of == index
    others = inside & ~own
    if others.any():
        to_lidar = np.linalg.inv(T_cam_lidar)
        query = cam[others] @ to_lidar[:3, :3].T + to_lidar[:3, 3]
        own_scan = points[window.index(index)] @ to_lidar[:3, :3].T + to_lidar[:3, 3]
        moved = seen_through(query, own_scan, az_step=az_step, el_step=el_step, beam_gap=beam_gap,
                              free_rel=free_rel, free_m=free_m)
        idx = np.flatnonzero(others)
        reason[idx[moved]] = MOVED

    # (a) Visibility against the splatted surface of what is left.
    live = np.flatnonzero(reason == KEPT)
    flat = v[live] * width + u[live]
    zl = z[live]
    radius = np.clip(np.rint(K[0, 0] * surfel_m / zl), 0, max_splat_px).astype(np.int64)
    surface = _splat_surface(flat, zl, radius, (height, width))
    occluded = zl > surface[flat] * (1.0 + band_rel) + band_m
    reason[live[occluded]] = OCCLUDED

    # Targets: nearest kept own return, else nearest kept return of the window (rule c).
    kept = reason == KEPT
    flat_all = np.where(inside, v * width + u, 0)
    depth = np.full(height * width, np.inf)
    own_kept = kept & own
    np.minimum.at(depth, flat_all[own_kept], z[own_kept])
    from_own = np.isfinite(depth)
    rest = np.full(height * width, np.inf)
    np.minimum.at(rest, flat_all[kept & ~own], z[kept & ~own])
    depth = np.where(from_own, depth, rest)
    has = np.isfinite(depth)

    # Support: scans with a kept return within the band of the target.
    kept_idx = np.flatnonzero(kept)
    target = depth[flat_all[kept_idx]]
    agree = np.abs(z[kept_idx] - target) <= band_rel * target + band_m
    pairs = np.unique(flat_all[kept_idx[agree]] * (len(scans) + 1) + scan_of[kept_idx[agree]])
    support = np.bincount(pairs // (len(scans) + 1), minlength=height * width)

    pixel_reason = np.zeros(height * width, dtype=np.uint8)
    dropped = inside & ((reason == OCCLUDED) | (reason == MOVED))
    np.maximum.at(pixel_reason, flat_all[dropped], reason[dropped])
    pixel_reason[has] = KEPT

    splits = np.cumsum([len(p) for p in points])[:-1]
    return Targets(
        depth=np.where(has, depth, 0.0).astype(np.float32).reshape(height, width),
        support=np.minimum(support, np.iinfo(np.uint16).max).astype(np.uint16).reshape(height, width),
        own=from_own.reshape(height, width),
        reason=pixel_reason.reshape(height, width),
        point_reason=np.split(reason, splits),
        window=tuple(window),
        index=index,
    )
