"""Input and output paths: the checks every reader and writer makes, and the atomic write.

Paths are checked before any work (docs/design.md section 8): an input must be an
existing file, an output a file name in an existing folder where a file can be created,
so a bad path fails at once, naming the user's argument, never after a long computation.

A file is written to a new temporary file beside its destination and renamed over it
(``os.replace``, atomic on one file system): a reader never sees a partial file, and a
failed write leaves no file behind and the old one, if any, untouched.

An output folder is locked by the run that writes it (:func:`lock_folder`): a lock file
``.crfdepth.lock`` in the folder, created exclusively (``O_CREAT | O_EXCL``), holding the
run's pid, host, start time and command, and removed when the run ends (also on an error
or Ctrl-C). A second run into the folder is refused naming the first
(:class:`FolderLockedError`); a lock left by a run that is gone (its pid no longer runs on
this host, e.g. after ``kill -9``) is taken over with a warning.

An input file must be a regular file (:func:`check_input_file`, :func:`read_text`): a device
(``/dev/zero``, ``/dev/urandom``), a FIFO or a socket is refused before it is opened for
reading, since reading one whole never ends (or blocks); a text input is read only up to a
bound (``max_bytes``: :data:`MAX_CALIBRATION_BYTES` for calibrations, :data:`MAX_TEXT_BYTES`
otherwise), so a huge file is refused after reading at most that many bytes.
"""

from __future__ import annotations

import contextlib
import datetime
import json
import logging
import os
import secrets
import socket
import stat
import sys
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Callable

from crfdepth.errors import InputError

__all__ = ["LOCK_NAME", "MAX_CALIBRATION_BYTES", "MAX_TEXT_BYTES", "FolderLockedError", "atomic_write",
           "atomic_write_bytes", "check_input_file", "check_not_locked", "check_output_file", "file_kind",
           "lock_folder", "probe_folder", "read_text"]

logger = logging.getLogger(__name__)

LOCK_NAME = ".crfdepth.lock"  # the lock file of an output folder (lock_folder)
# Largest calibration file read (KITTI calib_*.txt, a rig YAML/JSON, a 9-number K file), bytes. The
# largest real one, a KITTI raw day's calib_cam_to_cam.txt, is 3 kB: 1 MiB is 350 times that, and
# small enough to parse in well under a second whatever it holds.
MAX_CALIBRATION_BYTES = 1 << 20
# Largest other text input read whole (a poses file: KITTI odometry's longest is about 0.75 MB), bytes.
MAX_TEXT_BYTES = 64 << 20


def check_input_file(path: str | os.PathLike, name: str = "path") -> Path:
    """``path`` as a Path, checked as an existing file to read.

    Raises:
        FileNotFoundError: ``path`` does not exist (the message names the argument ``name``).
        IsADirectoryError: ``path`` is a folder.
        InputError: ``path`` is not a regular file (a device such as ``/dev/zero``, a FIFO, a
            socket), which no reader can read whole.
    """
    file = Path(path)
    if not file.exists():
        raise FileNotFoundError(f"{name}: no such file: {file}")
    if file.is_dir():
        raise IsADirectoryError(f"{name}: expected a file, got a folder: {file}")
    kind = file_kind(file.stat().st_mode)
    if kind is not None:
        raise InputError(f"{name}: expected a regular file, got {kind} {file}")
    return file


def file_kind(mode: int) -> str | None:
    """None for a regular file's ``st_mode``, else what it is ("a character device (like /dev/zero)" ...)."""
    if stat.S_ISREG(mode):
        return None
    for test, kind in ((stat.S_ISDIR, "a folder"), (stat.S_ISCHR, "a character device (like /dev/zero)"),
                       (stat.S_ISBLK, "a block device"), (stat.S_ISFIFO, "a FIFO (named pipe)"),
                       (stat.S_ISSOCK, "a socket")):
        if test(mode):
            return kind
    return "a special file"


