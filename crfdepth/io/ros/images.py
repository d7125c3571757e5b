"""Camera images of ROS messages as numpy arrays (docs/design.md section 11).

:func:`decode_image`: ``sensor_msgs/Image`` (``rgb8``, ``bgr8``, ``mono8``, ``rgba8``,
``bgra8``; Bayer ``bayer_*8`` and YUV 4:2:2) or ``sensor_msgs/CompressedImage`` (JPEG /
PNG) -> (H, W, 3) uint8 RGB. Messages of ROS 1 or ROS 2 as deserialised by ``rosbags`` are
read by duck typing (any object with the same field names works); only Bayer and YUV images
need the optional extra (``rosbags-image``'s conversion). A depth image given as the camera
image is refused by name. Bad content raises :class:`~crfdepth.errors.InputError`, one line
``<where>: expected ..., got ...``.
"""

from __future__ import annotations

from types import SimpleNamespace

import cv2
import numpy as np

from crfdepth.errors import InputError
from crfdepth.io.ros.fields import message_bytes, message_field, message_rows, message_size

__all__ = ["IMAGE_ENCODINGS", "decode_image"]

_CHANNELS = {"rgb8": 3, "bgr8": 3, "mono8": 1, "rgba8": 4, "bgra8": 4}
# Colour-filter and YUV encodings, converted by rosbags-image (the ros extra) with OpenCV:
# encoding -> bytes per pixel.
_CONVERTED = {"bayer_rggb8": 1, "bayer_bggr8": 1, "bayer_gbrg8": 1, "bayer_grbg8": 1, "uyvy": 2, "yuv422": 2,
              "yuyv": 2, "yuv422_yuy2": 2}
IMAGE_ENCODINGS = (*_CHANNELS, *_CONVERTED)
_DEPTH_ENCODINGS = ("16uc1", "32fc1")
_PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"


def decode_image(msg, where: str) -> np.ndarray:
    """The (H, W, 3) uint8 RGB camera image of a ``sensor_msgs/Image`` or ``CompressedImage``.

    A ``CompressedImage`` (it has ``format``) is decoded by OpenCV from JPEG or PNG; an
    ``Image`` (it has ``encoding``) must be one of :data:`IMAGE_ENCODINGS`: ``mono8`` is
    replicated to three channels, alpha dropped, BGR reordered to RGB, Bayer patterns and
    YUV 4:2:2 converted by rosbags-image; padded rows (``step > width * channels``) are
    honoured. The result is a new C-contiguous array.

    Raises:
        InputError: unsupported encoding (depth images named as such), truncated data,
            inconsistent sizes, bytes that are not JPEG/PNG, 16-bit PNG.
    """
    if hasattr(msg, "format"):
        return _decode_compressed(msg, where)
    if hasattr(msg, "encoding"):
        return _decode_raw(msg, where)
    raise InputError(f"{where}: expected a sensor_msgs/Image (with 'encoding') or sensor_msgs/CompressedImage "
                     f"(with 'format'), got {type(msg).__name__} with neither")


def _check_encoding(encoding: str, where: str) -> str:
    """The lower-case ``encoding`` when supported, else an InputError listing the supported ones."""
    name = str(encoding).strip().lower()
    if name in _CHANNELS or name in _CONVERTED:
        return name
    supported = ", ".join(IMAGE_ENCODINGS)
    if name in _DEPTH_ENCODINGS:
        raise InputError(f"{where}: expected an 8-bit camera image with encoding {supported}, got encoding "
                         f"{encoding!r}, which looks like a depth image, not a camera image (check --image-topic)")
    raise InputError(f"{where}: expected an 8-bit image with encoding {supported}, got unsupported encoding "
                     f"{encoding!r} (use an 8-bit colour or mono topic, e.g. image_color or image_rect_color)")


