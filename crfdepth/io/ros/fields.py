"""Checked access to the fields of a deserialised ROS message, shared by the message readers.

Messages are read by duck typing on their attribute names (docs/design.md section 11), so a
missing or ill-typed field is an :class:`~crfdepth.errors.InputError` naming the message
(``where``) and the field, as in :mod:`crfdepth.io.ros.images` and :mod:`crfdepth.io.ros.messages`:
a field, a size (``height``, ``step`` ...), the ``data`` bytes, and the rows of an image or
an organised cloud with their padding.
"""

from __future__ import annotations

import numpy as np

from crfdepth.errors import InputError

__all__ = ["message_bytes", "message_field", "message_rows", "message_size"]


def message_field(msg, name: str, where: str, kind: str):
    """``msg.<name>``, or an InputError saying which ``kind`` of message lacks it."""
    if not hasattr(msg, name):
        raise InputError(f"{where}: expected a {kind} message with field '{name}', got "
                         f"{type(msg).__name__} without it")
    return getattr(msg, name)


def message_size(msg, name: str, where: str, kind: str, *, positive: bool = True) -> int:
    """A non-negative (or positive) integer field such as ``height`` or ``step``."""
    value = message_field(msg, name, where, kind)
    low = 1 if positive else 0
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < low:
        raise InputError(f"{where}: expected {name} an integer >= {low}, got {value!r}")
    return int(value)


def message_bytes(data, where: str) -> np.ndarray:
    """``data`` (bytes or a 1-D uint8 array, as rosbags gives it) as a 1-D uint8 array, not copied."""
    if isinstance(data, (bytes, bytearray, memoryview)):
        return np.frombuffer(data, dtype=np.uint8)
    array = np.asarray(data)
    if array.dtype != np.uint8 or array.ndim != 1:
        raise InputError(f"{where}: expected data as bytes or a 1-D uint8 array, got "
                         f"{type(data).__name__} of shape {array.shape} {array.dtype}")
    return array


def message_rows(msg, where: str, kind: str, sizes: tuple[int, int, int, int], names: tuple[str, str],
                 what: str) -> np.ndarray:
    """The ``height * step`` bytes of ``msg.data`` holding ``height`` rows of ``width`` items of ``item`` bytes,
    each row ``step`` bytes long (padding allowed); ``sizes`` = (height, width, item, step), ``names`` the
    message's words for item and step. Refuses a step shorter than a row and data shorter than the rows."""
    height, width, item, step = sizes
    if step < width * item:
        raise InputError(f"{where}: expected {names[1]} >= width * {names[0]} = {width} * {item} = {width * item} "
                         f"bytes for a {width}x{height} {what}, got {names[1]} {step}")
    data = message_bytes(message_field(msg, "data", where, kind), where)
    if data.size < height * step:
        raise InputError(f"{where}: expected at least height * {names[1]} = {height} * {step} = {height * step} "
                         f"bytes of {what} data, got {data.size}: truncated {what.split()[-1]}")
    return data[:height * step]