def check_output_file(path: str | os.PathLike, name: str = "path", *, suffix: str | None = None) -> Path:
    """``path`` as a Path, checked as a file to create or replace.

    Besides the folder's existence, a file is actually created there and removed again
    (permission bits do not bind root, and file systems such as ``/proc`` refuse new files
    whatever ``os.access`` says), so an unwritable folder fails here, before any work,
    rather than at the final write.

    Args:
        suffix: when given (``".png"``), the file name must end in it (any case).

    Raises:
        InputError: ``path`` is a folder, or does not end in ``suffix`` (the message names
            the argument ``name``).
        FileNotFoundError: its folder does not exist.
        PermissionError: no file can be created in its folder.
    """
    file = Path(path)
    if suffix is not None and file.suffix.lower() != suffix:
        raise InputError(f"{name}: expected a file name ending in {suffix}, got {file}")
    if file.is_dir():
        raise InputError(f"{name}: expected a file name, got a folder: {file}")
    if not file.parent.is_dir():
        raise FileNotFoundError(f"{name}: the folder of {file} does not exist")
    problem = probe_folder(file.parent)
    if problem is not None:
        raise PermissionError(f"{name}: cannot create {file}: the folder {file.parent} does not accept new "
                              f"files ({problem})")
    return file


def probe_folder(folder: Path) -> str | None:
    """Create a hidden file in ``folder`` and remove it again: None when that works, else the reason
    (``os.strerror``). Permission bits do not bind root and file systems such as ``/proc`` refuse new
    files whatever ``os.access`` says, so only a real creation tells whether an output can be written."""
    probe = Path(folder) / f".crfdepth-probe-{secrets.token_hex(6)}"
    try:
        os.close(os.open(probe, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600))
    except OSError as exc:
        return exc.strerror or type(exc).__name__
    probe.unlink(missing_ok=True)
    return None


# --------------------------------------------------------------------------- output-folder lock


class FolderLockedError(PermissionError):
    """An output folder is locked by another running crfdepth command (one-line message naming it)."""


def _command() -> str:
    """This process's command line as the user typed it (``crfdepth complete ...``)."""
    argv = list(sys.argv) or ["crfdepth"]
    argv[0] = "crfdepth" if Path(argv[0]).name in ("__main__.py", "crfdepth", "-c", "") else Path(argv[0]).name
    return " ".join(argv)


def _read_lock(lock: Path) -> dict | None:
    """The holder recorded in ``lock`` (pid, host, started, command, token); None when there is no lock
    file; ``{}`` when it cannot be read (being written this instant, or damaged)."""
    for attempt in range(3):
        try:
            text = lock.read_text(encoding="utf-8")
        except FileNotFoundError:
            return None
        except OSError:
            text = ""
        try:
            holder = json.loads(text)
            if isinstance(holder, dict) and isinstance(holder.get("pid"), int):
                return holder
        except ValueError:
            pass
        time.sleep(0.05 * (attempt + 1))  # created but not yet written by its run: look again
    return {}


def _gone(holder: dict) -> bool:
    """Whether the run that wrote ``holder`` no longer runs: on this host, its pid is not a process."""
    if not holder or holder.get("host") != socket.gethostname():
        return False  # another machine (a shared folder) or an unreadable lock: assume it runs
    pid = holder["pid"]
    if pid == os.getpid():
        return False
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return True
    except OSError:  # PermissionError: a process of another user
        return False
    return False


def _describe(holder: dict) -> str:
    if not holder:
        return "a crfdepth run whose lock file cannot be read"
    return (f"another crfdepth run (pid {holder['pid']} on {holder.get('host', '?')}, started "
            f"{holder.get('started', '?')}: {holder.get('command', '?')})")


def _locked(name: str, folder: Path, holder: dict) -> FolderLockedError:
    return FolderLockedError(f"{name}: the folder {folder} is being written by {_describe(holder)}; wait for it "
                             f"to finish or choose another folder; if that run is gone, delete {folder / LOCK_NAME}")


def check_not_locked(folder: str | os.PathLike, name: str = "path") -> None:
    """Refuse (:class:`FolderLockedError`, naming the argument ``name`` and the other run) an output
    ``folder`` that a running crfdepth command holds locked; a missing folder or lock, or a stale lock,
    passes. Takes no lock: :func:`lock_folder` does, once the run is about to write."""
    folder = Path(folder)
    holder = _read_lock(folder / LOCK_NAME)
    if holder is not None and not _gone(holder):
        raise _locked(name, folder, holder)


