"""OS errors on the files a command reads and writes, told in one line naming the user's flag.

A reader or writer of :mod:`crfdepth.io` raises ``OSError`` with the system's message and the
file's name (``[Errno 36] File name too long: '/tmp/aaa...png'``), or a message naming its own
argument (``depth png: no such file: x.png``); neither names the flag the user typed. The
commands wrap each read and write of a file the user named:

- :func:`flagged` (``with flagged("--sparse", path, "read", labels=("depth png",)):``): an error
  of the system becomes :class:`FileError` ``--sparse: cannot read x.png: Permission denied``;
  a reader's own message gets the flag in place of its label, keeping its class
  (``--sparse: no such file: x.png``);
- :func:`cannot_write`: the :class:`FileError` of a failed write, naming the file the user asked
  for, never the temporary file it was being written to
  (``--out: cannot write out/depth.png: No space left on device``);
- :func:`error_message`: what ``crfdepth.cli.main`` prints for an OS error that no wrapper told:
  the flag whose path the error concerns, found in the command line.
"""

from __future__ import annotations

import contextlib
import errno
import os
import re
from collections.abc import Iterator

from crfdepth.errors import InputError

__all__ = ["FileError", "cannot_write", "error_message", "flagged", "reason"]

# The name of a temporary file of crfdepth.io.files.atomic_write: ".<name>.<12 hex digits>.tmp".
_TEMPORARY = re.compile(r"^\.(.+)\.[0-9a-f]{12}\.tmp$")
# Errors that only a write meets: named "cannot write" even by the last resort.
_WRITE_ERRNOS = {errno.ENOSPC, errno.EROFS, errno.EDQUOT, errno.EFBIG}


class FileError(OSError):
    """A file the user named could not be read or written; the message is one line naming the flag,
    the file and the system's reason (``--out: cannot write d/depth.png: Read-only file system``).

    Not one of :data:`crfdepth.cli.arguments.BAD_INPUT`: a run over many frames stops on it even with
    ``--skip-bad`` (a full disk or a read-only folder fails every later frame the same way).
    ``crfdepth.cli.main`` prints it as the other errors (exit status 2).
    """


def reason(exc: OSError) -> str:
    """The system's words for ``exc`` (``Permission denied``), without the errno and file name."""
    return exc.strerror or (os.strerror(exc.errno) if exc.errno else str(exc))


def cannot_write(exc: OSError, flag: str, path: os.PathLike | str) -> FileError:
    """The error of a failed write of ``path`` (the file the user asked for, under ``flag``)."""
    return FileError(f"{flag}: cannot write {path}: {reason(exc)}")


def _is_system_error(exc: BaseException) -> bool:
    """An ``OSError`` raised by the system (errno set), not a message a reader wrote itself (``FileNotFoundError(
    "image: no such file: x")`` has no errno)."""
    return isinstance(exc, OSError) and not isinstance(exc, FileError) and exc.errno is not None


def _relabelled(exc: BaseException, flag: str, labels: tuple[str, ...]) -> BaseException | None:
    """``exc`` of the same class with its message naming ``flag``: its leading label (one of ``labels``,
    ``<label>: ...``) replaced by the flag, or the flag put before it; None when it starts with a flag already
    (this one, or another that the message is about: ``--camera 0: ...``)."""
    text = str(exc)
    if not text or text.startswith("--"):
        return None
    label = next((label for label in labels if text.startswith(f"{label}: ")), None)
    message = f"{flag}: {text[len(label) + 2:]}" if label is not None else f"{flag}: {text}"
    try:
        return type(exc)(message)
    except TypeError:  # a subclass that takes other arguments
        return InputError(message)


