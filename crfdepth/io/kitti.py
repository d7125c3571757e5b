"""Readers and writers for the KITTI data files (docs/design.md section 1).

Covers the depth-completion PNGs (uint16, depth = value / 256, 0 = missing), the
camera images, the 3x3 intrinsics of ``val_selection_cropped/intrinsics`` and the
Velodyne scans (``N x 4`` float32 ``.bin``). Both KITTI calibration formats are read by
:mod:`crfdepth.io.calibration`.

Missing files raise ``FileNotFoundError`` naming the path; files that exist but hold
the wrong content raise :class:`crfdepth.errors.InputError` naming the file, what was
expected and what was found.
"""

from __future__ import annotations

import logging
import math
import os
from pathlib import Path

import cv2
import numpy as np

from crfdepth.checks import check_choice
from crfdepth.errors import InputError
from crfdepth.io.files import MAX_CALIBRATION_BYTES, atomic_write_bytes, check_input_file, read_text
from crfdepth.plausibility import MAX_LIDAR_DEPTH_M, TYPICAL_MEDIAN_M

__all__ = ["MAX_PNG_DEPTH_M", "check_png_depth", "depth_png_codes", "read_depth_png", "read_intrinsics", "read_rgb", "read_velodyne",
           "write_depth_png"]

logger = logging.getLogger(__name__)
PathLike = str | os.PathLike

# KITTI depth PNGs store depth * 256 as uint16.
_DEPTH_SCALE = 256.0
# Codes per metre of the units a depth PNG may be read in (read_depth_png).
_UNIT_SCALES = {"kitti": _DEPTH_SCALE, "mm": 1000.0, "m": 1.0}
_UINT16_MAX = np.iinfo(np.uint16).max
MAX_PNG_DEPTH_M = _UINT16_MAX / _DEPTH_SCALE
"""The deepest value a KITTI depth PNG holds: 65535 / 256 = 255.996 m."""


# --------------------------------------------------------------------------- helpers


def _decode_image(path: PathLike, what: str) -> np.ndarray:
    """Decode an image file with ``cv2.IMREAD_UNCHANGED`` (no bit-depth or channel change)."""
    path = check_input_file(path, what)
    buffer = np.fromfile(path, dtype=np.uint8)
    image = cv2.imdecode(buffer, cv2.IMREAD_UNCHANGED) if buffer.size else None
    if image is None:
        raise InputError(f"{what}: {path} is not a readable image ({buffer.size} bytes)")
    return image


# --------------------------------------------------------------------------- depth PNG


def read_depth_png(path: PathLike, units: str = "kitti") -> np.ndarray:
    """Read a sparse or dense depth PNG (velodyne_raw, groundtruth or a prediction).

    Args:
        path: 16-bit single-channel PNG.
        units: what its codes are: ``"kitti"`` (the KITTI format, metres * 256), ``"mm"``
            (millimetres) or ``"m"`` (whole metres); ``crfdepth complete --sparse-units``.

    Returns:
        (H, W) float32 depth in metres (codes / 256, / 1000 or / 1); 0 = no measurement.

    Raises:
        FileNotFoundError: ``path`` does not exist.
        InputError: the file is not a 16-bit single-channel image, or ``units`` is unknown.
    """
    check_choice("units", units, tuple(_UNIT_SCALES))
    image = _decode_image(path, "depth png")
    if image.dtype != np.uint16 or image.ndim != 2:
        channels = 1 if image.ndim == 2 else image.shape[2]
        raise InputError(
            f"depth png: expected a 16-bit single-channel PNG (depth * 256), got {image.dtype} "
            f"with {channels} channel(s) in {path}")
    return image.astype(np.float32) / np.float32(_UNIT_SCALES[units])


