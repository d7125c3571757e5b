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

:func:`flagged`, :func:`cannot_write` and :class:`FileError` are the library's
(:mod:`crfdepth.io.file_errors`), so that library code reading a file the user named tells its errors alike.
"""

from __future__ import annotations

import errno
import os
import re

from crfdepth.io.file_errors import FileError, cannot_write, flagged, is_system_error, reason

__all__ = ["FileError", "cannot_write", "error_message", "flagged", "reason"]

# The name of a temporary file of crfdepth.io.files.atomic_write: ".<name>.<12 hex digits>.tmp".
_TEMPORARY = re.compile(r"^\.(.+)\.[0-9a-f]{12}\.tmp$")
# Errors that only a write meets: named "cannot write" even by the last resort.
_WRITE_ERRNOS = {errno.ENOSPC, errno.EROFS, errno.EDQUOT, errno.EFBIG}


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
    if not is_system_error(exc):
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
