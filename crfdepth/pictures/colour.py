"""Colour pictures of depth and uncertainty maps (for the CLI's ``--vis`` and the demo).

Pure functions: they take an (H, W) map (numpy array or torch tensor, metres) and return
an uint8 **RGB** image; nothing is written and the input is never modified. Pixels
without a value (0, negative, NaN or inf: KITTI's "no measurement") are painted
``invalid_color`` (black by default), which neither colour map uses.

Pictures for people, with a colour bar in metres under the map, are in :mod:`crfdepth.pictures.figures`:

- :func:`crfdepth.pictures.figures.depth_picture`: the dense depth (docs/design.md section 1), TURBO on *inverse*
  depth, near = warm (red), far = cold (blue). Inverse depth spreads the near range,
  where the detail is, and compresses the sky and far background.
- :func:`crfdepth.pictures.figures.std_picture`: the standard deviation (docs/design.md section 5),
  VIRIDIS (dark purple = certain, yellow = uncertain) on a *log* scale by default: the
  std is small near the LiDAR and one or two decades larger far from it, and a linear
  scale paints everything near the data with a single colour.

Both take ``vis_range=(min_m, max_m)``: the same colours for the same metres in every
frame of a sequence. Without it the range is robust and per frame: the 2nd to 98th
percentile of the map's values (:func:`depth_range`, :func:`std_range`).

The bare colour maps, same size as the map, no bar: :func:`colorize_depth`,
:func:`colorize_std` (linear by default, ``scale="log"`` as in the picture). Both accept
``vis_range`` too, or ``vmin`` / ``vmax`` (default: computed per map).

- :func:`draw_points`: sparse LiDAR drawn over the camera image, coloured by depth.
- :func:`render_point_cloud`: a dense depth map as a coloured 3D point cloud seen from a
  virtual camera above and behind the real one.
"""

from __future__ import annotations

import math
from numbers import Real
from typing import Literal

import cv2
import numpy as np
import torch

from crfdepth.errors import InputError

__all__ = [
    "colorize_depth",
    "colorize_std",
    "depth_range",
    "draw_points",
    "render_point_cloud",
    "std_range",
]

Scale = Literal["linear", "log"]
"""Colour scale of a std map: linear in metres or linear in log(metres)."""

BLACK = (0, 0, 0)
WHITE = (255, 255, 255)


def as_map(name: str, values) -> np.ndarray:
    """(H, W) float64 copy of a numpy array or tensor; leading singleton dims dropped."""
    if isinstance(values, torch.Tensor):
        values = values.detach().cpu().numpy()
    array = np.asarray(values)
    while array.ndim > 2 and array.shape[0] == 1:
        array = array[0]
    if array.ndim != 2 or array.size == 0:
        raise InputError(f"{name}: expected a non-empty (H, W) map (or (1, H, W), (1, 1, H, W)), "
                         f"got shape {np.shape(values)}")
    if not (np.issubdtype(array.dtype, np.floating) or np.issubdtype(array.dtype, np.integer)):
        raise InputError(f"{name}: expected real values in metres, got dtype {array.dtype}")
    return array.astype(np.float64)


def check_color(color, name: str = "invalid_color") -> np.ndarray:
    """``color`` as a (3,) uint8 RGB triple; InputError naming ``name`` unless it is three numbers in [0, 255]."""
    colour = np.asarray(color)
    if colour.shape != (3,) or not np.all((colour >= 0) & (colour <= 255)):
        raise InputError(f"{name}: expected an (R, G, B) triple in [0, 255], got {color!r}")
    return colour.astype(np.uint8)


def _check_range(vmin: float, vmax: float, what: str) -> None:
    if not (np.isfinite(vmin) and np.isfinite(vmax)) or vmax < vmin:
        raise InputError(f"vmin, vmax: expected finite {what} with vmin <= vmax, got {vmin!r}, {vmax!r}")


def _paint(t: np.ndarray, valid: np.ndarray, colormap: int, invalid_color) -> np.ndarray:
    """Colour map of ``t`` in [0, 1] (1 = top of the map) as RGB; invalid pixels painted."""
    codes = np.round(np.clip(np.where(valid, t, 0.0), 0.0, 1.0) * 255.0).astype(np.uint8)
    rgb = cv2.cvtColor(cv2.applyColorMap(codes, colormap), cv2.COLOR_BGR2RGB)
    rgb[~valid] = check_color(invalid_color)
    return rgb


