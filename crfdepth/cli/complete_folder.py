"""``crfdepth complete --input-dir``: the folder run's options read from the command line and its summary printed;
the run itself (checks, batches, ``--resume``, ``--skip-bad``, ``--devices``) is the library's
:func:`crfdepth.runs.folder.complete_folder` (see :mod:`crfdepth.cli.complete`)."""

from __future__ import annotations

import argparse
import functools

from crfdepth.cli.completion import cli_advice
from crfdepth.cli.model_options import model_maker
from crfdepth.cli.progress import FrameBars
from crfdepth.errors import InputError
from crfdepth.runs.folder import FolderResult, FolderRun, complete_folder
from crfdepth.runs.ranks import Ranks, Spread

__all__ = ["folder_run", "run_folder", "summary"]


def folder_run(args: argparse.Namespace) -> FolderRun:
    """The :class:`~crfdepth.runs.folder.FolderRun` that ``args`` asks for; refuses a folder run without
    ``--out-dir`` or with one-frame options."""
    if args.out_dir is None:
        raise InputError("--input-dir needs --out-dir (the folder for the output PNGs)")
    stray = [flag for flag, value in (("--image", args.image), ("--sparse", args.sparse),
                                      ("--intrinsics", args.intrinsics), ("--points", args.points),
                                      ("--calib", args.calib), ("--out", args.out),
                                      ("--out-std", args.out_std)) if value is not None]
    if stray:
        raise InputError(f"{', '.join(stray)}: one-frame options cannot be combined with --input-dir")
    argv = getattr(args, "argv", None)
    return FolderRun(
        input_dir=args.input_dir, out_dir=args.out_dir, out_std_dir=args.out_std_dir, vis=args.vis,
        vis_range=args.vis_range, camera=args.camera, batch_size=args.batch_size, workers=args.workers,
        skip_bad=args.skip_bad, resume=args.resume, quiet=args.quiet, device=args.device,
        spread=Spread(args.devices, args.num_nodes, args.strategy, args.device, tuple(argv) if argv is not None else None),
        make_model=model_maker(args), memory_advice=functools.partial(cli_advice, args.device),
        progress=FrameBars(), report=summary, recorder=args.recorder)


def run_folder(args: argparse.Namespace, ranks: Ranks | None = None) -> int:
    """Folder mode (:mod:`crfdepth.cli.complete`); ``ranks``: the group the caller has joined (``--input-list``
    joins it once for the whole list), else the run is spread as ``--strategy`` says."""
    return complete_folder(folder_run(args), ranks)


def summary(result: FolderResult) -> None:
    """The lines a folder run prints when it ends (unless ``--quiet``)."""
    out_dir, std_dir, vis_dir = result.folders
    finished, good, skipped, total = result.finished, result.good, result.skipped, result.total
    print(f"wrote {result.written} depth PNG(s) to {out_dir}" + (f", std to {std_dir}" if std_dir else "")
          + (f", pictures to {vis_dir}" if vis_dir else "") + f" in {result.seconds:.1f} s")
    if finished:
        redone = result.planned - (len(good) - len(finished & set(good)))
        print(f"{len(finished)} of {total} frame(s) were finished by an earlier run (--resume)"
              + (f"; {redone} of them done again with the unfinished frames of their batch" if redone else ""))
    if skipped:
        print(f"skipped {len(skipped)} bad frame(s) of {total} (--skip-bad), listed with the reasons in "
              f"{result.skipped_csv}")
    if result.failed:
        print(f"{len(result.failed)} frame(s) failed (--skip-bad), listed with the reasons in {result.failed_csv}; "
              f"--resume completes them once fixed")
