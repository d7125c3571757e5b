"""Writing output files safely: the output-path checks and the atomic write every writer uses.

A file is written to a new temporary file beside its destination and renamed over it
(``os.replace``, atomic on one file system): a reader never sees a partial file, and a
failed write leaves no file behind and the old one, if any, untouched.
"""

from __future__ import annotations

import os
import secrets
from pathlib import Path
from typing import Callable

from crfdepth.errors import InputError

__all__ = ["atomic_write", "atomic_write_bytes", "check_output_file"]


def check_output_file(path: str | os.PathLike, name: str = "path") -> Path:
    """``path`` as a Path, checked as a file to create or replace.

    Raises:
        InputError: ``path`` is a folder (the message names the argument ``name``).
        FileNotFoundError: its folder does not exist.
    """
    file = Path(path)
    if file.is_dir():
        raise InputError(f"{name}: expected a file name, got a folder: {file}")
    if not file.parent.is_dir():
        raise FileNotFoundError(f"{name}: the folder of {file} does not exist")
    return file


def atomic_write(path: Path, write: Callable[[Path], None]) -> None:
    """Call ``write(temporary)`` on a fresh temporary file beside ``path``, then rename it to ``path``.

    On any failure (``write`` raising, an interrupt) the temporary file is removed and the
    exception propagates.
    """
    temporary = path.parent / f".{path.name}.{secrets.token_hex(6)}.tmp"
    try:
        write(temporary)
        os.replace(temporary, path)
    except BaseException:
        temporary.unlink(missing_ok=True)
        raise


def atomic_write_bytes(path: Path, data: bytes) -> None:
    """Write ``data`` to ``path`` atomically. The temporary file is created exclusively
    (``O_EXCL``: never someone else's file) with mode 0o666 reduced by the umask."""

    def write(temporary: Path) -> None:
        fd = os.open(temporary, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o666)
        with os.fdopen(fd, "wb") as handle:
            handle.write(data)

    atomic_write(path, write)