def check_vis_range(vis_range, *, positive: bool) -> tuple[float, float]:
    """``vis_range`` as two floats ``(min, max)``: finite, min < max, min > 0 (``positive``) or >= 0."""
    bound = "0 < min < max" if positive else "0 <= min < max"
    expected = f"vis_range: expected two finite numbers (min, max) in metres with {bound}, got {vis_range!r}"
    if isinstance(vis_range, (str, bytes)) or not hasattr(vis_range, "__len__") or len(vis_range) != 2:
        raise InputError(expected)
    lo, hi = vis_range
    if not all(isinstance(v, Real) and not isinstance(v, bool) for v in (lo, hi)):
        raise InputError(expected)
    lo, hi = float(lo), float(hi)
    if not (math.isfinite(lo) and math.isfinite(hi)) or not lo < hi or (lo <= 0 if positive else lo < 0):
        raise InputError(expected)
    return lo, hi


def _range_or_bounds(vis_range, vmin, vmax, *, positive: bool):
    """``(vmin, vmax)`` from ``vis_range`` when given (then vmin/vmax must be None)."""
    if vis_range is None:
        return vmin, vmax
    if vmin is not None or vmax is not None:
        raise InputError(f"vis_range: expected either vis_range or vmin/vmax, not both, got vis_range={vis_range!r}, "
                         f"vmin={vmin!r}, vmax={vmax!r}")
    return check_vis_range(vis_range, positive=positive)


def check_scale(scale) -> str:
    """``scale`` as ``"linear"`` or ``"log"`` (see :data:`Scale`); InputError for anything else."""
    if scale not in ("linear", "log"):
        raise InputError(f"scale: expected 'linear' or 'log', got {scale!r}")
    return str(scale)


def _check_percentiles(percentiles) -> tuple[float, float]:
    expected = f"percentiles: expected two numbers (low, high) with 0 <= low < high <= 100, got {percentiles!r}"
    if isinstance(percentiles, (str, bytes)) or not hasattr(percentiles, "__len__") or len(percentiles) != 2:
        raise InputError(expected)
    lo, hi = percentiles
    if not all(isinstance(v, Real) and not isinstance(v, bool) for v in (lo, hi)) or not 0 <= lo < hi <= 100:
        raise InputError(expected)
    return float(lo), float(hi)


def _robust_range(values: np.ndarray, percentiles, name: str, what: str) -> tuple[float, float]:
    """Percentile range of ``values`` (already the valid ones), widened when degenerate."""
    p_lo, p_hi = _check_percentiles(percentiles)
    if values.size == 0:
        raise InputError(f"{name}: expected at least one {what} to choose a colour range, got none "
                         f"(pass vis_range)")
    lo, hi = (float(v) for v in np.percentile(values, [p_lo, p_hi]))
    if not hi > lo * (1.0 + 1e-6):  # a constant map: a range around its value
        lo, hi = lo / 1.25, lo * 1.25
    return lo, hi


def depth_range(depth, percentiles=(2.0, 98.0)) -> tuple[float, float]:
    """The default colour range of :func:`crfdepth.pictures.figures.depth_picture`: robust percentiles of the valid depths.

    The 2nd to 98th percentile by default, so a few very near points or the far
    background do not squeeze the colours of the rest. To give every frame of a sequence
    the same colours, compute it once (e.g. on the first frame) and pass it as
    ``vis_range`` to every picture.

    Args:
        depth: (H, W) depth in metres (also (1, H, W) or (1, 1, H, W); numpy or torch);
            0, negative or non-finite = no depth (ignored).
        percentiles: (low, high) percentiles, 0 <= low < high <= 100.

    Returns:
        ``(min_m, max_m)`` in metres, 0 < min_m < max_m (a constant map gets its value
        / 1.25 to its value * 1.25).

    Raises:
        InputError: not a 2-D real map, no valid depth, or bad ``percentiles``.
    """
    d = as_map("depth", depth)
    return _robust_range(d[np.isfinite(d) & (d > 0)], percentiles, "depth", "valid depth (finite, > 0 metres)")