def write_depth_png(path: PathLike, depth: np.ndarray) -> None:
    """Write a depth map as a KITTI depth PNG (uint16, ``round(depth * 256)``).

    The file appears atomically: the PNG is written to a temporary file in the same
    directory and moved onto ``path`` only when complete, so a failure never leaves a
    half-written file. ``read_depth_png(write_depth_png(p, x))`` returns ``x`` exactly when
    every value is a multiple of 1/256 m in [0, 65535/256].

    Args:
        path: output file; must end in ``.png``; its directory must exist.
        depth: (H, W) depth in metres, 0 = missing. Values are rounded to the nearest
            1/256 m, so a positive depth below 1/512 m also becomes 0 (missing); depths
            above ``MAX_PNG_DEPTH_M`` = 65535/256 m (about 256 m) are clipped to the largest
            code, with a logged warning: call :func:`check_png_depth` first to refuse them.

    Raises:
        InputError: ``depth`` is not a 2-D real array, holds NaN, infinite or negative
            values, or ``path`` does not end in ``.png``.
        FileNotFoundError: the directory of ``path`` does not exist.
        PermissionError: the directory is not writable.
    """
    path = Path(path)
    array = np.asarray(depth)
    if array.ndim != 2:
        raise InputError(f"depth: expected a 2-D (H, W) array in metres, got shape {array.shape}")
    if not (np.issubdtype(array.dtype, np.floating) or np.issubdtype(array.dtype, np.integer)):
        raise InputError(f"depth: expected a real-valued array in metres, got dtype {array.dtype}")
    if array.size and not np.all(np.isfinite(array)):
        raise InputError(f"depth: expected finite values in metres (0 = missing), got "
                         f"{int(np.count_nonzero(~np.isfinite(array)))} NaN or infinite value(s)")
    if array.size and array.min() < 0:
        raise InputError(f"depth: expected values >= 0 metres (0 = missing), got minimum {array.min()}")
    if path.suffix.lower() != ".png":
        raise InputError(f"path: expected a file name ending in .png, got {path}")
    directory = path.parent
    if not directory.is_dir():
        raise FileNotFoundError(f"depth png: output directory does not exist: {directory}")

    codes = depth_png_codes(array, path)
    ok, encoded = cv2.imencode(".png", codes)
    if not ok:  # pragma: no cover - cv2 encodes any 2-D uint16 array
        raise InputError(f"depth: could not encode an array of shape {codes.shape} as PNG")

    atomic_write_bytes(path, encoded.tobytes())


def depth_png_codes(depth: np.ndarray, where: object = "depth") -> np.ndarray:
    """The uint16 codes of a KITTI depth PNG for ``depth`` (metres, finite, >= 0): ``round(depth * 256)``;
    values beyond ``MAX_PNG_DEPTH_M`` are clipped to the largest code with a logged warning naming ``where``."""
    codes = np.round(np.asarray(depth, np.float64) * _DEPTH_SCALE)
    if codes.size and codes.max() > _UINT16_MAX:
        logger.warning("%s: %d depth value(s) beyond %.3f m (up to %.4g m) clipped to the largest code of a KITTI "
                       "depth PNG", where, np.count_nonzero(codes > _UINT16_MAX), MAX_PNG_DEPTH_M,
                       float(np.max(depth)))
    return np.clip(codes, 0, _UINT16_MAX).astype(np.uint16)


def check_png_depth(name: str, depth: np.ndarray) -> None:
    """Refuse a depth map a KITTI depth PNG cannot hold: a value beyond ``MAX_PNG_DEPTH_M`` (65535/256 =
    255.996 m), which :func:`write_depth_png` would clip. ``name`` is the user's name of its source."""
    far = np.asarray(depth) > MAX_PNG_DEPTH_M
    if far.any():
        raise InputError(f"{name}: expected depths a KITTI depth PNG holds (16 bits, metres * 256: at most "
                         f"{MAX_PNG_DEPTH_M:.3f} m), got {np.count_nonzero(far)} pixel(s) beyond, up to "
                         f"{float(np.max(depth)):.4g} m; refusing to clip them")


# --------------------------------------------------------------------------- images


def read_rgb(path: PathLike) -> np.ndarray:
    """Read a camera image as RGB.

    Args:
        path: 8-bit PNG/JPEG. A greyscale image (KITTI cameras 0 and 1) is repeated over
            the three channels; an alpha channel is dropped.

    Returns:
        (H, W, 3) uint8 image in RGB channel order.

    Raises:
        FileNotFoundError: ``path`` does not exist.
        InputError: the file is not an 8-bit image.
    """
    image = _decode_image(path, "image")
    if image.dtype != np.uint8:
        raise InputError(f"image: expected an 8-bit image, got {image.dtype} in {path}")
    if image.ndim == 2:
        return np.repeat(image[:, :, None], 3, axis=2)
    if image.shape[2] == 4:
        return cv2.cvtColor(image, cv2.COLOR_BGRA2RGB)
    if image.shape[2] == 3:
        return cv2.cvtColor(image, cv2.COLOR_BGR2RGB)
    raise InputError(f"image: expected 1, 3 or 4 channels, got {image.shape[2]} in {path}")


# --------------------------------------------------------------------------- intrinsics


def read_intrinsics(path: PathLike) -> np.ndarray:
    """Read the 3x3 camera matrix of ``val_selection_cropped/intrinsics/*.txt``.

    Args:
        path: text file with the 9 entries of K, row-major, separated by white space.

    Returns:
        (3, 3) float64 K in pixels (fx, fy, cx, cy already follow the benchmark's crop).

    Raises:
        FileNotFoundError: ``path`` does not exist.
        InputError: the file does not hold exactly 9 numbers, or is not text (an image?).
    """
    path = check_input_file(path, "intrinsics")
    tokens = read_text(path, "intrinsics", "9 numbers (row-major 3x3 K)", max_bytes=MAX_CALIBRATION_BYTES).split()
    try:
        values = np.array([float(token) for token in tokens], dtype=np.float64)
    except ValueError as exc:
        raise InputError(f"intrinsics: expected 9 numbers in {path}, got non-numeric text ({exc})") from None
    if values.size != 9:
        raise InputError(f"intrinsics: expected 9 numbers (row-major 3x3 K) in {path}, got {values.size}")
    return values.reshape(3, 3)


