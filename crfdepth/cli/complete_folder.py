"""``crfdepth complete --input-dir``: every frame of a KITTI ``val_selection_cropped`` or
``test_depth_completion_anonymous`` folder, checked first, then completed in batches (see
:mod:`crfdepth.cli.complete`)."""

from __future__ import annotations

import argparse
import functools
import logging
import os
import sys
import time
from pathlib import Path

from torch.utils.data import Subset
from tqdm import tqdm

from crfdepth.cli.arguments import BAD_INPUT
from crfdepth.cli.batches import bad_frames, frame_batches
from crfdepth.cli.completion import check_sample, complete_batch_with_cli_advice, flag_names
from crfdepth.cli.model_options import build_model
from crfdepth.cli.outputs import check_output_folders, output_folders, write_frame
from crfdepth.cli.skip_bad import skipped_frames, write_skipped
from crfdepth.data.kitti import open_completion_folder
from crfdepth.errors import InputError

logger = logging.getLogger("crfdepth.cli.complete")  # the command's logger, whichever mode runs

__all__ = ["run_folder"]


def _where(index: int, total: int, name: str) -> str:
    """How folder mode names a frame: ``frame 2/5 <name>``."""
    return f"frame {index + 1}/{total} {name}"


def _check_frame(sample, index: int, *, total: int, positions: list[int] | None = None) -> None:
    """:func:`~crfdepth.cli.completion.check_sample` in the DataLoader workers, naming the frame's files
    as the one-frame path names its flags (``frame 2/5 <name> (velodyne_raw/<name>.png): ...``);
    ``positions[index]`` is the frame's place in the folder when the run leaves frames out (--skip-bad)."""
    try:
        check_sample(sample)
    except InputError as exc:
        where = _where(index if positions is None else positions[index], total, sample.name)
        raise flag_names(exc, {"K": f"{where} (intrinsics/)", "sparse": f"{where} (velodyne_raw/{sample.name}.png)",
                                "image": f"{where} (image/)"}) from None


def _open_folder(path: str):
    """The ``depth_selection`` dataset of ``--input-dir`` (errors name the flag)."""
    folder = Path(path)
    if not folder.exists():
        raise FileNotFoundError(f"--input-dir: no such folder: {path}")
    if not folder.is_dir():
        raise InputError(f"--input-dir: expected a folder with image/, velodyne_raw/ and intrinsics/ (a KITTI "
                         f"val_selection_cropped or test_depth_completion_anonymous folder), got a file: {path}")
    try:
        return open_completion_folder(folder)
    except InputError as exc:
        raise InputError(f"--input-dir {path}: {exc}") from None


def _check_frames(dataset, args, total: int) -> list[tuple[int, type[BaseException], str]]:
    """Pass 1 of folder mode: every frame read and checked (:func:`~crfdepth.cli.batches.bad_frames`); each
    message names its frame (``frame 3/6 <name>: ...``; a check names the file too)."""
    progress = tqdm(total=total, unit="frame", desc="check", disable=args.quiet or not sys.stderr.isatty())
    checked = []

    def step(index: int) -> None:
        checked.append(index)
        progress.update(1)

    try:
        bad = bad_frames(dataset, args.workers, functools.partial(_check_frame, total=total), step)
        return [(i, error, message if message.startswith(_where(i, total, dataset.names[i]))
                 else f"{_where(i, total, dataset.names[i])}: {message}") for i, error, message in bad]
    except KeyboardInterrupt:
        raise KeyboardInterrupt(f"while checking the frames ({len(checked)} of {total} checked); nothing "
                                f"written") from None
    finally:
        progress.close()


def _other_pngs(out_dir: Path, names: list[str]) -> int:
    """PNG files in ``out_dir`` that this run does not write (an earlier run's, on other frames)."""
    mine = {f"{name}.png" for name in names}
    return sum(1 for entry in os.scandir(out_dir) if entry.name.endswith(".png") and entry.name not in mine)