def std_range(std, percentiles=(2.0, 98.0)) -> tuple[float, float]:
    """The default colour range of :func:`crfdepth.pictures.figures.std_picture`: robust percentiles of the stds > 0.

    Like :func:`depth_range`; zero stds are left out (the log scale has no place for
    them; they are painted with the bottom colour).

    Args:
        std: (H, W) standard deviation in metres (numpy or torch); negative or non-finite
            = no value (ignored).
        percentiles: (low, high) percentiles, 0 <= low < high <= 100.

    Returns:
        ``(min_m, max_m)`` in metres, 0 < min_m < max_m.

    Raises:
        InputError: not a 2-D real map, no std > 0, or bad ``percentiles``.
    """
    s = as_map("std", std)
    return _robust_range(s[np.isfinite(s) & (s > 0)], percentiles, "std", "finite std > 0 metres")


def colorize_depth(depth, vmin: float | None = None, vmax: float | None = None, *,
                   vis_range: tuple[float, float] | None = None, colormap: int = cv2.COLORMAP_TURBO,
                   invalid_color=BLACK) -> np.ndarray:
    """Colour map of a depth map, near = warm (no colour bar: see :func:`crfdepth.pictures.figures.depth_picture`).

    The colour is linear in inverse depth: ``t = (1/d - 1/vmax) / (1/vmin - 1/vmax)``,
    clipped to [0, 1], so ``vmin`` (and nearer) gets the warm end of ``colormap`` (dark
    red for TURBO) and ``vmax`` (and farther) the cold end (dark blue).

    Args:
        depth: (H, W) depth in metres (also (1, H, W) or (1, 1, H, W); numpy or torch);
            0, negative or non-finite = no depth.
        vmin: nearest depth of the scale, metres > 0; default the smallest valid depth.
        vmax: farthest depth of the scale, metres >= vmin; default the largest valid depth.
        vis_range: ``(min_m, max_m)`` instead of ``vmin`` / ``vmax`` (then leave those
            None), 0 < min_m < max_m: a fixed range gives the same colour to the same
            metres in every frame.
        colormap: an OpenCV colour map id (``cv2.COLORMAP_*``), low index = far.
        invalid_color: (R, G, B) of pixels without depth; default black.

    Returns:
        (H, W, 3) uint8 RGB. An all-invalid map is all ``invalid_color``; a constant map
        (vmin == vmax) is painted with the warm end.

    Raises:
        InputError: not a 2-D real map, vmin/vmax not finite with 0 < vmin <= vmax, or a
            bad ``vis_range`` (or given with vmin/vmax).
    """
    d = as_map("depth", depth)
    vmin, vmax = _range_or_bounds(vis_range, vmin, vmax, positive=True)
    valid = np.isfinite(d) & (d > 0)
    # Computed ends never cross a given one (e.g. vmin given beyond the farthest depth).
    if vmin is None:
        vmin = float(d[valid].min()) if valid.any() else 1.0
        vmin = vmin if vmax is None else min(vmin, float(vmax))
    vmin = float(vmin)
    if vmax is None:
        vmax = max(float(d[valid].max()), vmin) if valid.any() else vmin
    vmax = float(vmax)
    _check_range(vmin, vmax, "depths in metres")
    if vmin <= 0:
        raise InputError(f"vmin: expected a depth > 0 metres, got {vmin!r}")
    inverse = np.divide(1.0, d, out=np.zeros_like(d), where=valid)
    span = 1.0 / vmin - 1.0 / vmax
    t = (inverse - 1.0 / vmax) / span if span > 0 else np.ones_like(d)
    return _paint(t, valid, colormap, invalid_color)


