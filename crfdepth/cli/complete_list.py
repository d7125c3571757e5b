"""``crfdepth complete --input-list FILE``: many inputs in one run, one after the other.

FILE names one input per line: a KITTI depth-completion folder (``val_selection_cropped``,
``test_depth_completion_anonymous`` or their parent, as ``--input-dir`` takes), a KITTI raw drive
folder (``<day>/<day>_drive_<NNNN>_sync``, as ``--input-dir`` takes it too, with ``--camera``) or a ROS
1 / ROS 2 recording (as ``--bag`` takes, with the same topics for every recording). Blank lines and
lines starting with ``#`` are skipped; a relative path is relative to FILE's folder. Every line is
checked before anything runs: a path that is missing, unreadable or of another kind is refused naming
FILE and the line number; so is a raw day folder (``2011_09_26``), with its drives named: each drive
is a line of its own, completed into a subfolder of its own.

Each input is completed into a subfolder of ``--out-dir`` (and of ``--out-std-dir`` and ``--vis``
when given) named after it (``<folder, drive or recording name>``, with ``-<line>`` added where two inputs
share a name), by the folder or bag mode with the run's options, ``--resume``, ``--skip-bad``, ``--devices``,
``--num-nodes`` and ``--strategy`` included. One input is held at a time, so the memory is that of the
largest input's run, not of the list. An input that fails stops the run, naming its line, unless
``--skip-bad``: then the others go on and the summary lists the failed lines. ``--resume`` continues a
stopped list: each folder input resumes (:mod:`crfdepth.runs.resume`), and a recording is completed again
whole (its ``index.csv`` lists the frames of one run).

As ranks of a group (``--num-nodes`` under torchrun, ``--strategy ddp``: :mod:`crfdepth.runs.ranks`) the
group is joined once for the whole list. Rank 0 reads the list and shares it; each folder is then checked
and planned by rank 0 and its batches dealt to the ranks, as ``--input-dir`` does; a recording is
completed by rank 0 alone (its frames are read in order, from one file) while the other ranks wait. An
input's error is shared with every rank, so with ``--skip-bad`` every rank goes on to the next input, and
without it every rank stops, alike.
"""

from __future__ import annotations

import argparse
import copy
import functools
import os
from pathlib import Path

from crfdepth.cli.arguments import BAD_INPUT
from crfdepth.data.kitti.drive import is_raw_drive, raw_drives, shown_drives
from crfdepth.errors import InputError
from crfdepth.runs.outputs import is_inside, same_file
from crfdepth.runs.ranks import Ranks, Spread, run_in_group

__all__ = ["read_input_list", "run_list"]

BAG_SUFFIXES = (".bag", ".mcap", ".db3")
COMPLETION_FOLDERS = ("val_selection_cropped", "test_depth_completion_anonymous")


def read_input_list(path: str) -> list[tuple[int, Path, str]]:
    """``(line number, path, kind)`` of each input of the list file ``path``; kind is "folder" or "bag"."""
    listing = Path(path)
    if not listing.is_file():
        raise FileNotFoundError(f"--input-list: no such file: {path}")
    try:
        lines = listing.read_text().splitlines()
    except (OSError, UnicodeDecodeError) as exc:
        raise InputError(f"--input-list: cannot read {path} as text ({exc})") from None
    entries = []
    for number, line in enumerate(lines, start=1):
        text = line.strip()
        if not text or text.startswith("#"):
            continue
        entry = Path(text) if Path(text).is_absolute() else listing.parent / text
        entries.append((number, entry, _kind(entry, f"--input-list {path}, line {number}: {text}")))
    if not entries:
        raise InputError(f"--input-list: {path} names no input (one KITTI depth-completion folder, raw drive "
                         f"folder or ROS recording per line)")
    return entries


def _kind(entry: Path, where: str) -> str:
    if not entry.exists():
        raise FileNotFoundError(f"{where}: no such file or folder")
    if not os.access(entry, os.R_OK | (os.X_OK if entry.is_dir() else 0)):
        raise PermissionError(f"{where}: cannot be read (permission denied)")
    if entry.is_file():
        if entry.suffix in BAG_SUFFIXES:
            return "bag"
        raise InputError(f"{where}: expected a KITTI depth-completion folder, a KITTI raw drive folder or a ROS "
                         f"recording ({', '.join(BAG_SUFFIXES)} or a ROS 2 bag folder), got a "
                         f"{entry.suffix or 'plain'} file")
    if (entry / "metadata.yaml").is_file():
        return "bag"
    if any((folder / "velodyne_raw").is_dir() for folder in (entry, *(entry / n for n in COMPLETION_FOLDERS))):
        return "folder"
    if is_raw_drive(entry):
        return "folder"
    drives = raw_drives(entry)
    if drives:
        raise InputError(f"{where}: expected one KITTI raw drive folder, got a day folder holding {len(drives)} "
                         f"drive(s); list each on a line of its own ({shown_drives(drives)})")
    raise InputError(f"{where}: expected a KITTI depth-completion folder (velodyne_raw/, image/, intrinsics/), a "
                     f"KITTI raw drive folder (velodyne_points/, image_02/) or a ROS recording, got a folder "
                     f"without them")


