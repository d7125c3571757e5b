"""ROS message contents as numpy arrays: camera calibration, point clouds, time stamps, and a
depth map as an image to write (docs/design.md section 11).

The functions read ``sensor_msgs`` messages of ROS 1 or ROS 2 as deserialised by
``rosbags`` (``rosbags.highlevel.AnyReader``) by duck typing on their attributes, so it
works with any object carrying the same field names (``types.SimpleNamespace`` in tests).
Camera images are decoded by :mod:`crfdepth.io.ros.images`; the checked access to a
message's fields both use is :mod:`crfdepth.io.ros.fields`.

- :func:`camera_from_info`: ``sensor_msgs/CameraInfo`` -> :class:`CameraModel` (K,
  OpenCV distortion, image size). ROS 2 spells the matrices ``k d r p``, ROS 1 ``K D R P``.
- :func:`points_from_cloud`: ``sensor_msgs/PointCloud2`` -> (N, 3) float32 x y z (metres,
  message frame), viewed through a structured dtype without a loop over points.
- :func:`depth_image_fields`: the fields of a ``32FC1`` ``sensor_msgs/Image`` holding a
  depth map (metres, 0 = missing), for writing.
- :func:`stamp_ns`: a header's stamp in integer nanoseconds.

Bad message content raises :class:`~crfdepth.errors.InputError`, one line ``<where>: expected
..., got ...``; ``where`` describes the message (``--image-topic /cam/image_raw (image at ...)``).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from crfdepth.errors import InputError
from crfdepth.intrinsics import check_intrinsics
from crfdepth.io.calibration import DISTORTION_LENGTHS
from crfdepth.io.ros.fields import message_field, message_rows, message_size

__all__ = [
    "CameraModel",
    "camera_from_info",
    "depth_image_fields",
    "points_from_cloud",
    "stamp_ns",
]

_DISTORTION_MODELS = ("plumb_bob", "rational_polynomial")
# sensor_msgs/PointField datatype -> (name, numpy type code without byte order)
_POINT_TYPES = {1: ("INT8", "i1"), 2: ("UINT8", "u1"), 3: ("INT16", "i2"), 4: ("UINT16", "u2"),
                5: ("INT32", "i4"), 6: ("UINT32", "u4"), 7: ("FLOAT32", "f4"), 8: ("FLOAT64", "f8")}
_NS_PER_S = 1_000_000_000


# --------------------------------------------------------------------------- time stamps


def stamp_ns(header) -> int:
    """A header's stamp in nanoseconds, as an exact Python int (no float rounding).

    ``header.stamp.sec * 1_000_000_000 + header.stamp.nanosec`` (rosbags names both the
    ROS 1 and ROS 2 fields ``sec`` / ``nanosec``; genpy's ``secs`` / ``nsecs`` work too).
    """
    stamp = getattr(header, "stamp", None)
    sec = getattr(stamp, "sec", getattr(stamp, "secs", None))
    nanosec = getattr(stamp, "nanosec", getattr(stamp, "nsecs", None))
    integers = (int, np.integer)
    if not isinstance(sec, integers) or not isinstance(nanosec, integers) or isinstance(sec, bool):
        raise InputError(f"header: expected a std_msgs/Header with integer stamp.sec and stamp.nanosec, got "
                         f"{type(header).__name__} with stamp {type(stamp).__name__}")
    if not 0 <= int(nanosec) < _NS_PER_S:
        raise InputError(f"header.stamp.nanosec: expected 0 <= nanosec < 1e9, got {int(nanosec)}")
    return int(sec) * _NS_PER_S + int(nanosec)


# --------------------------------------------------------------------------- camera calibration


@dataclass(frozen=True, eq=False)
class CameraModel:
    """A pinhole camera from a ``sensor_msgs/CameraInfo``.

    Attributes:
        K: (3, 3) float64 intrinsics in pixels (read-only).
        distortion: OpenCV coefficients ``k1 k2 p1 p2 [k3 [k4 k5 k6]]`` (float64, read-only),
            or None when the image has no distortion (all zero, absent, or rectified).
        image_size: (height, width) in pixels of the images ``K`` belongs to.
    """

    K: np.ndarray
    distortion: np.ndarray | None
    image_size: tuple[int, int]


def _matrix(msg, name: str, where: str, size: int | None) -> np.ndarray:
    """Field ``name`` (ROS 2 lower case) or ``name.upper()`` (ROS 1) as a finite 1-D float64 array."""
    for attribute in (name, name.upper()):
        if hasattr(msg, attribute):
            break
    else:
        raise InputError(f"{where}: expected a sensor_msgs/CameraInfo with field '{name}' (ROS 2) or "
                         f"'{name.upper()}' (ROS 1), got {type(msg).__name__} with neither")
    try:
        values = np.array(getattr(msg, attribute), dtype=np.float64).reshape(-1)
    except (TypeError, ValueError) as error:
        raise InputError(f"{where}: expected {attribute} as numbers, got {type(getattr(msg, attribute)).__name__} "
                         f"({error})") from None
    if size is not None and values.size != size:
        raise InputError(f"{where}: expected {attribute} with {size} numbers, got {values.size}")
    if not np.all(np.isfinite(values)):
        raise InputError(f"{where}: expected finite numbers in {attribute}, got {values.tolist()}")
    return values


def _check_binning_and_roi(msg, where: str, height: int, width: int) -> None:
    """Refuse binning > 1 and a region of interest other than empty or the full image."""
    kind = "sensor_msgs/CameraInfo"
    binning = [message_size(msg, key, where, kind, positive=False) if hasattr(msg, key) else 0
               for key in ("binning_x", "binning_y")]
    if max(binning) > 1:
        raise InputError(f"{where}: expected binning_x and binning_y 0 or 1, got {binning[0]} and "
                         f"{binning[1]}: binned camera info is not supported (calibrate at the image's "
                         f"resolution, or pass --calib FILE)")
    roi = getattr(msg, "roi", None)
    if roi is None:
        return
    box = tuple(message_size(roi, key, where, f"{kind}.roi", positive=False)
                for key in ("x_offset", "y_offset", "height", "width"))
    if box not in ((0, 0, 0, 0), (0, 0, height, width)):
        raise InputError(f"{where}: expected an empty roi or the full {width}x{height} (WxH) image, got roi "
                         f"x_offset={box[0]} y_offset={box[1]} height={box[2]} width={box[3]}: a region of "
                         f"interest is not supported")


def _distortion(msg, where: str, coefficients: np.ndarray) -> np.ndarray | None:
    """OpenCV distortion coefficients for ``msg.distortion_model``, None when there is none."""
    model = str(getattr(msg, "distortion_model", "")).strip()
    zero = not np.any(coefficients)
    if model.lower() in ("", "none"):
        if zero:
            return None
        raise InputError(f"{where}: expected distortion_model plumb_bob or rational_polynomial for non-zero "
                         f"distortion coefficients, got distortion_model {model!r} with D = {coefficients.tolist()}")
    if model.lower() not in _DISTORTION_MODELS:
        raise InputError(f"{where}: expected distortion_model plumb_bob or rational_polynomial (the only ones "
                         f"supported), got {model!r}: subscribe to the rectified image topic (image_rect / "
                         f"image_rect_color) instead, which needs rectified=True")
    if zero:
        return None
    if coefficients.size not in DISTORTION_LENGTHS:
        raise InputError(f"{where}: expected {model} distortion with 5 (plumb_bob) or 8 (rational_polynomial) "
                         f"coefficients, got {coefficients.size}: {coefficients.tolist()}")
    return coefficients


def camera_from_info(msg, where: str, *, rectified: bool = False) -> CameraModel:
    """The :class:`CameraModel` of a ``sensor_msgs/CameraInfo`` (ROS 1 or ROS 2 field names).

    Args:
        msg: the CameraInfo; matrices ``k d r p`` (ROS 2) or ``K D R P`` (ROS 1).
        where: the caller's description of the message, first in every error.
        rectified: True when the images are already rectified (``image_rect*`` topics):
            then ``K = P[:3, :3]`` and no distortion. Otherwise ``K`` with the
            ``plumb_bob`` / ``rational_polynomial`` coefficients in OpenCV order.

    Raises:
        InputError: zero width/height, non-finite numbers, an uncalibrated camera (K or P
            all zero), an implausible K, binning > 1, a partial roi, or an unsupported
            distortion model (equidistant, fisheye, ...) when ``rectified`` is False.
    """
    kind = "sensor_msgs/CameraInfo"
    height, width = message_size(msg, "height", where, kind), message_size(msg, "width", where, kind)
    _check_binning_and_roi(msg, where, height, width)
    k, p = _matrix(msg, "k", where, 9), _matrix(msg, "p", where, 12)
    coefficients = _matrix(msg, "d", where, None)
    name, matrix = ("P[:3, :3]", p.reshape(3, 4)[:, :3]) if rectified else ("K", k.reshape(3, 3))
    if not np.any(matrix):
        raise InputError(f"{where}: expected a calibrated camera, got {name} all zero: the camera is not "
                         f"calibrated; calibrate it or pass --calib FILE")
    K = check_intrinsics(matrix, what=f"{where}: {name}", image_size=(height, width))
    distortion = None if rectified else _distortion(msg, where, coefficients)
    K.setflags(write=False)
    if distortion is not None:
        distortion = distortion.copy()
        distortion.setflags(write=False)
    return CameraModel(K=K, distortion=distortion, image_size=(height, width))


# --------------------------------------------------------------------------- point clouds


def _describe_fields(fields) -> str:
    """``x FLOAT32@0, y FLOAT32@4, ...`` for error messages."""
    parts = []
    for field in fields:
        datatype = getattr(field, "datatype", "?")
        type_name = _POINT_TYPES.get(datatype, (f"type {datatype}",))[0]
        count = getattr(field, "count", 1)
        parts.append(f"{getattr(field, 'name', '?')} {type_name}{'' if count == 1 else f'x{count}'}"
                     f"@{getattr(field, 'offset', '?')}")
    return ", ".join(parts) if parts else "none"


def _xyz_dtype(msg, where: str, point_step: int) -> np.dtype:
    """A structured dtype with fields x, y, z at their offsets and itemsize ``point_step``."""
    fields = list(message_field(msg, "fields", where, "sensor_msgs/PointCloud2"))
    by_name = {}
    for field in fields:
        by_name.setdefault(str(getattr(field, "name", "")), field)
    found = _describe_fields(fields)
    order = ">" if bool(getattr(msg, "is_bigendian", False)) else "<"
    formats, offsets = [], []
    for axis in "xyz":
        if axis not in by_name:
            raise InputError(f"{where}: expected fields x, y and z, got no '{axis}' field (fields: {found})")
        try:
            datatype, offset, count = (int(getattr(by_name[axis], key)) for key in ("datatype", "offset", "count"))
        except (AttributeError, TypeError, ValueError):
            raise InputError(f"{where}: expected field {axis} as a sensor_msgs/PointField with integer datatype, "
                             f"offset and count, got {by_name[axis]!r}") from None
        if datatype not in (7, 8):
            type_name = _POINT_TYPES.get(datatype, (f"unknown type {datatype}",))[0]
            raise InputError(f"{where}: expected field {axis} of type FLOAT32 or FLOAT64 (the only ones supported), "
                             f"got {type_name} (fields: {found})")
        if count != 1:
            raise InputError(f"{where}: expected field {axis} with count 1, got count {count} (fields: {found})")
        code = _POINT_TYPES[datatype][1]
        if offset < 0 or offset + int(code[1]) > point_step:
            raise InputError(f"{where}: expected field {axis} within point_step {point_step} bytes, got offset "
                             f"{offset} + {code[1]} bytes, beyond it (fields: {found})")
        formats.append(order + code)
        offsets.append(offset)
    spans = sorted((o, o + int(f[-1])) for o, f in zip(offsets, formats))
    if any(spans[i][1] > spans[i + 1][0] for i in range(2)):
        raise InputError(f"{where}: expected fields x, y and z not to overlap, got offsets {offsets} (fields: {found})")
    return np.dtype({"names": ["x", "y", "z"], "formats": formats, "offsets": offsets, "itemsize": point_step})


def points_from_cloud(msg, where: str) -> np.ndarray:
    """The (height * width, 3) float32 x, y, z (metres, message frame) of a ``sensor_msgs/PointCloud2``.

    Points are in message order (row by row for organised clouds); NaN / infinite rows are
    kept for the caller to count and drop. ``x``, ``y``, ``z`` must be FLOAT32 or FLOAT64
    with count 1; other fields are ignored. ``is_bigendian``, ``point_step`` and padded
    rows (``row_step > width * point_step``) are honoured. An empty cloud (width or height
    0) gives a (0, 3) array.

    Raises:
        InputError: missing or non-float x/y/z, a field beyond ``point_step``, ``row_step``
            too small, or data shorter than ``height * row_step`` (truncated); the message
            lists the fields found with their types and offsets.
    """
    kind = "sensor_msgs/PointCloud2"
    height = message_size(msg, "height", where, kind, positive=False)
    width = message_size(msg, "width", where, kind, positive=False)
    if height == 0 or width == 0:
        return np.zeros((0, 3), dtype=np.float32)
    point_step = message_size(msg, "point_step", where, kind)
    row_step = message_size(msg, "row_step", where, kind, positive=False)
    dtype = _xyz_dtype(msg, where, point_step)
    data = message_rows(msg, where, kind, (height, width, point_step, row_step), ("point_step", "row_step"), "cloud")
    records = np.ndarray(shape=(height, width), dtype=dtype, buffer=np.ascontiguousarray(data),
                         strides=(row_step, point_step))
    points = np.empty((height * width, 3), dtype=np.float32)
    with np.errstate(over="ignore"):  # float64 beyond float32's range becomes inf, kept like NaN
        for column, axis in enumerate("xyz"):
            points[:, column] = records[axis].reshape(-1)
    return points


# --------------------------------------------------------------------------- writing


def depth_image_fields(depth: np.ndarray) -> dict:
    """The fields of a ``32FC1`` ``sensor_msgs/Image`` holding a depth map.

    Args:
        depth: (H, W) real array, metres, 0 = missing; written as little-endian float32.

    Returns:
        ``{"height": H, "width": W, "encoding": "32FC1", "is_bigendian": 0, "step": 4 * W,
        "data": (4 * H * W,) uint8 array}``, the data a copy (not a view of ``depth``);
        add a ``header`` to build the message.
    """
    array = np.asarray(depth)
    if array.ndim != 2 or 0 in array.shape or array.dtype.kind not in "biuf":
        raise InputError(f"depth: expected a non-empty (H, W) real array (metres, 0 = missing), got "
                         f"shape {array.shape} {array.dtype}")
    height, width = array.shape
    data = np.array(array, dtype="<f4", order="C", copy=True).view(np.uint8).reshape(-1)
    return {"height": int(height), "width": int(width), "encoding": "32FC1", "is_bigendian": 0,
            "step": 4 * int(width), "data": data}