def colorize_std(std, vmin: float | None = None, vmax: float | None = None, *,
                 vis_range: tuple[float, float] | None = None, scale: Scale = "linear",
                 percentile: float = 99.0, colormap: int = cv2.COLORMAP_VIRIDIS,
                 invalid_color=BLACK) -> np.ndarray:
    """Colour map of a standard-deviation (uncertainty) map, certain = dark (no colour bar:
    see :func:`crfdepth.pictures.figures.std_picture`).

    ``scale="linear"``: ``t = (std - vmin) / (vmax - vmin)``; ``scale="log"``:
    ``t = log(std / vmin) / log(vmax / vmin)``; clipped to [0, 1]. With VIRIDIS, ``vmin``
    (and below) is dark purple and ``vmax`` (and above) yellow. The std spans
    two or more decades (small at the LiDAR points, large far from them and in the sky,
    docs/design.md section 5); the linear scale paints everything near the data with one
    colour, the log scale shows its structure.

    Args:
        std: (H, W) standard deviation in metres (also (1, H, W) or (1, 1, H, W); numpy or
            torch); negative or non-finite = no value. 0 is a valid (fully certain) std
            (the bottom colour).
        vmin: std at the bottom of the scale, metres; default: linear 0, log the lower
            end of :func:`std_range` (2nd percentile of the stds > 0). Must be > 0 for log.
        vmax: std at the top of the scale, metres; default: linear the ``percentile``-th
            percentile of the valid stds (the std has a long tail in the sky and
            far background that would otherwise flatten the rest of the picture), log the
            upper end of :func:`std_range` (98th percentile).
        vis_range: ``(min_m, max_m)`` instead of ``vmin`` / ``vmax`` (then leave those
            None): a fixed range for a sequence; min_m > 0 for log, >= 0 for linear.
        scale: "linear" or "log".
        percentile: in (0, 100], the linear scale's default ``vmax``.
        colormap: an OpenCV colour map id (``cv2.COLORMAP_*``), low index = certain.
        invalid_color: (R, G, B) of pixels without a value; default black.

    Returns:
        (H, W, 3) uint8 RGB. A constant map (vmin == vmax) is painted with the low end.

    Raises:
        InputError: not a 2-D real map, vmin/vmax not finite with vmin <= vmax (vmin > 0
            for log), a bad ``vis_range`` / ``scale``, ``percentile`` outside (0, 100], or
            (log, no range given) no std > 0.
    """
    s = as_map("std", std)
    scale = check_scale(scale)
    vmin, vmax = _range_or_bounds(vis_range, vmin, vmax, positive=scale == "log")
    if not 0.0 < float(percentile) <= 100.0:
        raise InputError(f"percentile: expected a number in (0, 100], got {percentile!r}")
    valid = np.isfinite(s) & (s >= 0)
    if scale == "log":
        if vmin is None or vmax is None:
            low, high = std_range(s)
            vmin = low if vmin is None else vmin
            vmax = max(high, float(vmin)) if vmax is None else vmax  # never below a given bottom
        vmin, vmax = float(vmin), float(vmax)
        _check_range(vmin, vmax, "stds in metres")
        if vmin <= 0:
            raise InputError(f"vmin: expected a std > 0 metres for the log scale, got {vmin!r}")
        logs = np.log(np.maximum(np.where(valid, s, vmin), vmin))
        span = math.log(vmax / vmin)
        t = (logs - math.log(vmin)) / span if span > 0 else np.zeros_like(s)
        return _paint(t, valid, colormap, invalid_color)
    vmin = 0.0 if vmin is None else float(vmin)
    if vmax is None:  # a computed top never falls below the given bottom
        vmax = max(float(np.percentile(s[valid], percentile)), vmin) if valid.any() else vmin
    vmax = float(vmax)
    _check_range(vmin, vmax, "stds in metres")
    span = vmax - vmin
    t = (s - vmin) / span if span > 0 else np.zeros_like(s)
    return _paint(t, valid, colormap, invalid_color)