# --------------------------------------------------------------------------- Velodyne

_POINT_BYTES = 16  # a KITTI scan's point: 4 little-endian float32, x, y, z, reflectance
# What a scan's values may be (read_velodyne). Coordinates are metres: the median range of the
# shared KITTI scans is 4.9-12.2 m (the synthetic street's: 8.0-8.6 m). No LiDAR sees half its
# returns nearer than 0.1 m (minimum ranges are 0.1-1 m) or further than MAX_LIDAR_DEPTH_M = 300 m,
# its reach: a scan in millimetres or centimetres (a median in the thousands or hundreds) fails.
MIN_SCAN_MEDIAN_RANGE_M = 0.1
# No coordinate of a scan in any length unit comes near this (10,000 km in metres, 10 km in
# millimetres): larger values are bytes that are not float32 coordinates (float64, another format).
MAX_SCAN_COORDINATE = 1e7
# Reflectance is >= 0 (KITTI's: 0-0.99). An N x 3 float32 file read as N x 4 puts x, y and z in
# that column: negative in about 60 % of the rows of the shared scans; above 1 % is that evidence.
MAX_NEGATIVE_REFLECTANCE_SHARE = 0.01
# In a scan's sensor order consecutive points lie 2-3 cm apart (median, shared scans); read in the
# wrong layout, 6-10 m apart. A layout whose median step is below this fraction of the other's is the file's.
SCAN_ORDER_RATIO = 0.25
# The units a scan may be in by mistake (the refusal's hint) and their factor to metres.
_SCAN_UNITS = {"millimetres: divide the coordinates by 1000": 1e-3, "centimetres: divide the coordinates by 100": 1e-2,
               "kilometres: multiply the coordinates by 1000": 1e3}
_ADD_REFLECTANCE = "numpy.hstack([xyz, numpy.zeros((len(xyz), 1))]).astype(numpy.float32).tofile(path)"


def read_velodyne(path: PathLike, name: str = "velodyne") -> np.ndarray:
    """Read a KITTI Velodyne scan, checked to be one (the reader of every ``.bin`` scan).

    Args:
        path: ``.bin`` file of little-endian float32 records (x, y, z, reflectance).
        name: the user's name of the file in messages (``velodyne``, ``points``).

    Returns:
        (N, 4) float32: x, y, z in metres in the Velodyne frame (x forward, y left,
        z up) and reflectance in [0, 1], in the sensor's scan order (which
        :func:`crfdepth.geometry.projection.recover_rings` relies on).

    Raises:
        FileNotFoundError: ``path`` does not exist.
        InputError: ``<name>: expected ..., got ...`` naming the file: empty; a size that is
            not a multiple of 16 bytes (4 float32 per point); NaN or infinite values; a
            coordinate beyond ``MAX_SCAN_COORDINATE`` (1e7); a median range (distance from the
            sensor) outside [``MIN_SCAN_MEDIAN_RANGE_M``, ``MAX_LIDAR_DEPTH_M``] = [0.1, 300] m,
            naming millimetres, centimetres or kilometres where one of them fits. A file in
            another layout is named when its bytes read so pass these checks: float64 (N x 4 or
            N x 3; read as float32 its values are garbage) or N x 3 float32 (x, y, z: read as
            N x 4, over 1 % of the reflectance values negative, or consecutive points metres
            apart where the N x 3 reading keeps the scan order's centimetres).
    """
    path = check_input_file(path, name)
    size = path.stat().st_size
    expected = f"a KITTI Velodyne scan (N x 4 float32: x, y, z, reflectance; {_POINT_BYTES} bytes per point)"
    if size == 0:
        raise InputError(f"{name}: expected {expected}, got an empty file (0 bytes): {path}")
    raw = np.fromfile(path, dtype=np.uint8)
    if size % _POINT_BYTES:
        layout = _other_layout(raw, None, None)
        raise InputError(f"{name}: expected a file size that is a multiple of {_POINT_BYTES} bytes (N x 4 float32: x, "
                         f"y, z, reflectance), got {size} bytes in {path}: not a whole number of points (a truncated "
                         f"file or not a KITTI Velodyne scan)" + (f"; it looks like {layout}" if layout else ""))
    points = raw.view("<f4").astype(np.float32, copy=False).reshape(-1, 4)
    problem = _scan_problem(points)
    negative = float(np.mean(points[:, 3] < 0))
    if problem is not None or negative > MAX_NEGATIVE_REFLECTANCE_SHARE:
        what = problem[1] if problem else f"{negative:.0%} of the reflectance values (4th column) negative"
        layout = _other_layout(raw, points, what)
        if layout is not None:
            raise InputError(f"{name}: expected {expected}, got {path}, which looks like {layout}")
    if problem is not None:
        raise InputError(f"{name}: expected {problem[0]}, got {problem[1]} in {path}{problem[2]}")
    return points