def run_folder(args: argparse.Namespace) -> int:
    if args.out_dir is None:
        raise InputError("--input-dir needs --out-dir (the folder for the output PNGs)")
    stray = [flag for flag, value in (("--image", args.image), ("--sparse", args.sparse),
                                      ("--intrinsics", args.intrinsics), ("--points", args.points),
                                      ("--calib", args.calib), ("--out", args.out),
                                      ("--out-std", args.out_std)) if value is not None]
    if stray:
        raise InputError(f"{', '.join(stray)}: one-frame options cannot be combined with --input-dir")
    dataset = _open_folder(args.input_dir)
    inputs = [dataset.root / sub for sub in ("image", "velodyne_raw", "intrinsics", "groundtruth_depth")]
    targets = check_output_folders(args, inputs, f"an input folder of {dataset.root}")
    model = build_model(args)
    total = len(dataset)
    bad = _check_frames(dataset, args, total)
    skipped = skipped_frames(bad, total, f"--input-dir {args.input_dir}", args.skip_bad)
    good = [i for i in range(total) if i not in skipped]
    names = [dataset.names[i] for i in good]
    frames = Subset(dataset, good) if skipped else dataset
    with_std = args.out_std_dir is not None or args.vis is not None
    start = time.perf_counter()
    with output_folders(targets) as folders:
        out_dir, std_dir = folders[0], folders[1]
        vis_dir = folders[2] if args.vis is not None else None
        others = _other_pngs(out_dir, names)
        if others:
            logger.warning("--out-dir %s already holds %d PNG file(s) that this run does not write (an earlier "
                           "run on other frames?); they stay", out_dir, others)
        skipped_csv = write_skipped(out_dir, [(dataset.names[i], m) for i, m in skipped.items()])
        written = _complete_frames(args, model, frames, names, total, good, out_dir, std_dir, vis_dir, with_std)
    seconds = time.perf_counter() - start
    if not args.quiet:
        print(f"wrote {written} depth PNG(s) to {out_dir}" + (f", std to {std_dir}" if std_dir else "")
              + (f", pictures to {vis_dir}" if vis_dir else "") + f" in {seconds:.1f} s")
        if skipped:
            print(f"skipped {len(skipped)} bad frame(s) of {total} (--skip-bad), listed with the reasons in "
                  f"{skipped_csv}")
    return 0


def _complete_frames(args, model, frames, names: list[str], total: int, positions: list[int], out_dir: Path,
                     std_dir: Path | None, vis_dir: Path | None, with_std: bool) -> int:
    """Pass 2 of folder mode: complete and write ``frames`` (frame ``k`` is frame ``positions[k]`` of the
    folder's ``total``); returns the number written. A failure now (the frame changed since pass 1, a
    non-finite model output) stops the run saying how many frames were written, as does Ctrl-C."""
    progress = tqdm(total=len(names), unit="frame", desc="complete", disable=args.quiet or not sys.stderr.isatty())
    check = functools.partial(_check_frame, total=total, positions=positions)
    batches = frame_batches(frames, args.batch_size, args.workers, check)
    written = 0
    where = _where(positions[0], total, names[0])
    try:
        for batch in batches:  # a frame that fails to read or check is raised here, after the frames before it
            if len(batch) > 1:
                where = (f"frames {positions[written] + 1}-{positions[written + len(batch) - 1] + 1}/{total} "
                         f"({', '.join(batch.names)})")
            depth, std = complete_batch_with_cli_advice(model, batch, with_std)
            depth = depth.cpu().numpy()  # float32, as the one-frame mode writes it
            std = std.cpu().numpy() if std is not None else [None] * len(batch)
            for name, frame_depth, frame_std in zip(batch.names, depth, std):
                where = _where(positions[written], total, name)
                write_frame(frame_depth, frame_std, out_dir / f"{name}.png",
                            std_dir / f"{name}.png" if std_dir is not None else None, vis_dir, name,
                            args.vis_range)
                written += 1
                progress.update(1)
            if written < len(names):
                where = _where(positions[written], total, names[written])
    except BAD_INPUT as exc:
        raise type(exc)(f"{exc} [stopped at {where}; {written} of {len(names)} frame(s) written to "
                        f"{out_dir}]") from None
    except KeyboardInterrupt:
        raise KeyboardInterrupt(f"after {written} of {len(names)} frame(s) written to {out_dir}") from None
    finally:
        batches.close()  # stops the DataLoader workers
        progress.close()
    return written