def _decode_raw(msg, where: str) -> np.ndarray:
    """(H, W, 3) uint8 RGB of a ``sensor_msgs/Image``."""
    kind = "sensor_msgs/Image"
    encoding = _check_encoding(message_field(msg, "encoding", where, kind), where)
    height, width = message_size(msg, "height", where, kind), message_size(msg, "width", where, kind)
    step = message_size(msg, "step", where, kind)
    channels = _CHANNELS.get(encoding) or _CONVERTED[encoding]
    data = message_rows(msg, where, kind, (height, width, channels, step), ("channels", "step"), f"{encoding} image")
    rows = data.reshape(height, step)[:, :width * channels]
    pixels = rows.reshape(height, width, channels)
    if encoding in _CONVERTED:
        return _convert(np.ascontiguousarray(pixels[:, :, 0] if channels == 1 else pixels), encoding, where)
    if encoding == "mono8":
        pixels = np.repeat(pixels, 3, axis=2)
    elif encoding.startswith("bgr"):
        pixels = pixels[:, :, 2::-1]
    else:
        pixels = pixels[:, :, :3]
    return np.array(pixels, dtype=np.uint8, order="C", copy=True)


def _convert(pixels: np.ndarray, encoding: str, where: str) -> np.ndarray:
    """RGB of a Bayer or YUV image (``pixels``: (H, W) or (H, W, 2), rows without padding) by rosbags-image's
    conversion: OpenCV's, with the ROS names of the patterns (ROS's ``bayer_rggb8`` is OpenCV's ``BayerBG``)."""
    try:
        from rosbags.image import ImageError, image_to_cvimage
    except ImportError:
        raise InputError(f"{where}: {encoding} images are converted by the rosbags-image package, which is not "
                         f"installed; install it with: pip install 'crfdepth[ros]'") from None
    height, width = pixels.shape[:2]
    unpadded = SimpleNamespace(encoding=encoding, height=height, width=width, is_bigendian=0, data=pixels.ravel())
    try:
        rgb = image_to_cvimage(unpadded, "rgb8")
    except (ImageError, cv2.error) as exc:
        raise InputError(f"{where}: could not convert the {encoding} image of {pixels.shape[1]}x{pixels.shape[0]} "
                         f"pixels to RGB ({str(exc).strip().splitlines()[-1]})") from None
    return np.array(rgb, dtype=np.uint8, order="C", copy=True)


def _png_bit_depth(data: np.ndarray) -> int | None:
    """The bit depth of a PNG from its IHDR chunk (byte 24), None when ``data`` is no PNG."""
    if data.size < 25 or data[:8].tobytes() != _PNG_SIGNATURE:
        return None
    return int(data[24])


def _decode_compressed(msg, where: str) -> np.ndarray:
    """(H, W, 3) uint8 RGB of a ``sensor_msgs/CompressedImage`` (JPEG or PNG)."""
    kind = "sensor_msgs/CompressedImage"
    fmt = str(message_field(msg, "format", where, kind))
    if "compresseddepth" in fmt.lower():
        raise InputError(f"{where}: expected a compressed camera image (JPEG/PNG), got format {fmt!r}, "
                         f"a compressed depth image, not a camera image (check --image-topic)")
    data = message_bytes(message_field(msg, "data", where, kind), where)
    if data.size == 0:
        raise InputError(f"{where}: expected JPEG/PNG bytes in a compressed image (format {fmt!r}), got 0 bytes")
    depth = _png_bit_depth(data)
    if depth is not None and depth > 8:
        raise InputError(f"{where}: expected an 8-bit camera image, got a {depth}-bit PNG (format {fmt!r}), "
                         f"not an 8-bit camera image (a depth or raw 16-bit image? check --image-topic)")
    try:
        bgr = cv2.imdecode(np.ascontiguousarray(data), cv2.IMREAD_COLOR)
    except cv2.error as error:
        bgr, reason = None, str(error).strip().splitlines()[-1]
    else:
        reason = "OpenCV returned no image"
    if bgr is None or bgr.ndim != 3 or bgr.shape[2] != 3 or bgr.dtype != np.uint8:
        raise InputError(f"{where}: expected JPEG/PNG bytes (format {fmt!r}), got {data.size} bytes that "
                         f"could not be decoded as JPEG/PNG ({reason})")
    return np.ascontiguousarray(cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB))