def _names(entries: list[tuple[int, Path, str]]) -> list[str]:
    """The output subfolder of each input: its name, with ``-<line>`` where two inputs share one."""
    base = [(p.stem if kind == "bag" and p.is_file() else p.name) for _, p, kind in entries]
    return [name if base.count(name) == 1 else f"{name}-{number}" for name, (number, _, _) in zip(base, entries)]


def run_list(args: argparse.Namespace, run_folder, run_bag) -> int:
    """Complete every input of ``--input-list`` in turn (module docstring); returns 0."""
    if args.out_dir is None:
        raise InputError("--input-list needs --out-dir (a subfolder per input is written there)")
    if args.out_bag is not None:
        raise InputError("--out-bag: one output recording per input is not supported with --input-list; complete "
                         "each recording with --bag")
    stray = [flag for flag, value in (("--image", args.image), ("--sparse", args.sparse), ("--points", args.points),
                                      ("--out", args.out), ("--out-std", args.out_std)) if value is not None]
    if stray:
        raise InputError(f"{', '.join(stray)}: one-frame options cannot be combined with --input-list")
    argv = getattr(args, "argv", None)
    spread = Spread(args.devices, args.num_nodes, args.strategy, args.device, tuple(argv) if argv is not None else None)
    return run_in_group(spread, functools.partial(_run_list, args, run_folder=run_folder, run_bag=run_bag))


def _run_list(args: argparse.Namespace, ranks: Ranks | None, run_folder, run_bag) -> int:
    """:func:`run_list` alone or as one rank of a group joined once for the whole list: rank 0 reads the list and
    runs each recording, each folder is shared out (:func:`~crfdepth.cli.complete_folder.run_folder`), and an
    input's error is raised on every rank alike, so that ``--skip-bad`` goes on, or the run stops, everywhere."""
    def read_and_check():
        entries = read_input_list(args.input_list)
        return entries, _check_inputs(args, entries, _names(entries))

    entries, bad = read_and_check() if ranks is None else ranks.share(read_and_check)
    names = _names(entries)
    failed, done = [], 0
    for (number, entry, kind), name in zip(entries, names):
        if number in bad:  # --skip-bad: refused by the check of every line, before any input was completed
            failed.append(bad[number])
            continue
        mine = _input_args(args, entry, kind, name)
        try:
            if kind == "folder":
                run_folder(mine, ranks)
            elif ranks is None:
                run_bag(mine)
            else:  # a recording is read in order: rank 0 completes it while the others wait for the outcome
                ranks.share(lambda: run_bag(mine))
        except BAD_INPUT as exc:
            message = f"--input-list line {number} ({entry}): {exc}"
            if not args.skip_bad:
                raise type(exc)(f"{message} [{done} of {len(entries)} input(s) completed before it; --resume "
                                f"continues]") from None
            failed.append(message)
            continue
        done += 1
    if not args.quiet and (ranks is None or ranks.is_main):
        print(f"completed {done} of {len(entries)} input(s) of --input-list {args.input_list} into {args.out_dir}")
        for message in failed:
            print(f"failed: {message}")
    return 0


def _check_inputs(args: argparse.Namespace, entries: list[tuple[int, Path, str]], names: list[str]) -> dict[int, str]:
    """Every line checked as its run will check it before reading a frame (the folder's layout and frames, the
    recording's topics, the output subfolders: not among the inputs of any line, writable, not locked), nothing
    written. The first bad line raises, named ``--input-list line N (PATH): ...``; with ``--skip-bad`` the bad
    lines are returned instead (line number -> message), to be left out and listed as failed."""
    from crfdepth.cli.complete_bag import check_bag
    from crfdepth.cli.complete_folder import folder_run
    from crfdepth.runs.folder import check_folder_run

    bad = {}
    for (number, entry, kind), name in zip(entries, names):
        mine = _input_args(args, entry, kind, name)
        try:
            for flag, value in (("--out-dir", mine.out_dir), ("--out-std-dir", mine.out_std_dir), ("--vis", mine.vis)):
                inside = next((p for _, p, _ in entries if value and (same_file(value, p) or is_inside(value, p))),
                              None)
                if inside is not None:
                    raise InputError(f"{flag}: {value} is or lies inside the input {inside} of the list; refusing "
                                     f"to write among the inputs, choose a folder outside them")
            if kind == "folder":
                check_folder_run(folder_run(mine))
            else:
                check_bag(mine)
        except BAD_INPUT as exc:
            message = f"--input-list line {number} ({entry}): {exc}"
            if not args.skip_bad:
                raise type(exc)(f"{message} [every line is checked before any input is completed; nothing "
                                f"written]") from None
            bad[number] = message
    return bad


def _input_args(args: argparse.Namespace, entry: Path, kind: str, name: str) -> argparse.Namespace:
    """The options of the run of one input of the list (``kind`` "folder" or "bag"), written into ``name``."""
    mine = copy.copy(args)
    mine.input_list = None
    mine.input_dir = str(entry) if kind == "folder" else None
    mine.bag = str(entry) if kind == "bag" else None
    mine.out_dir = str(Path(args.out_dir) / name)
    mine.out_std_dir = str(Path(args.out_std_dir) / name) if args.out_std_dir is not None else None
    mine.vis = str(Path(args.vis) / name) if args.vis else args.vis
    if kind == "bag" and args.resume:  # a recording is completed whole again: its index.csv lists one run
        mine.overwrite, mine.resume = True, False
    return mine
