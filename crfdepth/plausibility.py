"""Whether a sparse depth map is plausibly metres of a real LiDAR scene, and if not, its likely unit.

A map in the wrong unit passes every shape and range check and gives a confident, wrong
depth, so every sparse map (an array, a PNG of any unit, a KITTI folder frame) is checked
against the statistics of real scenes before the CRF sees it; the refusal names the unit
that, rescaled, fits and the fix (docs/design.md sections 1 and 8). Messages follow
:mod:`crfdepth.checks`: ``<name>: expected <what>, got <what was received>``.
"""

from __future__ import annotations

import math
import warnings

import numpy as np
import torch

from crfdepth.errors import InputError

__all__ = [
    "CODES_PER_METRE",
    "ImplausibleDepth",
    "PlausibilityWarning",
    "UpsideDownWarning",
    "MAX_LIDAR_DEPTH_M",
    "SPARSE_UNITS",
    "check_sparse_plausible",
    "check_sparse_orientation",
    "check_sparse_units",
    "likely_units",
]

# No LiDAR sees further: a sparse map whose median depth exceeds this is not in metres.
MAX_LIDAR_DEPTH_M = 300.0
# Codes per metre of each unit a sparse depth map (or a 16-bit PNG) may be in.
CODES_PER_METRE = {"kitti": 256.0, "mm": 1000.0, "cm": 100.0, "m": 1.0}
# The units ``crfdepth complete --sparse-units`` reads a sparse PNG in.
SPARSE_UNITS = ("kitti", "mm", "m")
NEAR_M, FAR_M = 1.0, 200.0
MAX_NEAR_SHARE = 0.5  # at most this share of the returns nearer than NEAR_M
MAX_FAR_SHARE = 0.02  # at most this share beyond FAR_M
MAX_CAMERA_HEIGHT_M = 4.0  # the ground at most this far below the camera ...
DEEP_MEDIAN_M = 20.0  # ... where the median depth exceeds this
MIN_CAMERA_HEIGHT_M = 0.2  # a unit guess must put the camera at least this high
TYPICAL_CAMERA_HEIGHT_M = 1.5  # unit guesses are ranked by their closeness to it
TYPICAL_MEDIAN_M = 10.0  # or, without a ground estimate, to this median
_MIN_GROUND_RETURNS = 20