def _scan_problem(points: np.ndarray) -> tuple[str, str, str] | None:
    """(expected, got, hint) of the first value check of :func:`read_velodyne` that (N, C >= 3) ``points`` fail,
    or None."""
    finite = np.isfinite(points)
    if not finite.all():
        return "finite values", f"{np.count_nonzero(~finite)} NaN or infinite value(s) among {points.size}", ""
    xyz = points[:, :3]
    largest = float(np.abs(xyz).max())
    if largest > MAX_SCAN_COORDINATE:
        return f"coordinates within +-{MAX_SCAN_COORDINATE:g} (metres)", f"values up to {largest:.3g}", ""
    median = _median_range(xyz)
    if MIN_SCAN_MEDIAN_RANGE_M <= median <= MAX_LIDAR_DEPTH_M:
        return None
    fits = [(abs(math.log(median * factor / TYPICAL_MEDIAN_M)), unit) for unit, factor in _SCAN_UNITS.items()
            if MIN_SCAN_MEDIAN_RANGE_M <= median * factor <= MAX_LIDAR_DEPTH_M]
    return (f"coordinates in metres (a median range from the sensor of {MIN_SCAN_MEDIAN_RANGE_M:g} to "
            f"{MAX_LIDAR_DEPTH_M:g} m)", f"a median range of {median:.4g}" + (" (every point at the sensor)" if
                                                                           median == 0 else ""),
            f"; that looks like {min(fits)[1]}" if fits else "")


def _median_step(points: np.ndarray) -> float:
    """Median distance between consecutive rows of (N, C >= 3) ``points``; NaN for fewer than two."""
    if len(points) < 2:
        return math.nan
    return float(np.median(np.linalg.norm(np.diff(points[:, :3].astype(np.float64), axis=0), axis=1)))


def _median_range(points: np.ndarray) -> float:
    """Median distance of (N, C >= 3) ``points`` from the sensor (the root of the median squared distance)."""
    xyz = points[:, :3]
    return math.sqrt(float(np.median(np.einsum("ij,ij->i", xyz, xyz))))


def _other_layout(raw: np.ndarray, points: np.ndarray | None, what: str | None) -> str | None:
    """The layout the bytes ``raw`` of a scan are in, with the evidence and the fix, when N x 4 float32 is not
    (``points``, which show ``what``; None when the size does not fit it): float64 or N x 3 float32, whichever
    reading passes :func:`_scan_problem` (and keeps the scan order better); None when none does."""
    size = raw.size
    read4 = f"read as N x 4 float32 it holds {what}, " if points is not None else ""
    for columns in (4, 3):
        if size % (8 * columns) == 0:
            wide = raw.view("<f8").reshape(-1, columns)
            negative = 0.0 if columns == 3 else float(np.mean(wide[:, 3] < 0))
            if _scan_problem(wide) is None and negative <= MAX_NEGATIVE_REFLECTANCE_SHARE:
                fix = ("points.astype(numpy.float32).tofile(path)" if columns == 4 else
                       f"with a reflectance column, e.g. {_ADD_REFLECTANCE}")
                return (f"float64 ({len(wide)} x {columns} float64, {8 * columns} bytes per point): {read4}read as "
                        f"float64 its points have a median range of {_median_range(wide):.3g} m; write it as float32, {fix}")
    if size % 12:
        return None
    narrow = raw.view("<f4").reshape(-1, 3)
    if _scan_problem(narrow) is not None:
        return None
    evidence = f"read as {len(narrow)} x 3 float32 its points have a median range of {_median_range(narrow):.3g} m"
    if points is not None:
        step4, step3 = _median_step(points), _median_step(narrow)
        if step3 < SCAN_ORDER_RATIO * step4:
            evidence = (f"read as N x 4 float32 consecutive points lie {step4:.3g} m apart (median), read as N x 3 "
                        f"{step3:.3g} m, a scan's order")
        elif step4 < SCAN_ORDER_RATIO * step3:
            return None  # N x 4 keeps the scan order: its fourth column is something else
        else:
            evidence = read4 + evidence
    return (f"N x 3 float32 (x, y, z without reflectance, 12 bytes per point): {evidence}; add a reflectance "
            f"column, e.g. {_ADD_REFLECTANCE}")
