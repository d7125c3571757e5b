"""An image file's size from its header, without decoding it (PNG and JPEG).

``crfdepth complete`` refuses an image too large for the memory before decoding it
(:func:`crfdepth.memory.check_image_file`): decoding a 20000 x 15000 PNG alone takes 900 MB.
"""

from __future__ import annotations

import struct
from os import PathLike

__all__ = ["read_image_size"]

_PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
# JPEG start-of-frame markers (baseline, progressive, lossless ...; not DHT C4, JPG C8, DAC CC).
_SOF_MARKERS = frozenset(range(0xC0, 0xD0)) - {0xC4, 0xC8, 0xCC}
_JPEG_SCAN_LIMIT = 1 << 20  # bytes of JPEG segments read before giving up (EXIF thumbnails come first)


def read_image_size(path: str | PathLike) -> tuple[int, int] | None:
    """``(height, width)`` of a PNG or JPEG file from its header; None for another format, a
    file that cannot be read or a header that does not parse (the decoder then says why)."""
    try:
        with open(path, "rb") as f:
            head = f.read(24)
            if head[:8] == _PNG_SIGNATURE and head[12:16] == b"IHDR":
                width, height = struct.unpack(">II", head[16:24])
                return (height, width) if width and height else None
            if head[:2] == b"\xff\xd8":
                f.seek(2)
                return _jpeg_size(f)
    except (OSError, struct.error):
        return None
    return None


def _jpeg_size(f) -> tuple[int, int] | None:
    """Walk the JPEG segments up to the first start-of-frame marker."""
    while f.tell() < _JPEG_SCAN_LIMIT:
        byte = f.read(1)
        while byte == b"\xff":  # fill bytes before a marker
            marker = f.read(1)
            if marker != b"\xff":
                break
            byte = marker
        else:
            return None  # not at a marker: a corrupt stream
        if not marker:
            return None
        code = marker[0]
        if code in (0x01, *range(0xD0, 0xD8)):  # markers without a length
            continue
        length = struct.unpack(">H", f.read(2))[0]
        if code in _SOF_MARKERS:
            _, height, width = struct.unpack(">BHH", f.read(5))
            return (height, width) if width and height else None
        if code == 0xDA or length < 2:  # start of scan before any frame header
            return None
        f.seek(length - 2, 1)
    return None
