"""The ``crfdepth`` command line: one sub-command per module in this package.

Each sub-command module ``crfdepth.cli.<command>`` defines ``HELP`` (its line in
``crfdepth --help``), ``DESCRIPTION`` (the head of its own ``--help``),
``add_arguments(parser)`` and ``run(args)``, so this file only lists them
(:func:`add_command`). Nothing happens at import.

Exit statuses: 0 on success; 2 for bad input or a file that cannot be read or written, with
one line on stderr naming the option (``crfdepth project: error: --keep-every-ring: expected
..., got ...``, ``crfdepth complete: error: --out: cannot write d/depth.png: No space left on
device``) and no output file written, whether argparse refuses an option (``SystemExit(2)``)
or a sub-command raises :class:`~crfdepth.errors.InputError` or any ``OSError`` (``main``
returns 2): the commands tell the errors of the files they read and write under the flag
(:mod:`crfdepth.cli.file_errors`), and an OS error that none told is named by the flag whose
path it concerns, found in the command line, never shown as a traceback; 130 on Ctrl-C, with
one line (``crfdepth project: interrupted``; a folder or bag run adds how many frames it
wrote: ``crfdepth complete: interrupted after 3 of 10 frame(s) written to pred/``, the
text of the ``KeyboardInterrupt`` it re-raises); 1 when a command fails on good input, with one line: a solve
that did not converge under ``on_nonconvergence="raise"``, no memory left, or an internal error (a bug: the line
says so, and ``crfdepth --verbose`` shows Python's traceback instead). Warnings raised while a command runs (NaN
points dropped, a solve that did not converge) are one line each on stderr,
``crfdepth complete: warning: points: dropped 3 of ...``, without Python's category and
source line (:func:`warnings_as_lines`). ``crfdepth --version`` prints
``crfdepth <version>`` (:data:`crfdepth.__version__`).
"""

from __future__ import annotations

import argparse
import contextlib
import difflib
import importlib
import logging
import sys
import warnings
from collections.abc import Iterator
from types import ModuleType

from crfdepth._version import __version__
from crfdepth.cli.arguments import OneLineParser
from crfdepth.errors import ConvergenceError, InputError

# Sub-command modules, in the order ``crfdepth --help`` lists them.
_COMMANDS = (
    "crfdepth.cli.demo",
    "crfdepth.cli.project",
    "crfdepth.cli.complete",
    "crfdepth.cli.evaluate",
    "crfdepth.cli.targets",
)
# The exit status of a command stopped by Ctrl-C (128 + SIGINT), as shells report it.
EXIT_INTERRUPTED = 130
# The exit status of a command that failed on good input: a solve that did not converge when asked to raise, no
# memory left, or a bug (one line each, never a traceback; --verbose shows the traceback of a bug).
EXIT_FAILED = 1


def _first_line(exc: BaseException) -> str:
    """The first line of ``exc``'s message (a traceback-free summary)."""
    text = str(exc).strip()
    return text.splitlines()[0] if text else ""


@contextlib.contextmanager
def warnings_as_lines(command: str | None) -> Iterator[None]:
    """Within the block, print each warning as ``crfdepth <command>: warning: <message>``.

    Python's default shows ``<file>:<line>: UserWarning: <message>`` and the source line,
    which tells a command-line user nothing; the message alone (its lines joined) is what
    they need. Filters (``-W``, ``PYTHONWARNINGS``) still decide which warnings show; the
    previous ``warnings.showwarning`` and filters are restored afterwards.
    """
    prefix = f"crfdepth{' ' + command if command else ''}: warning: "

    def show(message, category, filename, lineno, file=None, line=None) -> None:
        text = " ".join(str(message).split("\n")).strip()
        if category is not UserWarning and not category.__module__.startswith("crfdepth."):
            text = f"{category.__name__}: {text}"  # another library's FutureWarning etc.: say which kind
        try:
            print(prefix + text, file=file if file is not None else sys.stderr, flush=True)
        except OSError:  # stderr closed: as warnings.showwarning, never fail the command over a warning
            pass

    with warnings.catch_warnings():
        warnings.showwarning = show
        # --workers: DataLoader forks its workers from this process, which holds torch's thread pools;
        # PyTorch supports that (its pools restart in the child), and Python 3.12+ warns about any fork
        # of a multi-threaded process (shown under pytest and -W default: an extra stderr line). It made
        # three --workers error tests fail on a Python 3.12 machine; with this filter they pass there.
        warnings.filterwarnings("ignore", message=r"This process \(pid=\d+\) is multi-threaded, use of fork\(\)",
                                category=DeprecationWarning)
        yield


def add_command(subparsers: argparse._SubParsersAction, module: ModuleType) -> argparse.ArgumentParser:
    """Register the sub-command of ``module`` (``crfdepth.cli.<command>``) on ``subparsers``; ``args.func`` is its
    ``run``."""
    parser = subparsers.add_parser(module.__name__.rpartition(".")[2], help=module.HELP,
                                   description=module.DESCRIPTION)
    module.add_arguments(parser)
    parser.set_defaults(func=module.run)
    return parser


