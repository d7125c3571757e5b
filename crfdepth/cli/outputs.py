"""The commands' output options as the library's typed arguments: :mod:`crfdepth.runs.outputs` checks, creates,
locks and writes the output folders and files (atomically); these adapters read the flags from ``args``."""

from __future__ import annotations

import argparse
import contextlib
from collections.abc import Iterator
from pathlib import Path

from crfdepth.pictures.rerun_recording import Recorder
from crfdepth.runs import outputs
from crfdepth.runs.outputs import output_folders

__all__ = ["check_output_folders", "output_folders", "rerun_recording"]


def check_output_folders(args: argparse.Namespace, inputs: list[Path], source: str) -> list[tuple[str, str | None]]:
    """:func:`crfdepth.runs.outputs.check_output_folders` of ``--out-dir``, ``--out-std-dir`` and ``--vis``."""
    return outputs.check_output_folders(args.out_dir, args.out_std_dir, args.vis, inputs, source)


@contextlib.contextmanager
def rerun_recording(args: argparse.Namespace) -> Iterator[Recorder | None]:
    """:func:`crfdepth.runs.outputs.rerun_recording` of ``--rerun``; once the file is written, a line saying so
    (not with ``--quiet``, nor for a bare ``--rerun`` streaming to a viewer)."""
    with outputs.rerun_recording(args.rerun) as recorder:
        yield recorder
    if recorder is not None and args.rerun and not getattr(args, "quiet", False):
        print(f"wrote {args.rerun}: a Rerun recording of {recorder.frames} frame(s); open it with: rerun {args.rerun}")
