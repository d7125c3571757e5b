"""The annotated scene as KITTI's Velodyne returns it: a scan simulated from a camera-view depth map.

A real scan projected into the camera carries see-through returns at depth edges: the Velodyne
sits 0.27 m behind and 8 cm above the camera (KITTI's ``calib_velo_to_cam``), so next to a nearer
surface it sees a sliver of the background that the camera does not, and those returns land on the
nearer surface's pixels. KITTI's annotation has none of them (it was cleaned against stereo), so an
input drawn from it teaches weights to trust every return (docs/design.md section 16). This module
renders the Velodyne's view of the annotated scene, hidden background included, to give training
the inputs a real scan would give, with the annotation as their target (section 16, "Simulated
scans"):

1. the surface: the annotation, its gaps filled from the nearest annotated pixel within
   ``fill_radius`` pixels, and padded beyond the image border so the border does not open holes;
2. the hidden background: behind each pixel with a farther surface within ``hidden_window``
   pixels, a point at that farther depth (the background is taken to go on behind the edge);
3. the Velodyne's z-buffer: every point moved into the Velodyne frame, binned by laser ring (the
   HDL-64E's 64 elevations, a point within half a pixel's angle of one) and azimuth
   (``azimuth_step_deg``), and the nearest point of each bin kept, as the laser returns the
   first surface it meets; hidden points survive only where the Velodyne sees past the nearer
   surface;
4. the camera's z-buffer: the kept points at their pixels, the nearest per pixel, plus the
   scanner's range noise (``range_noise`` metres, one sigma).

Everything is geometry from the calibration; no parameter is fitted to KITTI's scans.
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

import cv2
import numpy as np

from crfdepth.errors import InputError

if TYPE_CHECKING:
    from crfdepth.io.calibration import Calibration

__all__ = ["HDL64_ELEVATIONS_DEG", "lift_to_velodyne", "simulate_scan"]

#: Elevation of the 64 lasers of a Velodyne HDL-64E (KITTI's scanner), degrees, top to bottom:
#: the upper block from +2 to -8.33 in steps of 1/3, the lower block from -8.83 to -24.33 in steps of 1/2.
HDL64_ELEVATIONS_DEG = np.concatenate([2.0 - np.arange(32) / 3.0, -8.83 - 0.5 * np.arange(32)])
AZIMUTH_STEP_DEG = 0.18  # one HDL-64E revolution at 10 Hz: about 2,000 returns per ring (KITTI's scans: 0.179-0.180)
HIDDEN_MARGIN = 0.05  # a farther surface counts as hidden background when 5% beyond the pixel's own depth


def lift_to_velodyne(v: np.ndarray, u: np.ndarray, depth: np.ndarray, calib: Calibration) -> np.ndarray:
    """(4, N) homogeneous Velodyne-frame points of pixels (v, u) at ``depth`` (the third row of
    ``P_rect R_rect T_velo_to_cam x``, the value of KITTI's depth maps)."""
    P = calib.P_rect
    z = depth - P[2, 3]
    x = (u * depth - P[0, 2] * z - P[0, 3]) / P[0, 0]
    y = (v * depth - P[1, 2] * z - P[1, 3]) / P[1, 1]
    rect = np.stack([x, y, z, np.ones_like(z)])
    return np.linalg.inv(calib.R_rect @ calib.T_velo_to_cam) @ rect


def _fill(target: np.ndarray, radius: float) -> np.ndarray:
    """``target`` with each empty pixel within ``radius`` pixels of an annotated one given that one's depth."""
    empty = target <= 0
    from scipy.ndimage import distance_transform_edt  # at first use: SciPy's import is 0.1 s

    distance, (iv, iu) = distance_transform_edt(empty, return_indices=True)
    return np.where(distance <= radius, target[iv, iu], 0.0)


def simulate_scan(
    target: np.ndarray,
    calib: Calibration,
    *,
    keep_every_ring: int = 1,
    ring_offset: int = 0,
    azimuth_step_deg: float = AZIMUTH_STEP_DEG,
    fill_radius: float = 4.0,
    hidden_window: tuple[int, int] = (17, 49),
    range_noise: float = 0.02,
    generator: np.random.Generator | None = None,
) -> np.ndarray:
    """A Velodyne scan of the scene in ``target``, projected into the camera, see-through returns included.

    Args:
        target: (H, W) camera-view depth in metres (KITTI's annotation), 0 = none.
        calib: the camera's calibration (:class:`~crfdepth.io.calibration.Calibration`): ``P_rect``,
            ``R_rect`` and ``T_velo_to_cam`` place the Velodyne.
        keep_every_ring: k >= 1: the returns of every k-th ring (1 = 64 beams, 4 = 16 beams).
        ring_offset: which ring of each group of k, ``0 <= ring_offset < k``.
        azimuth_step_deg: the scanner's horizontal step, degrees, > 0.
        fill_radius: pixels, >= 0: how far the annotation's surface reaches into its gaps.
        hidden_window: (height, width) in pixels, odd: where a farther surface is looked for behind each pixel.
        range_noise: metres, >= 0: one sigma of Gaussian noise on each return's depth.
        generator: numpy generator of the noise and of the azimuth grid's phase; None = a fresh one.

    Returns:
        (H, W) float32 depth in metres, 0 = no return: the nearest simulated return in each pixel.

    Raises:
        InputError: a bad argument (named).
    """
    target = np.asarray(target)
    if target.ndim != 2 or not np.issubdtype(target.dtype, np.floating):
        raise InputError(f"target: expected an (H, W) floating depth map in metres, got {target.dtype} "
                         f"of shape {target.shape}")
    if isinstance(keep_every_ring, bool) or not isinstance(keep_every_ring, int) or not 1 <= keep_every_ring <= 64:
        raise InputError(f"keep_every_ring: expected an integer in [1, 64], got {keep_every_ring!r}")
    if not 0 <= ring_offset < keep_every_ring:
        raise InputError(f"ring_offset: expected an integer in [0, {keep_every_ring}), got {ring_offset!r}")
    for name, value, low in (("azimuth_step_deg", azimuth_step_deg, "> 0"), ("fill_radius", fill_radius, ">= 0"),
                             ("range_noise", range_noise, ">= 0")):
        number = isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)
        if not number or not (value > 0 if low == "> 0" else value >= 0):
            raise InputError(f"{name}: expected a finite number {low}, got {value!r}")
    window = tuple(hidden_window) if isinstance(hidden_window, (tuple, list)) else ()
    if len(window) != 2 or any(isinstance(n, bool) or not isinstance(n, int) or n < 1 or n % 2 == 0 for n in window):
        raise InputError(f"hidden_window: expected (height, width) of odd positive integers, got {hidden_window!r}")
    rng = generator if generator is not None else np.random.default_rng()
    height, width = target.shape
    pad = hidden_window[1]  # surface beyond the border, so points near it are covered as in the scene

    surface = _fill(np.where(np.isfinite(target), target, 0.0).astype(np.float32), fill_radius)
    surface = cv2.copyMakeBorder(surface, pad, pad, pad, pad, cv2.BORDER_REPLICATE)
    farther = cv2.dilate(surface, cv2.getStructuringElement(cv2.MORPH_RECT, hidden_window[::-1]))
    hidden = np.where((surface > 0) & (farther > surface * (1.0 + HIDDEN_MARGIN)), farther, 0.0)

    points = []
    for layer in (surface, hidden):
        v, u = np.nonzero(layer > 0)
        points.append((v - pad, u - pad, layer[v, u].astype(np.float64)))
    v, u, depth = (np.concatenate(parts) for parts in zip(*points, strict=True))
    velo = lift_to_velodyne(v.astype(np.float64), u.astype(np.float64), depth, calib)
    horizontal = np.hypot(velo[0], velo[1])
    elevation = np.degrees(np.arctan2(velo[2], horizontal))
    rings = HDL64_ELEVATIONS_DEG[ring_offset::keep_every_ring]
    nearest = np.abs(elevation[:, None] - rings[None, :]).argmin(axis=1)
    on_ring = np.abs(elevation - rings[nearest]) <= math.degrees(0.5 / calib.P_rect[1, 1])
    phase = rng.uniform(0.0, azimuth_step_deg)
    column = np.floor((np.degrees(np.arctan2(velo[1], velo[0])) + phase) / azimuth_step_deg).astype(np.int64)
    bins = nearest * (column.max() - column.min() + 1) + (column - column.min())
    distance = np.linalg.norm(velo[:3], axis=0)

    keep = np.nonzero(on_ring)[0]
    keep = keep[np.lexsort((distance[keep], bins[keep]))]
    first = np.r_[True, bins[keep][1:] != bins[keep][:-1]]  # the first surface each laser meets
    keep = keep[first]
    inside = (v[keep] >= 0) & (v[keep] < height) & (u[keep] >= 0) & (u[keep] < width)
    keep = keep[inside]

    returned = depth[keep] + rng.normal(0.0, range_noise, keep.size) if range_noise else depth[keep]
    out = np.full(target.shape, np.inf)
    np.minimum.at(out, (v[keep], u[keep]), np.maximum(returned, 1e-3))  # the camera's z-buffer
    return np.where(np.isfinite(out), out, 0.0).astype(np.float32)
