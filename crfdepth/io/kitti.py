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

import os
from pathlib import Path

import cv2
import numpy as np

from crfdepth.checks import check_choice
from crfdepth.errors import InputError
from crfdepth.io.files import atomic_write_bytes, check_input_file, read_text

__all__ = ["read_depth_png", "read_intrinsics", "read_rgb", "read_velodyne", "write_depth_png"]

PathLike = str | os.PathLike

# KITTI depth PNGs store depth * 256 as uint16.
_DEPTH_SCALE = 256.0
# Codes per metre of the units a depth PNG may be read in (read_depth_png).
_UNIT_SCALES = {"kitti": _DEPTH_SCALE, "mm": 1000.0, "m": 1.0}
_UINT16_MAX = np.iinfo(np.uint16).max


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
            above 65535/256 m (about 256 m) are clipped to the largest code.

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

    codes = np.clip(np.round(array.astype(np.float64) * _DEPTH_SCALE), 0, _UINT16_MAX).astype(np.uint16)
    ok, encoded = cv2.imencode(".png", codes)
    if not ok:  # pragma: no cover - cv2 encodes any 2-D uint16 array
        raise InputError(f"depth: could not encode an array of shape {codes.shape} as PNG")

    atomic_write_bytes(path, encoded.tobytes())


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
    tokens = read_text(path, "intrinsics", "9 numbers (row-major 3x3 K)").split()
    try:
        values = np.array([float(token) for token in tokens], dtype=np.float64)
    except ValueError as exc:
        raise InputError(f"intrinsics: expected 9 numbers in {path}, got non-numeric text ({exc})") from None
    if values.size != 9:
        raise InputError(f"intrinsics: expected 9 numbers (row-major 3x3 K) in {path}, got {values.size}")
    return values.reshape(3, 3)


# --------------------------------------------------------------------------- Velodyne


def read_velodyne(path: PathLike) -> np.ndarray:
    """Read a KITTI Velodyne scan.

    Args:
        path: ``.bin`` file of little-endian float32 records (x, y, z, reflectance).

    Returns:
        (N, 4) float32: x, y, z in metres in the Velodyne frame (x forward, y left,
        z up) and reflectance in [0, 1], in the sensor's scan order (which
        :func:`crfdepth.geometry.projection.recover_rings` relies on).

    Raises:
        FileNotFoundError: ``path`` does not exist.
        InputError: the file size is not a multiple of 16 bytes (4 float32 per point).
    """
    path = check_input_file(path, "velodyne")
    size = path.stat().st_size
    if size % 16:
        raise InputError(f"velodyne: expected a file size that is a multiple of 16 bytes "
                         f"(4 float32 per point), got {size} bytes in {path}")
    return np.fromfile(path, dtype="<f4").astype(np.float32, copy=False).reshape(-1, 4)