def _camera_height(depth: np.ndarray, K: np.ndarray | None) -> float | None:
    """How far the ground lies below the camera, metres, from the returns of the image's
    bottom quarter: the 90th percentile of their camera-frame ``y = (v - cy) z / fy``
    (y down); None without K or with fewer than 20 such returns below the principal point."""
    if K is None:
        return None
    height = depth.shape[0]
    rows, cols = np.nonzero(depth[height - height // 4:] > 0)
    rows = rows + (height - height // 4)
    below = rows > K[1, 2]
    if np.count_nonzero(below) < _MIN_GROUND_RETURNS:
        return None
    y = (rows[below] - K[1, 2]) * depth[rows[below], cols[below]] / K[1, 1]
    return float(np.percentile(y, 90))


def _implausible(values: np.ndarray, camera_height: float | None) -> tuple[str, str] | None:
    """(expected, got) of the first rule of :func:`check_sparse_plausible` that ``values``
    (the non-zero depths, metres) break, or None."""
    median = float(np.median(values))
    near, far = float(np.mean(values < NEAR_M)), float(np.mean(values > FAR_M))
    stats = f"median {median:.4g} m over {values.size} return(s)"
    if median > MAX_LIDAR_DEPTH_M:
        return f"a median of at most {MAX_LIDAR_DEPTH_M:g} m, the reach of a LiDAR", f"a {stats}"
    if near > MAX_NEAR_SHARE:
        return (f"at most {MAX_NEAR_SHARE:.0%} of the returns nearer than {NEAR_M:g} m",
                f"{near:.0%} of them (a {stats})")
    if far > MAX_FAR_SHARE:
        return (f"at most {MAX_FAR_SHARE:.0%} of the returns beyond {FAR_M:g} m",
                f"{far:.1%} of them (a {stats})")
    if camera_height is not None and camera_height > MAX_CAMERA_HEIGHT_M and median > DEEP_MEDIAN_M:
        return (f"the ground at most {MAX_CAMERA_HEIGHT_M:g} m below the camera where the median depth exceeds "
                f"{DEEP_MEDIAN_M:g} m", f"the ground {camera_height:.3g} m below it (the returns of the image's "
                                         f"bottom quarter) and a {stats}")
    return None


# What each unit guess says, by how the map was read: an array meant to be metres ("api"), or a
# PNG read by ``crfdepth complete --sparse-units`` in one of SPARSE_UNITS.
_API_HINTS = {
    "kitti": "the raw codes of a KITTI depth PNG (metres * 256, as cv2.imread(path, -1) returns them): divide by "
             "256 (crfdepth.io.kitti.read_depth_png does)",
    "mm": "millimetres: divide by 1000",
    "cm": "centimetres: divide by 100",
    "mm-png": "a millimetre PNG read as a KITTI PNG (metres * 256, e.g. by read_depth_png): read its codes with "
              "cv2.imread(path, -1) and divide by 1000",
    "m-png": "a PNG of whole metres read as a KITTI PNG (metres * 256, e.g. by read_depth_png): use its codes "
             "(cv2.imread(path, -1)) as metres",
}


def _guesses(read_as: str) -> dict[str, float]:
    """Unit guess -> factor from the map as read to metres in that unit."""
    if read_as == "api":
        return {"kitti": 1 / 256.0, "mm": 1e-3, "cm": 1e-2, "mm-png": 256.0 / 1000.0, "m-png": 256.0}
    here = CODES_PER_METRE[read_as]
    return {unit: here / per for unit, per in CODES_PER_METRE.items() if unit != read_as}


def _hint(read_as: str, unit: str) -> str:
    if read_as == "api":
        return _API_HINTS[unit]
    if unit == "cm":
        return "centimetres: no --sparse-units reads them; write the PNG in millimetres or as KITTI (metres * 256)"
    names = {"kitti": "KITTI codes (metres * 256)", "mm": "millimetres", "m": "whole metres"}
    return f"{names[unit]}: pass --sparse-units {unit}"


class ImplausibleDepth(InputError):
    """The refusal of :func:`check_sparse_plausible`. It keeps the map and K it judged, so that
    :meth:`retold` can say it again under another name and reading (the CLI's ``--sparse`` file and
    its ``--sparse-units``) without the map being checked twice when it passes."""

    def __init__(self, message: str, depth: np.ndarray | None = None, K: np.ndarray | None = None):
        super().__init__(message)
        self.depth, self.K = depth, K

    def retold(self, name: str, read_as: str) -> InputError:
        """The same refusal of the same map, naming ``name``, with the hints of ``read_as``
        (:func:`check_sparse_plausible`'s argument)."""
        if self.depth is None:
            return self
        try:
            check_sparse_plausible(name, self.depth, self.K, read_as=read_as)
        except InputError as exc:
            return exc
        return self


def check_sparse_plausible(name: str, depth: object, K: object = None, *, read_as: str = "api") -> None:
    """Refuse a sparse depth map that cannot be metres of a real LiDAR scene, naming the likely unit.

    The map (metres, 0 = no return) is refused when one of these holds for its returns
    (non-zero pixels), in this order:

    1. the median exceeds :data:`MAX_LIDAR_DEPTH_M` (300 m, the reach of a LiDAR);
    2. more than 50 % are nearer than 1 m (a plain-metres PNG read as metres * 256: all are);
    3. more than 2 % lie beyond 200 m;
    4. with ``K``: the ground lies more than 4 m below the camera while the median exceeds
       20 m. The ground's depth below the camera is the 90th percentile of the camera-frame
       height ``(v - cy) z / fy`` of the returns in the image's bottom quarter (needs 20 of
       them): a camera ``h`` above a flat ground sees it at exactly ``h``, whatever the row.
       This is what catches a millimetre PNG read as metres * 256 (depth 3.9x too deep): its
       median alone can look like an open road.

    Margins, measured on the shared KITTI data (the official val_selection_cropped and
    depth-completion maps; the raw scans of drives 0001 and 0060 and the 11 object frames
    projected, 64 beams and every 4th ring = 16 beams) and on the synthetic street
    (``make_scene`` seeds 0-5, 64 and 16 beams, and the docs/example rig): medians 5.9-15.8 m
    (rule 1: 19x margin), no return under 1 m or over 200 m (rules 2, 3: 0 % against 50 % and
    2 %), the ground 1.56-1.92 m below the camera (rule 4: 2.1x margin to 4 m; the medians
    stay 1.27x below 20 m). The same maps read in the wrong unit: plain metres as KITTI
    codes put 100 % of the returns under 1 m; millimetres as KITTI codes put the ground
    6.1-7.5 m below the camera with medians of 23-62 m (rule 4), or more than 2 % of the
    returns beyond 200 m; raw KITTI codes or millimetres as metres have medians over 1400 m.

    How the likely unit is told: each other unit (for an array meant as metres: raw KITTI
    codes, millimetres, centimetres, a millimetre or whole-metre PNG read as metres * 256;
    for a PNG read by ``--sparse-units U``: the other units) rescales the map, and the
    rescaled maps that pass the four rules and put the ground at least 0.2 m below the
    camera are named, closest first to a camera 1.5 m above the ground (without a ground
    estimate: to a median of 10 m). So centimetres get their own hint when the ground is
    seen (KITTI codes read as centimetres would put the camera 0.64 m high and come second);
    where two units both fit (a low robot camera), both are named.

    Args:
        name: the user's name of the map (``sparse``, ``--sparse x.png``).
        depth: (H, W) array or tensor in metres (0 = no return); NaN, infinite and negative
            values are ignored here (other checks refuse them).
        K: (3, 3) intrinsics of the image, pixels, or None (rule 4 is then skipped).
        read_as: ``"api"`` for an array meant as metres (hints say what to divide by), or the
            ``--sparse-units`` the PNG was read in (hints name the option).

    Rule 4 is a guess about the rig (a camera less than 4 m above the ground); a caller whose
    camera is higher turns it off by passing ``K=None`` (``complete_depth(trust_units=True)``,
    an explicit ``--sparse-units``), and its message says so.

    Raises:
        InputError: ``<name>: expected depth in metres (<rule>), got <statistic>; that looks
            like <unit>: <fix>``.
    """
    array = depth.detach().cpu().numpy() if isinstance(depth, torch.Tensor) else np.asarray(depth)
    array = np.where(np.isfinite(array) & (array > 0), array, 0).astype(np.float64) if array.dtype.kind == "f" \
        else np.where(array > 0, array, 0).astype(np.float64)
    values = array[array > 0]
    if values.size == 0:
        return
    K = None if K is None else np.asarray(K.detach().cpu() if isinstance(K, torch.Tensor) else K, dtype=np.float64)
    broken = _implausible(values, _camera_height(array, K))
    if broken is None:
        return
    ranked = _ranked_units(array, values, K, _guesses(read_as))
    expected, got = broken
    message = f"{name}: expected depth in metres ({expected}), got {got}"
    if ranked:
        hints = [_hint(read_as, unit) for unit in ranked]
        message += f"; that looks like {hints[0]}" + "".join(f"; or {h}" for h in hints[1:])
    else:
        message += "; check the unit and the scale of the map"
    if expected.startswith("the ground"):  # rule 4 is a guess about the rig: say how to overrule it
        message += ("; if the camera really is that high (a mast, a drone), pass trust_units=True" if read_as == "api"
                    else f"; if the camera really is that high (a mast, a drone), give --sparse-units {read_as} "
                         f"explicitly")
    raise ImplausibleDepth(message, array, K)


def _ranked_units(array: np.ndarray, values: np.ndarray, K: np.ndarray | None, guesses: dict[str, float]) -> list[str]:
    """The units of ``guesses`` (unit -> factor to metres) under which the map passes the rules of
    :func:`check_sparse_plausible` with the camera at least 0.2 m above the ground, closest first to a camera
    1.5 m above it (without a ground estimate: to a median of 10 m)."""
    ranked = []
    for unit, factor in guesses.items():
        height = _camera_height(array * factor, K)
        if _implausible(values * factor, height) is None and (height is None or height >= MIN_CAMERA_HEIGHT_M):
            closeness = abs(math.log(height / TYPICAL_CAMERA_HEIGHT_M)) if height is not None else \
                abs(math.log(float(np.median(values)) * factor / TYPICAL_MEDIAN_M))
            ranked.append((closeness, unit))
    return [unit for _, unit in sorted(ranked)]


#: What each unit of :func:`likely_units` says for a point cloud.
POINT_UNIT_HINTS = {"cm": "centimetres: divide them by 100", "mm": "millimetres: divide them by 1000"}


def likely_units(depth: np.ndarray, K: object = None, units: tuple[str, ...] = ("cm", "mm")) -> list[str]:
    """Which of ``units`` (keys of :data:`CODES_PER_METRE`) make an (H, W) depth map read as metres (0 = no
    return) a plausible LiDAR map, most likely first (the ranking of :func:`check_sparse_plausible`); empty
    when none does. Tells centimetres (100x too deep) from millimetres (1000x) for the advice of a map or a
    point cloud in the wrong unit."""
    array = np.where(np.isfinite(depth) & (depth > 0), depth, 0).astype(np.float64)
    values = array[array > 0]
    if values.size == 0:
        return []
    K = None if K is None else np.asarray(K, dtype=np.float64)
    return _ranked_units(array, values, K, {unit: 1.0 / CODES_PER_METRE[unit] for unit in units})


def check_sparse_units(name: str, sparse: object) -> None:
    """:func:`check_sparse_plausible` without K: rules 1-3, the depth values alone, for a map whose camera is
    not known."""
    check_sparse_plausible(name, sparse)


# --------------------------------------------------------------------------- orientation


class PlausibilityWarning(UserWarning):
    """An input that passes every check but looks wrong against the statistics of real frames (an upside-down
    map, a K of another image size): warned, not refused, since an unusual rig can produce it."""


class UpsideDownWarning(PlausibilityWarning):
    """A sparse map whose depth increases downwards (:func:`check_sparse_orientation`)."""


# check_sparse_orientation: warn when the rank correlation of depth with the row is at least UPSIDE_DOWN_MIN_RHO
# and the top quarter of the returns (by row) has at most UPSIDE_DOWN_MAX_RATIO times the bottom quarter's median
# depth, with at least UPSIDE_DOWN_MIN_RETURNS returns.
UPSIDE_DOWN_MIN_RHO = 0.4
UPSIDE_DOWN_MAX_RATIO = 0.7
UPSIDE_DOWN_MIN_RETURNS = 50


def _average_ranks(x: np.ndarray) -> np.ndarray:
    """Ranks of ``x`` from 0, ties given their mean rank (Spearman's convention)."""
    _, inverse, counts = np.unique(x, return_inverse=True, return_counts=True)
    starts = np.cumsum(counts) - counts
    return (starts + (counts - 1) / 2.0)[inverse.reshape(-1)]


def row_depth_statistics(depth: np.ndarray) -> tuple[float, float, float, int] | None:
    """``(rho, top, bottom, n)`` of an (H, W) depth map in metres (0 = no return): Spearman's rank correlation
    of the returns' depth with their row (row 0 at the top), the median depth of the top and of the bottom
    quarter of the returns by row, metres, and the number of returns; None with fewer than 2 rows of returns."""
    rows, cols = np.nonzero(np.isfinite(depth) & (depth > 0))
    if rows.size < 2 or rows.min() == rows.max():
        return None
    z = np.asarray(depth[rows, cols], dtype=np.float64)
    rv, rz = _average_ranks(rows), _average_ranks(z)
    rv, rz = rv - rv.mean(), rz - rz.mean()
    scale = math.sqrt(float(rv @ rv) * float(rz @ rz))
    rho = float(rv @ rz) / scale if scale > 0 else 0.0
    quarter = max(1, rows.size // 4)  # np.nonzero gives the returns in row order
    return rho, float(np.median(z[:quarter])), float(np.median(z[-quarter:])), int(rows.size)


def check_sparse_orientation(name: str, depth: object, *, fix: str | None = None) -> bool:
    """Warn (:class:`UpsideDownWarning`) when a sparse depth map looks upside down against its image.

    A camera sees the ground nearest at the bottom of its image and the scene deepens towards the horizon, so
    the depth of real LiDAR returns falls from the top rows to the bottom ones. The map is taken for upside down
    when, over at least 50 returns, the Spearman rank correlation of depth with the row (row 0 at the top) is at
    least ``UPSIDE_DOWN_MIN_RHO`` (+0.4) and the top quarter of the returns (by row) has a median depth at most
    ``UPSIDE_DOWN_MAX_RATIO`` (0.7) times the bottom quarter's. Measured (:func:`row_depth_statistics`; rho,
    top / bottom): shared KITTI velodyne_raw, ground truth, depth-selection crops, the projected raw scans of
    drives 0001, 0048 and 0060 and the 11 object frames: rho -0.98 to -0.11, ratio 1.01 to 5.5; synthetic street
    seeds 0-5 (64 and 16 beams) and docs/example: -0.89 to -0.67, 3.0 to 5.1; NYU v2 frames (full Kinect depth
    and 500 samples, the crop, the 160x120 frame): -0.89 to -0.21, 1.09 to 5.1. Flipped, the same maps give
    +0.11 to +0.98 (so a few flat, open scenes are not told) and 0.18 to 1.0.

    Args:
        name: the user's name of the map (``sparse``; ``points`` / ``T_cam_lidar`` for a projected cloud).
        depth: (H, W) array or tensor, metres, 0 = no return.
        fix: what to do about it; default: flip the map (or the image).

    Returns:
        Whether it warned.
    """
    array = depth.detach().cpu().float().numpy() if isinstance(depth, torch.Tensor) else np.asarray(depth)
    if array.ndim != 2:
        return False
    stats = row_depth_statistics(array)
    if stats is None:
        return False
    rho, top, bottom, count = stats
    if count < UPSIDE_DOWN_MIN_RETURNS or rho < UPSIDE_DOWN_MIN_RHO or top > UPSIDE_DOWN_MAX_RATIO * bottom:
        return False
    fix = fix or (f"flip it ({name}[::-1] for an (H, W) array, or np.flipud) or flip the image, whichever of the "
                  f"two is upside down; a camera mounted upside down needs both rotated")
    warnings.warn(f"{name}: expected depth that decreases towards the bottom of the image (the ground nearest at "
                  f"the bottom), got a map that looks upside down: the depth increases downwards (rank correlation "
                  f"with the row {rho:+.2f} over {count} returns; median {top:.3g} m in the top quarter of the "
                  f"returns, {bottom:.3g} m in the bottom quarter); {fix}", UpsideDownWarning, stacklevel=3)
    return True