def draw_points(rgb: np.ndarray, sparse, vmin: float | None = None, vmax: float | None = None,
                radius: int = 1) -> np.ndarray:
    """The camera image with the LiDAR pixels drawn on it, coloured like :func:`colorize_depth`.

    Args:
        rgb: (H, W, 3) uint8 RGB image.
        sparse: (H, W) depth in metres, 0 = no LiDAR (numpy or torch).
        vmin, vmax: depth range of the colours (see :func:`colorize_depth`).
        radius: points are drawn as (2 radius + 1)-pixel squares.

    Returns:
        (H, W, 3) uint8 RGB, the image darkened to half so the points stand out.
    """
    s = as_map("sparse", sparse)
    if rgb.shape != (*s.shape, 3) or rgb.dtype != np.uint8:
        raise InputError(f"rgb: expected a {s.shape + (3,)} uint8 image like sparse, got {rgb.shape} {rgb.dtype}")
    colours = colorize_depth(s, vmin, vmax)
    valid = (np.isfinite(s) & (s > 0)).astype(np.uint8)
    if radius > 0:
        size = 2 * radius + 1
        # Nearest point wins inside a square: dilate inverse depth (max = nearest).
        inverse = np.where(valid > 0, 1.0 / np.where(valid > 0, s, 1.0), 0.0).astype(np.float32)
        grown = cv2.dilate(inverse, np.ones((size, size), np.uint8))
        colours = colorize_depth(np.divide(1.0, grown, out=np.zeros_like(grown), where=grown > 0), vmin, vmax)
        valid = (grown > 0).astype(np.uint8)
    out = (rgb // 2).copy()
    out[valid > 0] = colours[valid > 0]
    return out


def render_point_cloud(depth, rgb: np.ndarray, K: np.ndarray, *, max_depth: float = 80.0,
                       pitch_deg: float = 12.0, lift_m: float = 4.0, back_m: float = 10.0,
                       step: int = 1) -> np.ndarray:
    """A dense depth map as a coloured 3D point cloud seen from above and behind.

    Every ``step``-th pixel with ``0 < depth <= max_depth`` is back-projected with ``K``
    (camera frame: x right, y down, z forward, metres), then seen by a virtual camera with
    the same intrinsics, ``lift_m`` above and ``back_m`` behind the real one, pitched down
    by ``pitch_deg``. Points are splatted with a z-buffer (nearest wins) onto a black
    canvas of the image's size; gaps of one pixel are closed.

    Args:
        depth: (H, W) z-depth in metres (numpy or torch).
        rgb: (H, W, 3) uint8 colours of the pixels.
        K: (3, 3) intrinsics in pixels.

    Returns:
        (H, W, 3) uint8 RGB picture.
    """
    d = as_map("depth", depth)
    h, w = d.shape
    K = np.asarray(K, dtype=np.float64)
    if K.shape != (3, 3) or rgb.shape != (h, w, 3):
        raise InputError(f"K, rgb: expected (3, 3) and {(h, w, 3)}, got {K.shape} and {rgb.shape}")
    v, u = np.mgrid[0:h:step, 0:w:step]
    z = d[::step, ::step]
    keep = np.isfinite(z) & (z > 0) & (z <= max_depth)
    u, v, z = u[keep], v[keep], z[keep]
    colour = rgb[::step, ::step][keep]
    x = (u - K[0, 2]) * z / K[0, 0]
    y = (v - K[1, 2]) * z / K[1, 1]
    p = np.stack([x, y + lift_m, z + back_m], 1)  # virtual camera above (y down) and behind
    a = np.deg2rad(pitch_deg)
    rot = np.array([[1, 0, 0], [0, np.cos(a), -np.sin(a)], [0, np.sin(a), np.cos(a)]])
    p = p @ rot.T
    front = p[:, 2] > 0.5
    p, colour = p[front], colour[front]
    pu = np.round(K[0, 0] * p[:, 0] / p[:, 2] + K[0, 2]).astype(np.int64)
    pv = np.round(K[1, 1] * p[:, 1] / p[:, 2] + K[1, 2]).astype(np.int64)
    inside = (pu >= 0) & (pu < w) & (pv >= 0) & (pv < h)
    pu, pv, pz, colour = pu[inside], pv[inside], p[inside, 2], colour[inside]
    order = np.argsort(-pz)  # far first, near last: near points overwrite
    canvas = np.zeros((h, w, 3), np.uint8)
    zbuf = np.full((h, w), np.inf)
    canvas[pv[order], pu[order]] = colour[order]
    zbuf[pv[order], pu[order]] = pz[order]
    holes = ~np.isfinite(zbuf)
    closed = cv2.dilate(canvas, np.ones((2, 2), np.uint8))
    canvas[holes] = closed[holes]
    return canvas