def build_parser(commands: tuple[str, ...] | None = None) -> argparse.ArgumentParser:
    """The ``crfdepth`` parser with the sub-commands ``commands`` (names, e.g. ``("complete",)``; default all).

    Only the modules of ``commands`` are imported (:func:`main` imports the chosen one alone: importing them all
    costs seconds of torch, kornia, scipy and more); each sub-parser is the same whichever others are there.
    """
    parser = OneLineParser(
        prog="crfdepth",
        description="Dense depth from a camera image and sparse LiDAR with a learnable CRF.",
    )
    parser.add_argument("--version", action="version", version=f"crfdepth {__version__}")
    parser.add_argument("-v", "--verbose", action="store_true", help="log progress at INFO level")
    subparsers = parser.add_subparsers(dest="command", metavar="COMMAND")
    parser.commands = {}  # name -> its parser, for refuse_unknown
    for name in _COMMANDS:
        if commands is None or name.rpartition(".")[2] in commands:
            command = add_command(subparsers, importlib.import_module(name))
            parser.commands[command.prog.rpartition(" ")[2]] = command
    return parser


def _commands_needed(argv: list[str]) -> tuple[str, ...] | None:
    """The sub-commands :func:`main` must build to parse ``argv`` as the full parser would (None: all of them).

    The options before the command take no value, so the first argument that is not an option names it: that one
    sub-command alone, unless a help option before it asks for the list of all. Without a command, ``--version``
    alone needs none (``crfdepth --version`` imports no sub-command, nor torch)."""
    names = {name.rpartition(".")[2] for name in _COMMANDS}
    for arg in argv:
        if arg == "--" or (arg.startswith("--") and "--help".startswith(arg.partition("=")[0]) and len(arg) > 2):
            return None
        if arg.startswith("-") and not arg.startswith("--") and "h" in arg:  # -h, -vh
            return None
        if not arg.startswith("-"):
            return (arg,) if arg in names else None
        if arg.startswith("--vers") and "--version".startswith(arg):
            return ()  # argparse prints the version and exits here, before any command
    return None


def refuse_unknown(parser: argparse.ArgumentParser, args: argparse.Namespace, unknown: list[str]) -> None:
    """Exit (status 2) on arguments no parser took, as the sub-command's usage error (argparse alone blames
    ``crfdepth``), naming the closest option of that command for a misspelt one."""
    target = getattr(parser, "commands", {}).get(getattr(args, "command", None), parser)
    message = f"unrecognized arguments: {' '.join(unknown)}"
    flag = next((a.partition("=")[0] for a in unknown if a.startswith("--")), None)
    close = difflib.get_close_matches(flag, [o for o in target._option_string_actions if o.startswith("--")],
                                      n=1, cutoff=0.7) if flag else []
    if close:
        message += f" (did you mean {close[0]}?)"
    target.error(message)


class _LineFormatter(logging.Formatter):
    """Log records as the command's one-line messages: ``crfdepth complete: warning: ...`` (like
    its errors and :func:`warnings_as_lines`), without the logger's name."""

    def __init__(self, prefix: str) -> None:
        super().__init__()
        self.prefix = prefix

    def format(self, record: logging.LogRecord) -> str:
        return f"{self.prefix}: {record.levelname.lower()}: {record.getMessage()}"


def main(argv: list[str] | None = None) -> int:
    """Run ``crfdepth`` with ``argv`` (default ``sys.argv[1:]``); returns the exit status.

    Usage errors, ``--help`` and ``--version`` leave through argparse's ``SystemExit``.
    """
    command = None
    try:
        argv = [str(a) for a in (sys.argv[1:] if argv is None else argv)]
        parser = build_parser(_commands_needed(argv))
        args, unknown = parser.parse_known_args(argv)
        if unknown:
            refuse_unknown(parser, args, unknown)
        args.argv = argv  # the command line, run again in each rank that --strategy ddp starts
        command = args.command
        handler = logging.StreamHandler()  # stderr; a no-op where the root logger is already set up
        handler.setFormatter(_LineFormatter(f"crfdepth{' ' + command if command else ''}"))
        logging.basicConfig(level=logging.INFO if args.verbose else logging.WARNING, handlers=[handler])
        if not getattr(args, "func", None):
            parser.print_help()
            return 2
        try:
            from crfdepth.cli.model_options import check_device  # imports torch: not for --help / --version

            check_device(getattr(args, "device", None))  # --device cuda without CUDA: refused before any work
            with warnings_as_lines(command):
                return int(args.func(args) or 0)
        except (InputError, OSError) as exc:  # bad input, or a file that cannot be read or written
            from crfdepth.cli.file_errors import error_message  # imports crfdepth.io: not for --help / --version

            print(f"crfdepth {command}: error: {error_message(exc, argv)}", file=sys.stderr)
            return 2
        except ConvergenceError as exc:  # a model whose solver settings say on_nonconvergence="raise"
            print(f"crfdepth {command}: error: {_first_line(exc)}", file=sys.stderr)
            return EXIT_FAILED
        except MemoryError as exc:  # torch's out-of-memory errors are MemoryErrors too
            print(f"crfdepth {command}: error: out of memory ({_first_line(exc) or 'no detail'}): give fewer or "
                  f"smaller frames at once (--batch-size, --devices) or a device with more memory", file=sys.stderr)
            return EXIT_FAILED
        except Exception as exc:  # a bug: one line that says so; --verbose shows Python's traceback
            if getattr(args, "verbose", False):
                raise
            print(f"crfdepth {command}: error: internal error, {type(exc).__name__}: {_first_line(exc)} (a bug in "
                  f"crfdepth {__version__}; run it again as crfdepth --verbose ... for the traceback and report it)",
                  file=sys.stderr)
            return EXIT_FAILED
    except KeyboardInterrupt as exc:
        detail = str(exc)  # a command that writes several files says how far it got ("after 3 of 10 ...")
        print(f"crfdepth{' ' + command if command else ''}: interrupted{' ' + detail if detail else ''}",
              file=sys.stderr)
        return EXIT_INTERRUPTED


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
