"""Input and output paths: the checks every reader and writer makes, and the atomic write.

Paths are checked before any work (docs/design.md section 8): an input must be an
existing file, an output a file name in an existing folder where a file can be created,
so a bad path fails at once, naming the user's argument, never after a long computation.

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

__all__ = ["atomic_write", "atomic_write_bytes", "check_input_file", "check_output_file", "read_text"]


def check_input_file(path: str | os.PathLike, name: str = "path") -> Path:
    """``path`` as a Path, checked as an existing file to read.

    Raises:
        FileNotFoundError: ``path`` does not exist (the message names the argument ``name``).
        IsADirectoryError: ``path`` is a folder.
    """
    file = Path(path)
    if not file.exists():
        raise FileNotFoundError(f"{name}: no such file: {file}")
    if file.is_dir():
        raise IsADirectoryError(f"{name}: expected a file, got a folder: {file}")
    return file


def check_output_file(path: str | os.PathLike, name: str = "path") -> Path:
    """``path`` as a Path, checked as a file to create or replace.

    Besides the folder's existence, a file is actually created there and removed again
    (permission bits do not bind root, and file systems such as ``/proc`` refuse new files
    whatever ``os.access`` says), so an unwritable folder fails here, before any work,
    rather than at the final write.

    Raises:
        InputError: ``path`` is a folder (the message names the argument ``name``).
        FileNotFoundError: its folder does not exist.
        PermissionError: no file can be created in its folder.
    """
    file = Path(path)
    if file.is_dir():
        raise InputError(f"{name}: expected a file name, got a folder: {file}")
    if not file.parent.is_dir():
        raise FileNotFoundError(f"{name}: the folder of {file} does not exist")
    probe = file.parent / f".{file.name}.{secrets.token_hex(6)}.probe"
    try:
        os.close(os.open(probe, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600))
    except OSError as exc:
        raise PermissionError(f"{name}: cannot create {file}: the folder {file.parent} does not accept new "
                              f"files ({exc.strerror})") from None
    probe.unlink(missing_ok=True)
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


def read_text(path: Path, what: str, holding: str) -> str:
    """A text file's contents (undecodable bytes replaced), or InputError naming ``what`` when the
    file is binary: an image or .npy signature, or NUL bytes (``<what>: expected a text file with
    <holding>, got a binary file (a PNG image) <path>``)."""
    data = path.read_bytes()
    kind = next((name for magic, name in _MAGIC if data.startswith(magic)), None)
    if kind is not None or b"\x00" in data:
        raise InputError(f"{what}: expected a text file with {holding}, got a binary file"
                         f" ({kind or 'NUL bytes'}) {path}")
    return data.decode("utf-8", errors="replace")


_MAGIC = ((b"\x89PNG", "a PNG image"), (b"\xff\xd8\xff", "a JPEG image"),
          (b"\x93NUMPY", "a .npy array"))
