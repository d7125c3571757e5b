"""The ``crfdepth`` command line: one sub-command per module in this package.

Each sub-command module defines ``add_parser(subparsers)`` (registers its arguments and
sets ``func``) so this file only lists them. Errors from bad input exit with status 2 and
a one-line message; nothing happens at import.
"""

from __future__ import annotations

import argparse
import importlib
import logging
import sys

from crfdepth.errors import InputError

# Sub-command modules, in the order ``crfdepth --help`` lists them.
_COMMANDS = (
    "crfdepth.cli.demo",
    "crfdepth.cli.project",
    "crfdepth.cli.complete",
    "crfdepth.cli.evaluate",
)


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="crfdepth",
        description="Dense depth from a camera image and sparse LiDAR with a learnable CRF.",
    )
    parser.add_argument("-v", "--verbose", action="store_true", help="log progress at INFO level")
    subparsers = parser.add_subparsers(dest="command", metavar="COMMAND")
    for name in _COMMANDS:
        importlib.import_module(name).add_parser(subparsers)
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO if args.verbose else logging.WARNING,
                        format="%(levelname)s %(name)s: %(message)s")
    if not getattr(args, "func", None):
        parser.print_help()
        return 2
    try:
        return int(args.func(args) or 0)
    except (InputError, FileNotFoundError, PermissionError, IsADirectoryError) as exc:
        print(f"crfdepth {args.command}: error: {exc}", file=sys.stderr)
        return 2


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