@contextlib.contextmanager
def lock_folder(folder: str | os.PathLike, name: str = "path") -> Iterator[Path]:
    """Hold the lock of the existing output ``folder`` for the ``with`` block (docstring of the module).

    The lock file is created with ``O_CREAT | O_EXCL`` (of two runs, exactly one gets it) and removed
    on leaving the block, whatever the reason, if it is still this run's. A lock whose run is gone
    (same host, pid not running) is taken over with a warning. Yields the lock file's path.

    Raises:
        FolderLockedError: another running crfdepth command holds the folder (pid, host, start time
            and command named, and the lock file to delete if that run is gone).
        PermissionError: the lock file cannot be created (the folder does not accept new files).
    """
    folder = Path(folder)
    lock = folder / LOCK_NAME
    token = secrets.token_hex(8)
    record = json.dumps({"pid": os.getpid(), "host": socket.gethostname(),
                         "started": datetime.datetime.now().astimezone().isoformat(timespec="seconds"),
                         "command": _command(), "token": token})
    for _ in range(3):
        try:
            fd = os.open(lock, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o644)
        except FileExistsError:
            holder = _read_lock(lock)
            if holder is None:
                continue  # released meanwhile: try again
            if not _gone(holder):
                raise _locked(name, folder, holder) from None
            _take_over(lock, holder, name)
            continue
        except OSError as exc:
            raise PermissionError(f"{name}: cannot create the lock file {lock} ({exc.strerror})") from None
        with os.fdopen(fd, "w", encoding="utf-8") as handle:
            handle.write(record + "\n")
        break
    else:
        raise _locked(name, folder, _read_lock(lock) or {})
    try:
        yield lock
    finally:
        holder = _read_lock(lock)
        if holder and holder.get("token") == token:
            lock.unlink(missing_ok=True)


def _take_over(lock: Path, holder: dict, name: str) -> None:
    """Remove the stale ``lock`` of a run that is gone. It is renamed aside first and checked to be the
    stale one, so that of two runs taking over at once neither removes the other's fresh lock."""
    aside = lock.with_name(f"{LOCK_NAME}.{secrets.token_hex(6)}.stale")
    try:
        os.rename(lock, aside)
    except FileNotFoundError:
        return  # another run took it over first
    if _read_lock(aside) != holder:  # a fresh lock of a run that took over just before: give it back
        with contextlib.suppress(OSError):
            os.link(aside, lock)
        aside.unlink(missing_ok=True)
        return
    aside.unlink(missing_ok=True)
    logger.warning("%s: taking over the lock of %s, which is no longer running (%s was left behind)",
                   name, _describe(holder).removeprefix("another "), lock)


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


def read_text(path: Path, what: str, holding: str, *, max_bytes: int = MAX_TEXT_BYTES) -> str:
    """A text file's contents (undecodable bytes replaced), or InputError naming ``what``.

    Refused: a path that is not a regular file (``<what>: expected a regular file with <holding>,
    got a FIFO (named pipe) <path>``), checked on the opened file before anything is read (opened
    non-blocking, so a FIFO without a writer does not hang); a file of more than ``max_bytes``
    bytes, of which at most ``max_bytes + 1`` are read; a binary file: an image or .npy signature,
    or NUL bytes (``<what>: expected a text file with <holding>, got a binary file (a PNG image)
    <path>``).
    """
    fd = os.open(path, os.O_RDONLY | getattr(os, "O_NONBLOCK", 0))
    try:
        info = os.fstat(fd)
        kind = file_kind(info.st_mode)
        if kind is not None:
            raise InputError(f"{what}: expected a regular file with {holding}, got {kind} {path}")
        if info.st_size > max_bytes:
            raise InputError(f"{what}: expected a text file of at most {_size(max_bytes)} with {holding}, got "
                             f"{_size(info.st_size)} in {path}")
    except BaseException:
        os.close(fd)
        raise
    with os.fdopen(fd, "rb") as handle:
        data = handle.read(max_bytes + 1)  # the size may grow after fstat: never read more than this
    if len(data) > max_bytes:
        raise InputError(f"{what}: expected a text file of at most {_size(max_bytes)} with {holding}, got more "
                         f"in {path}")
    kind = next((name for magic, name in _MAGIC if data.startswith(magic)), None)
    if kind is not None or b"\x00" in data:
        raise InputError(f"{what}: expected a text file with {holding}, got a binary file"
                         f" ({kind or 'NUL bytes'}) {path}")
    return data.decode("utf-8", errors="replace")


def _size(n: int) -> str:
    """``n`` bytes for messages: "1 MiB (1,048,576 bytes)", "512 bytes"."""
    for unit, scale in (("GiB", 1 << 30), ("MiB", 1 << 20), ("KiB", 1 << 10)):
        if n >= scale:
            return f"{n / scale:.4g} {unit} ({n:,} bytes)"
    return f"{n} bytes"


_MAGIC = ((b"\x89PNG", "a PNG image"), (b"\xff\xd8\xff", "a JPEG image"),
          (b"\x93NUMPY", "a .npy array"))
