"""The command lines of the benchmark scripts: one-line usage errors, checked option types, and a safety net.

Every bad input of a script is one line on stderr, ``<script>: error: --option: expected ..., got ...``, and
exit status 2, before any work (the convention of ``crfdepth``'s commands, crfdepth/cli/arguments.py):

- :class:`ScriptParser`: argparse's usage errors in one line (no usage block), choices and unknown options
  in the project's words;
- the option types: :func:`count` (an integer in a range; crfdepth.cli.arguments.int_at_least),
  :func:`seed`, :func:`share`, :func:`positive`, :func:`device` (one this machine has), :func:`folder`,
  :func:`file`, :func:`out_folder`;
- :func:`run_script`: a bad input found once the work began (an :class:`~crfdepth.errors.InputError`, a
  missing file, an unwritable output) in the same one line, never a traceback.
"""

from __future__ import annotations

import argparse
import math
import re
import sys
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import torch

from crfdepth.cli.arguments import MAX_SEED, MAX_WORKERS, OneLineParser, fraction, int_at_least
from crfdepth.errors import BAD_INPUT
from crfdepth.io.file_errors import FileError

__all__ = ["MAX_THREADS", "MAX_WORKERS", "ScriptParser", "count", "device", "file", "folder", "out_folder",
           "positive", "run_script", "seed", "share"]

#: Largest ``--threads``: torch CPU threads; more than any machine's cores is a typo.
MAX_THREADS = 1024


class ScriptParser(OneLineParser):
    """crfdepth's :class:`~crfdepth.cli.arguments.OneLineParser` (one-line usage errors, exit status 2, choices in the
    project's words), whose other usage errors are told in the project's form too (:func:`_words`).

    ``prog`` is the script's file name (``accuracy.py``), as the scripts are run: ``python benchmarks/<prog>``.
    """

    def error(self, message: str):
        self.exit(2, f"{self.prog}: error: {_words(message)}\n")


def _words(message: str) -> str:
    """argparse's usage error in the project's form, ``--option: expected ..., got ...``."""
    message = " ".join(message.split()).removeprefix("argument ")
    match = re.fullmatch(r"the following arguments are required: (.*)", message)
    if match:
        return f"{match.group(1)}: expected a value, got none (required)"
    match = re.fullmatch(r"unrecognized arguments: (\S+).*", message)
    if match:
        return f"{match.group(1)}: expected an option of this script (--help lists them), got an unknown one"
    match = re.fullmatch(r"([^:]+): expected (one|at least one|\d+) arguments?", message)
    if match:
        return (f"{match.group(1)}: expected {match.group(2)} value(s), got fewer (a value that starts with '-' "
                f"reads as an option: give it as {match.group(1).split('/')[-1]}=VALUE)")
    return message


def count(low: int, high: int | None = None, meaning: str | None = None) -> Callable[[str], int]:
    """An integer in [``low``, ``high``] (``high`` None: the largest C int); crfdepth's ``int_at_least``."""
    return int_at_least(low, high, meaning)


def seed(text: str) -> int:
    """A ``--seed``: an integer in [0, 2**32 - 1] (what every seeding API takes)."""
    return int_at_least(0, MAX_SEED, "a seed")(text)


def share(*, include_one: bool = False, meaning: str | None = None) -> Callable[[str], float]:
    """A number in (0, 1) or (0, 1]; crfdepth's ``fraction``."""
    return fraction(include_one=include_one, meaning=meaning)


def positive(unit: str, *, zero: bool = False) -> Callable[[str], float]:
    """A finite number of ``unit`` > 0 (>= 0 with ``zero``)."""
    def parse(text: str) -> float:
        try:
            value = float(text)
        except ValueError:
            value = math.nan
        if not math.isfinite(value) or (value < 0 if zero else value <= 0):
            raise argparse.ArgumentTypeError(f"expected a finite number of {unit} {'>=' if zero else '>'} 0, "
                                             f"got {text!r}")
        return value

    return parse


def device(text: str) -> str:
    """A torch device this machine has: ``cpu``, ``cuda``, ``cuda:K`` (K below the GPU count) or ``mps``."""
    try:
        dev = torch.device(text)
    except (RuntimeError, ValueError):
        raise argparse.ArgumentTypeError(f"expected cpu, cuda, cuda:K or mps, got {text!r}") from None
    if dev.type == "cuda":
        available = torch.cuda.device_count() if torch.cuda.is_available() else 0
        if available == 0 or (dev.index or 0) >= available:
            raise argparse.ArgumentTypeError(f"expected a device this machine has ({available} CUDA GPU(s)), got "
                                             f"{text!r}; likely fix: --device cpu")
    elif dev.type == "mps":
        if not torch.backends.mps.is_available():
            raise argparse.ArgumentTypeError(f"expected a device this machine has, got {text!r} without Apple's "
                                             "Metal backend; likely fix: --device cpu")
    elif dev.type != "cpu":
        raise argparse.ArgumentTypeError(f"expected cpu, cuda, cuda:K or mps, got {text!r}")
    return text


def _existing(what: str, *, is_folder: bool) -> Callable[[str], Path]:
    """An existing folder (``is_folder``) or readable file; ``what`` it should be, for the message."""
    def parse(text: str) -> Path:
        path = Path(text)
        if not text or not (path.is_dir() if is_folder else path.is_file()):
            other = path.is_file() if is_folder else path.is_dir()
            why = ("which is a file" if is_folder else "which is a folder") if other else \
                ("no such folder" if is_folder else "no such file")
            raise argparse.ArgumentTypeError(f"expected {what}, got {text!r} ({why})")
        return path

    return parse


def folder(what: str) -> Callable[[str], Path]:
    """An existing folder (``what`` it should hold, for the message)."""
    return _existing(what, is_folder=True)


def file(what: str) -> Callable[[str], Path]:
    """An existing, readable file (``what`` it should be, for the message)."""
    return _existing(what, is_folder=False)


def out_folder(text: str) -> Path:
    """A folder to write into: existing, or to be made (not an existing file, not an empty name)."""
    path = Path(text)
    if not text:
        raise argparse.ArgumentTypeError("expected a folder to write into, got ''")
    if path.exists() and not path.is_dir():
        raise argparse.ArgumentTypeError(f"expected a folder to write into, got {text!r}, which is a file")
    return path


def run_script(main: Callable[[Sequence[str] | None], Any], prog: str, argv: Sequence[str] | None = None) -> int:
    """``main(argv)``, with a bad input found once the work began (``InputError``, a missing or unreadable
    file, an output that cannot be written) as one line ``<prog>: error: ...`` and exit status 2: the safety
    net behind each script's own checks of its options. An ``int`` returned by ``main`` is the exit status."""
    try:
        result = main(argv)
    except (*BAD_INPUT, FileError) as exc:
        print(f"{prog}: error: {' '.join(str(exc).split())}", file=sys.stderr)
        return 2
    return result if isinstance(result, int) and not isinstance(result, bool) else 0
