"""Depth images of RGB-D cameras and datasets: 16-bit PNGs of millimetres, whole metres or KITTI codes.

An RGB-D camera (Kinect, RealSense) or a dataset (NYU Depth v2, docs/design.md section 17) gives depth
registered to the colour image as a single-channel 16-bit PNG of integer codes: millimetres (most
RGB-D cameras, NYU), whole metres, or KITTI's metres * 256. :func:`read_depth_image` reads one into
metres and refuses, naming the user's argument, what would give a confident wrong depth:

- a file that cannot be read or decoded;
- an 8-bit or colour PNG, and a 16-bit PNG that holds an 8-bit visualisation (every code at most
  255, or every code a multiple of 257: 8 bits scaled to 16), which are pictures, not depth codes;
- a depth image without any valid (non-zero) pixel;
- a depth image in another unit: the median valid depth outside [0.2 m, 80 m], the depths a camera
  sees indoors or outdoors; the refusal names the unit of :data:`DEPTH_UNITS` that would fit.

:func:`check_depth_units` is that check on an array, for datasets that read depth some other way,
and :func:`check_depth_matches_image` refuses a depth image and an RGB image of different sizes.
Messages follow :mod:`crfdepth.checks`: ``<argument>: expected <what>, got <what was received>``.
"""

from __future__ import annotations

import os

import cv2
import numpy as np
import torch

from crfdepth.checks import check_choice, to_numpy
from crfdepth.errors import InputError

__all__ = ["CODES_PER_METRE", "DEPTH_UNITS", "MAX_MEDIAN_M", "MIN_MEDIAN_M", "check_depth_matches_image",
           "check_depth_units", "read_depth_image"]

#: The units a depth image's integer codes may be in (``--depth-units``).
DEPTH_UNITS = ("mm", "m", "kitti")
#: Codes per metre of each unit of :data:`DEPTH_UNITS`.
CODES_PER_METRE = {"mm": 1000.0, "m": 1.0, "kitti": 256.0}
_UNIT_NAMES = {"mm": "millimetres", "m": "whole metres", "kitti": "KITTI codes (metres * 256)"}

# The median valid depth of a camera's depth image, metres: a Kinect sees nothing nearer than 0.4 m (NYU v2
# medians: 2.5-3.4 m) and a street scene has a median of 6-16 m (KITTI); no camera frame has a median beyond
# 80 m. Millimetres read as metres give medians of thousands of metres, metres read as millimetres a few mm.
MIN_MEDIAN_M, MAX_MEDIAN_M = 0.2, 80.0
# The 257 rule needs this many distinct non-zero codes: a visualisation spreads over many of the 256 levels,
# while a constant test depth of 2.57 m (2570 mm = 10 * 257) is not a picture.
_MIN_VISUALISATION_LEVELS = 8
_LARGEST_8_BIT_CODE = 255


def _unit_hint(unit: str, units_argument: str | None) -> str:
    return f"{_UNIT_NAMES[unit]}: pass {units_argument} {unit}" if units_argument else _UNIT_NAMES[unit]


def _hint_m(units_argument: str | None) -> str:
    return f"whole metres, pass {units_argument} m" if units_argument else "whole metres, read them as such"


def _in(source: object) -> str:
    return "" if source is None else f" in {os.fspath(source)}"


def check_depth_units(depth: object, units: str, argument: str, *, units_argument: str | None = "--depth-units",
                      source: str | os.PathLike | None = None) -> None:
    """Refuse a depth image that holds no depth or whose values are not depth in ``units``.

    Args:
        depth: (H, W) array or tensor: integer codes in ``units`` (as a depth PNG holds them), or floats in
            metres (already divided by the codes per metre of ``units``). 0, negative and non-finite values
            are no depth.
        units: one of :data:`DEPTH_UNITS`: ``"mm"`` (millimetres), ``"m"`` (whole metres), ``"kitti"``
            (metres * 256).
        argument: the user's name of the depth image (``--depth``, a dataset's file name).
        units_argument: the option that sets ``units`` (``--depth-units``), named in the fix; None where
            there is none (a dataset whose layout fixes the unit): the message then names the unit only.
        source: the file the values came from, named in messages; None for an array.

    Refused, in this order (integer codes only for the first two):

    1. every valid code at most 255 while ``units`` is not ``"m"`` (depth of at most 0.255 m in
       millimetres, 1 m in KITTI codes): an 8-bit visualisation saved as 16 bits, or whole metres;
    2. every valid code a multiple of 257, over at least 8 distinct codes: an 8-bit picture scaled to
       16 bits (``x * 257``);
    3. no valid pixel;
    4. a median valid depth outside [:data:`MIN_MEDIAN_M`, :data:`MAX_MEDIAN_M`] (0.2 m, 80 m); the message
       names each other unit of :data:`DEPTH_UNITS` whose reading falls inside, in the order of
       :data:`DEPTH_UNITS`. Millimetres read as KITTI codes (a median 3.9x too deep) still pass: the median
       alone cannot tell them.

    Raises:
        InputError: ``<argument>: expected ..., got ...``.
    """
    check_choice("units", units, DEPTH_UNITS)
    array = to_numpy(depth) if isinstance(depth, torch.Tensor) else np.asarray(depth)
    if array.dtype.kind in "iu":
        codes = array[array > 0]
        if codes.size and units != "m" and int(codes.max()) <= _LARGEST_8_BIT_CODE:
            raise InputError(
                f"{argument}: expected 16-bit depth codes in {_UNIT_NAMES[units]}, got codes all <= 255 (largest "
                f"{int(codes.max())}){_in(source)}: an 8-bit visualisation saved as 16 bits, not depth codes; if "
                f"the codes are {_hint_m(units_argument)}")
        levels = np.unique(codes)
        if levels.size >= _MIN_VISUALISATION_LEVELS and not np.any(levels % 257):
            raise InputError(
                f"{argument}: expected 16-bit depth codes in {_UNIT_NAMES[units]}, got every code a multiple of 257 "
                f"({levels.size} levels){_in(source)}: an 8-bit visualisation scaled to 16 bits, not depth codes")
        metres = codes.astype(np.float64) / CODES_PER_METRE[units]
    elif array.dtype.kind == "f":
        metres = array[np.isfinite(array) & (array > 0)].astype(np.float64)
    else:
        raise InputError(f"{argument}: expected an array of depth codes or metres, got dtype {array.dtype}")
    if metres.size == 0:
        raise InputError(f"{argument}: expected a depth image with at least one valid (non-zero) pixel, got none "
                         f"of its {array.size} pixel(s){_in(source)}")
    median = float(np.median(metres))
    if MIN_MEDIAN_M <= median <= MAX_MEDIAN_M:
        return
    message = (f"{argument}: expected depth in {_UNIT_NAMES[units]} with a median of {MIN_MEDIAN_M:g} to "
               f"{MAX_MEDIAN_M:g} m (a camera's scene, indoors or outdoors), got a median of {median:.4g} m over "
               f"{metres.size} valid pixel(s){_in(source)}")
    fits = [unit for unit in DEPTH_UNITS if unit != units
            and MIN_MEDIAN_M <= median * CODES_PER_METRE[units] / CODES_PER_METRE[unit] <= MAX_MEDIAN_M]
    if fits:
        hints = [_unit_hint(unit, units_argument) for unit in fits]
        message += f"; that looks like {hints[0]}" + "".join(f"; or {hint}" for hint in hints[1:])
    else:
        message += f"; check the unit and scale of the depth (codes per metre: {CODES_PER_METRE})"
    raise InputError(message)


