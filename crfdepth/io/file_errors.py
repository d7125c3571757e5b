"""Errors on the files a user named, told in one line naming the user's argument (docs/design.md section 8).

A reader or writer of :mod:`crfdepth.io` raises ``OSError`` with the system's message and the
file's name (``[Errno 36] File name too long: '/tmp/aaa...png'``), or a message naming its own
argument (``depth png: no such file: x.png``); neither names the argument (a command's flag) the
user typed. The code that reads or writes a file the user named wraps it:

- :func:`flagged` (``with flagged("--sparse", path, "read", labels=("depth png",)):``): an error
  of the system becomes :class:`FileError` ``--sparse: cannot read x.png: Permission denied``;
  a reader's own message gets the flag in place of its label, keeping its class
  (``--sparse: no such file: x.png``);
- :func:`cannot_write`: the :class:`FileError` of a failed write, naming the file the user asked
  for, never the temporary file it was being written to
  (``--out: cannot write out/depth.png: No space left on device``).

The command line's last resort for an error that no wrapper told is
:func:`crfdepth.cli.file_errors.error_message`.
"""

from __future__ import annotations

import contextlib
import os
from collections.abc import Iterator

from crfdepth.errors import InputError

__all__ = ["FileError", "cannot_write", "flagged", "is_system_error", "reason"]


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


def is_system_error(exc: BaseException) -> bool:
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
        if is_system_error(exc):
            file = exc.filename if verb == "read" and exc.filename is not None else path
            raise FileError(f"{flag}: cannot {verb} {os.fsdecode(file)}: {reason(exc)}") from None
        relabelled = _relabelled(exc, flag, labels)
        if relabelled is None:
            raise
        raise relabelled from None