@contextlib.contextmanager
def flagged(flag: str, path: os.PathLike | str, verb: str = "read", labels: tuple[str, ...] = ()
            ) -> Iterator[None]:
    """Within the block, errors on the file(s) of ``flag`` (``path``) name the flag.

    Args:
        verb: what the block does with ``path``: ``read`` or ``write``.
        labels: the names the readers in the block give the argument (``image``, ``depth png``):
            a message ``<label>: ...`` becomes ``<flag>: ...``, of the same class; any other message that
            does not start with a flag gets the flag in front (``--points: PLY x.ply: malformed header``).

    An ``OSError`` of the system becomes :class:`FileError` ``<flag>: cannot <verb> <file>: <reason>``
    (``<file>``: for a read, the file the system names, which may lie inside the folder ``path``; for a
    write, ``path`` itself, never a temporary file beside it). A :class:`FileError` passes unchanged.
    """
    try:
        yield
    except FileError:
        raise
    except (InputError, OSError) as exc:
        if _is_system_error(exc):
            file = exc.filename if verb == "read" and exc.filename is not None else path
            raise FileError(f"{flag}: cannot {verb} {os.fsdecode(file)}: {reason(exc)}") from None
        relabelled = _relabelled(exc, flag, labels)
        if relabelled is None:
            raise
        raise relabelled from None


def _flag_values(argv: list[str]) -> list[tuple[str, str]]:
    """``(flag, value)`` of each ``--flag VALUE`` / ``--flag=VALUE`` of ``argv``."""
    pairs = []
    for i, token in enumerate(argv):
        if not token.startswith("--"):
            continue
        flag, sep, value = token.partition("=")
        if sep:
            pairs.append((flag, value))
        elif i + 1 < len(argv) and not argv[i + 1].startswith("--"):
            pairs.append((flag, argv[i + 1]))
    return pairs


def _without_temporary(filename: str) -> str:
    """The file a temporary file of :func:`crfdepth.io.files.atomic_write` stands for (``d/.x.png.<hex>.tmp`` ->
    ``d/x.png``); any other name as it is."""
    folder, name = os.path.split(filename)
    match = _TEMPORARY.match(name)
    return os.path.join(folder, match.group(1)) if match else filename


def _flag_of(filename: str, argv: list[str]) -> tuple[str, str] | None:
    """The ``(flag, value)`` of ``argv`` whose path ``filename`` is, lies in, or lies beside (a temporary file
    in the folder of an output file); the closest one."""
    try:
        target = os.path.abspath(filename)
    except (TypeError, ValueError):
        return None
    best = None
    for flag, value in _flag_values(argv):
        if not value:
            continue
        given = os.path.abspath(value)
        if target == given:
            rank = 0
        elif target.startswith(given.rstrip(os.sep) + os.sep):
            rank = 1
        elif os.path.dirname(target) == os.path.dirname(given) and os.path.basename(target).startswith("."):
            rank = 2  # a hidden temporary file beside the output
        else:
            continue
        if best is None or rank < best[0]:
            best = (rank, flag, value if rank == 2 else filename)
    return None if best is None else best[1:]


def error_message(exc: BaseException, argv: list[str]) -> str:
    """What ``crfdepth.cli.main`` prints for an error of bad input or of a file: the message itself, or for an
    OS error that no :func:`flagged` told, ``<flag>: cannot <use|write> <file>: <reason>`` with the flag whose
    path the error names (the path itself, a file in that folder, or a hidden temporary file beside that
    output file), or ``cannot <use|write> <file>: <reason>`` when no flag's path matches."""
    if not _is_system_error(exc):
        return str(exc)
    verb = "write" if exc.errno in _WRITE_ERRNOS else "use"
    for filename in (exc.filename, exc.filename2):
        if filename is None:
            continue
        filename = _without_temporary(os.fsdecode(filename))
        found = _flag_of(filename, argv)
        if found is not None:
            return f"{found[0]}: cannot {verb} {found[1]}: {reason(exc)}"
    if exc.filename is not None:
        return f"cannot {verb} {_without_temporary(os.fsdecode(exc.filename))}: {reason(exc)}"
    return reason(exc)