def read_depth_image(path: str | os.PathLike, units: str = "mm", *, argument: str = "--depth",
                     units_argument: str | None = "--depth-units") -> np.ndarray:
    """Read a depth image (single-channel 16-bit PNG of integer codes) into metres, checked.

    Args:
        path: the PNG (any format OpenCV decodes unchanged, with 16-bit single-channel codes).
        units: what its codes are, one of :data:`DEPTH_UNITS`: ``"mm"`` (millimetres: NYU v2, most RGB-D
            cameras), ``"m"`` (whole metres) or ``"kitti"`` (metres * 256).
        argument: the user's name of the file, in every message (``--depth``).
        units_argument: the option that sets ``units``, named in the fix of a wrong unit (None: none).

    Returns:
        (H, W) float32 depth in metres (codes / codes per metre); 0 = no depth.

    Raises:
        InputError: naming ``argument``: the file cannot be read or decoded; it is not a single-channel
            16-bit image (an 8-bit or colour PNG: a visualisation, not depth codes); or
            :func:`check_depth_units` refuses its codes (an 8-bit visualisation in 16 bits, no valid pixel,
            another unit, naming ``units_argument``).
    """
    check_choice(units_argument or "units", units, DEPTH_UNITS)
    file = os.fspath(path)
    try:
        buffer = np.fromfile(file, dtype=np.uint8)
    except OSError as exc:
        why = exc.strerror or type(exc).__name__
        raise InputError(f"{argument}: expected a readable depth image, got {file}: {why}") from None
    image = cv2.imdecode(buffer, cv2.IMREAD_UNCHANGED) if buffer.size else None
    if image is None:
        raise InputError(f"{argument}: expected a depth image (a 16-bit PNG), got {file}, which does not decode as "
                         f"an image ({buffer.size} bytes)")
    channels = 1 if image.ndim == 2 else image.shape[2]
    if image.dtype != np.uint16 or channels != 1:
        bits = f"{8 * image.dtype.itemsize}-bit" if image.dtype.kind in "iu" else str(image.dtype)
        picture = ": a visualisation, not depth codes" if image.dtype == np.uint8 or channels > 1 else ""
        raise InputError(f"{argument}: expected a single-channel 16-bit depth PNG (codes in {_UNIT_NAMES[units]}), "
                         f"got a {bits} image with {channels} channel(s) in {file}{picture}")
    check_depth_units(image, units, argument, units_argument=units_argument, source=file)
    return image.astype(np.float32) / np.float32(CODES_PER_METRE[units])


def check_depth_matches_image(depth_shape: tuple[int, ...], image_shape: tuple[int, ...],
                              depth_argument: str = "--depth", image_argument: str = "--image") -> None:
    """Refuse a depth image and an RGB image of different sizes (the depth must be registered to the image).

    Args:
        depth_shape: (H, W) of the depth image (further entries ignored).
        image_shape: (H, W) or (H, W, C) of the RGB image.
        depth_argument: the user's name of the depth image (an option or a file name).
        image_argument: the user's name of the RGB image.

    Raises:
        InputError: ``<depth_argument>: expected the size of <image_argument>, HxW, got hxw``.
    """
    depth_hw, image_hw = tuple(int(n) for n in depth_shape[:2]), tuple(int(n) for n in image_shape[:2])
    if depth_hw != image_hw:
        raise InputError(f"{depth_argument}: expected the size of {image_argument}, {image_hw[0]}x{image_hw[1]} "
                         f"(HxW), got {depth_hw[0]}x{depth_hw[1]}: the depth must be registered to the image")
