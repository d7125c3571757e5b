"""The commands' output options as the library's typed arguments: :mod:`crfdepth.runs.outputs` checks, creates,
locks and writes the output folders and files (atomically); these adapters read the flags from ``args``."""

from __future__ import annotations

import argparse
from pathlib import Path

from crfdepth.runs import outputs
from crfdepth.runs.outputs import output_folders

__all__ = ["check_output_folders", "output_folders", "rerun_recording"]


def check_output_folders(args: argparse.Namespace, inputs: list[Path], source: str) -> list[tuple[str, str | None]]:
    """:func:`crfdepth.runs.outputs.check_output_folders` of ``--out-dir``, ``--out-std-dir`` and ``--vis``."""
    return outputs.check_output_folders(args.out_dir, args.out_std_dir, args.vis, inputs, source)


def rerun_recording(args: argparse.Namespace):
    """:func:`crfdepth.runs.outputs.rerun_recording` of ``--rerun``."""
    return outputs.rerun_recording(args.rerun)
