"""``crfdepth complete --input-dir``: every frame of a KITTI ``val_selection_cropped`` or
``test_depth_completion_anonymous`` folder, or of a KITTI raw drive folder, checked first, then completed in batches
(see :mod:`crfdepth.cli.complete`).

A raw drive (``<day>/<day>_drive_<NNNN>_sync``: ``velodyne_points/data/<frame>.bin``, ``image_0X/data/<frame>.png``, the
day's ``calib_cam_to_cam.txt`` and ``calib_velo_to_cam.txt`` in the folder above) is read by
:class:`~crfdepth.data.kitti.KittiDrive`: each scan projected whole into the ``--camera`` image (2 or 3), uncropped, as
``--points SCAN --calib DAY`` does for one frame; outputs ``<out-dir>/<frame>.png``; a day folder holding drives is
refused, naming them. The rest (batches, ``--resume``, ``--skip-bad``, ``--devices``, ``--rerun``) is the same for both;
resume's batch plan reads a frame's size from its image (a drive's scan is a ``.bin``), the run record holds the camera.
"""

from __future__ import annotations

import argparse
import contextlib
import functools
import itertools
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
from crfdepth.cli.file_errors import FileError, flagged
from crfdepth.cli.model_options import build_model
from crfdepth.cli.outputs import check_output_folders, output_folders, write_frame
from crfdepth.cli.processes import deal, in_processes, run_share
from crfdepth.cli.ranks import Ranks, run_in_group
from crfdepth.cli.resume import (
    batch_plan,
    check_resumable,
    earlier_run_record,
    finish_run_record,
    finished_frames,
    restore_run_record,
    run_record,
    write_run_record,
)
from crfdepth.cli.skip_bad import skipped_frames, write_failed, write_skipped
from crfdepth.data.kitti import KittiDrive, is_raw_drive, open_completion_folder, raw_drives
from crfdepth.errors import InputError

logger = logging.getLogger("crfdepth.cli.complete")  # the command's logger, whichever mode runs

__all__ = ["FOLDER_FLAGS", "complete_planned", "complete_share", "run_folder"]

# What names a frame's depth PNG, std PNG and pictures in a write error (crfdepth.cli.outputs.write_frame).
FOLDER_FLAGS = ("--out-dir", "--out-std-dir", "--vis")


def _where(index: int, total: int, name: str) -> str:
    """How folder mode names a frame: ``frame 2/5 <name>``."""
    return f"frame {index + 1}/{total} {name}"


_SELECTION_FILES = {"K": "intrinsics/", "sparse": "velodyne_raw/{name}.png", "image": "image/"}


def _check_frame(sample, index: int, *, total: int, positions: list[int] | None = None,
                 files: dict[str, str] = _SELECTION_FILES) -> None:
    """:func:`~crfdepth.cli.completion.check_sample` in the DataLoader workers, naming the frame's files
    as the one-frame path names its flags (``frame 2/5 <name> (velodyne_raw/<name>.png): ...``; ``files``:
    where the ``K``, ``sparse`` and ``image`` of frame ``{name}`` lie, :func:`_frame_files`);
    ``positions[index]`` is the frame's place in the folder when the run leaves frames out (--skip-bad)."""
    try:
        check_sample(sample)
    except InputError as exc:
        where = _where(index if positions is None else positions[index], total, sample.name)
        raise flag_names(exc, {key: f"{where} ({label.format(name=sample.name)})"
                               for key, label in files.items()}) from None


def _frame_files(dataset) -> dict[str, str]:
    """Where a frame's inputs lie in the folder ``dataset`` reads, for messages (:func:`_check_frame`)."""
    if isinstance(dataset, KittiDrive):
        return {"K": "../calib_cam_to_cam.txt", "sparse": "velodyne_points/data/{name}.bin",
                "image": f"image_0{dataset.camera}/data/{{name}}.png"}
    return _SELECTION_FILES


def _open_folder(path: str, camera: int):
    """The dataset of ``--input-dir``: a ``depth_selection`` folder or a raw drive (errors name the flag)."""
    folder = Path(path)
    with flagged("--input-dir", path):  # a name too long, a folder that cannot be listed ...
        return _open(folder, path, camera)


def _open(folder: Path, path: str, camera: int):
    if not folder.exists():
        raise FileNotFoundError(f"--input-dir: no such folder: {path}")
    if not folder.is_dir():
        raise InputError(f"--input-dir: expected a folder with image/, velodyne_raw/ and intrinsics/ (a KITTI "
                         f"val_selection_cropped or test_depth_completion_anonymous folder) or a KITTI raw drive "
                         f"folder (velodyne_points/, image_02/), got a file: {path}")
    drive = is_raw_drive(folder) or bool(raw_drives(folder))
    if drive and camera not in (2, 3):
        raise InputError(f"--camera {camera}: expected 2 or 3 (a colour camera) for the KITTI raw drive {path}")
    if not drive and camera != 2:
        raise InputError(f"--camera {camera}: applies to a KITTI raw drive; {path} is a depth-completion folder, "
                         f"whose file names say the camera")
    try:
        return KittiDrive(folder, camera=camera) if drive else open_completion_folder(folder)
    except InputError as exc:
        raise InputError(f"--input-dir {path}: {exc}") from None


def _inputs(dataset) -> tuple[list[Path], list[Path]]:
    """The input folders of ``dataset`` (no output folder may be one) and, per frame, the PNG whose header
    gives its size (resume's batch plan: a drive's sparse input is a ``.bin`` scan, so its image)."""
    if isinstance(dataset, KittiDrive):
        cam = f"image_0{dataset.camera}"
        subs = (cam, f"{cam}/data", "velodyne_points", "velodyne_points/data")
        return [dataset.root / sub for sub in subs], [dataset.image_path(i) for i in range(len(dataset))]
    subs = ("image", "velodyne_raw", "intrinsics", "groundtruth_depth")
    return [dataset.root / sub for sub in subs], [dataset.sparse_path(i) for i in range(len(dataset))]


def _check_frames(dataset, args, positions: list[int]) -> list[tuple[int, type[BaseException], str]]:
    """Pass 1 of folder mode: frames ``positions`` of the folder ``dataset`` read and checked
    (:func:`~crfdepth.cli.batches.bad_frames`); each message names its frame (``frame 3/6 <name>: ...``; a check
    names the file too). Returns (folder index, error, message) of the bad ones."""
    total = len(dataset)
    progress = tqdm(total=len(positions), unit="frame", desc="check", disable=args.quiet or not sys.stderr.isatty())
    checked = []

    def step(index: int) -> None:
        checked.append(index)
        progress.update(1)

    frames = dataset if len(positions) == total else Subset(dataset, positions)
    try:
        check = functools.partial(_check_frame, total=total, positions=positions, files=_frame_files(dataset))
        bad = bad_frames(frames, args.workers, check, step)
        found = []
        for k, error, message in bad:
            where = _where(positions[k], total, dataset.names[positions[k]])
            found.append((positions[k], error, message if message.startswith(where) else f"{where}: {message}"))
        return found
    except KeyboardInterrupt:
        raise KeyboardInterrupt(f"while checking the frames ({len(checked)} of {len(positions)} checked); nothing "
                                f"written") from None
    finally:
        progress.close()


def _other_pngs(out_dir: Path, names: list[str]) -> int:
    """PNG files in ``out_dir`` that this run does not write (an earlier run's, on other frames)."""
    mine = {f"{name}.png" for name in names}
    return sum(1 for entry in os.scandir(out_dir) if entry.name.endswith(".png") and entry.name not in mine)


def run_folder(args: argparse.Namespace, ranks: Ranks | None = None) -> int:
    """Folder mode (:mod:`crfdepth.cli.complete`); ``ranks``: the group the caller has joined (``--input-list``
    joins it once for the whole list), else the run is spread here as ``--strategy`` says
    (:func:`~crfdepth.cli.ranks.run_in_group`)."""
    if args.out_dir is None:
        raise InputError("--input-dir needs --out-dir (the folder for the output PNGs)")
    stray = [flag for flag, value in (("--image", args.image), ("--sparse", args.sparse),
                                      ("--intrinsics", args.intrinsics), ("--points", args.points),
                                      ("--calib", args.calib), ("--out", args.out),
                                      ("--out-std", args.out_std)) if value is not None]
    if stray:
        raise InputError(f"{', '.join(stray)}: one-frame options cannot be combined with --input-dir")
    return _run(args, ranks) if ranks is not None else run_in_group(args, _run)


def _run(args: argparse.Namespace, ranks: Ranks | None) -> int:
    """:func:`run_folder` alone, with ``--devices`` local processes, or as one rank of a group."""
    main = ranks is None or ranks.is_main
    built: dict = {}
    start = time.perf_counter()
    with contextlib.ExitStack() as stack:
        # what decides the files: checked and planned once (rank 0), the folders created and locked there
        run = _prepare(args, stack, built, eager_record=ranks is not None) if ranks is None else \
            ranks.share(lambda: _prepare(args, stack, built, eager_record=True))
        dataset, plan, folders, with_std = run["dataset"], run["plan"], run["folders"], run["with_std"]
        out_dir = folders[0]
        failed: list[tuple[str, str]] = []
        counts = {"written": 0}
        failing = False
        try:
            if ranks is not None or (args.devices > 1 and plan):
                if ranks is None:
                    write_run_record(out_dir, run["record"])
                    done = in_processes(args, [(dataset, batches, folders, with_std)
                                               for batches in deal(plan, args.devices)], complete_share)
                else:
                    shares = deal(plan, ranks.world)
                    mine = shares[ranks.rank] if ranks.rank < len(shares) else []
                    done = ranks.gather(run_share(f"rank {ranks.rank + 1}/{ranks.world}", args, complete_share,
                                                  (dataset, mine, folders, with_std), built.get("model")))
                counts["written"] = sum(partial.get("written", 0) for partial, _ in done)
                failed[:] = [row for partial, _ in done for row in partial.get("failed", [])]
                stopped = [stop for _, stop in done if stop is not None]
                if stopped:
                    raise _stopped(stopped, counts["written"], sum(map(len, plan)), out_dir)
            elif plan:
                complete_planned(args, built["model"], dataset, plan, folders, with_std, failed, counts,
                                 lambda: write_run_record(out_dir, run["record"]))
        except BaseException:
            failing = True
            raise
        finally:  # also when a run stops after writing frames: the failed ones are listed for --resume (a run
            # stopped before its first frame leaves nothing: its error names the frame)
            failed_csv = _close_run(args, run, out_dir, failed, counts["written"], failing) if main else None
        if main and not failed and (plan or (args.resume and run["earlier_record"] is not None)):
            finish_run_record(out_dir, run["record"])  # a run that wrote nothing leaves the record it found
    if main and not args.quiet:
        _summary(args, run, counts["written"], failed, failed_csv, time.perf_counter() - start)
    return 0


def _close_run(args: argparse.Namespace, run: dict, out_dir: Path, failed: list[tuple[str, str]], written: int,
               stopped: bool) -> Path | None:
    """``failed.csv`` of a run that wrote frames (or ran with ``--skip-bad``), for ``--resume``; returns it. A run
    ``stopped`` by an error or Ctrl-C before its first frame was written leaves nothing of its own: no
    ``failed.csv``, no ``skipped.csv`` and no run record that it wrote (the record of an earlier run, stopped or
    finished, is put back as it was, for ``--resume``: a group of ranks writes its record before the first
    frame), so that the output folders it created are empty and removed
    (:func:`~crfdepth.cli.outputs.output_folders`). When the run is stopped by an error, a file that cannot be
    written now (a full disk) does not hide it."""
    try:
        if stopped and not written:
            restore_run_record(out_dir, run["earlier_record"])
            if run["skipped_csv"] is not None:
                run["skipped_csv"].unlink(missing_ok=True)
            return None
        return write_failed(out_dir, failed if written or args.skip_bad else [])
    except OSError:
        if not stopped:
            raise
        return None


def _prepare(args: argparse.Namespace, stack: contextlib.ExitStack, built: dict, eager_record: bool) -> dict:
    """The folder opened and checked, the model built (kept in ``built``), the frames checked and the batches
    planned (``--resume``, ``--skip-bad``), the output folders created and locked (on ``stack``) and
    ``skipped.csv`` written; with ``eager_record``, the run's record too. Returns what the ranks share."""
    dataset = _open_folder(args.input_dir, args.camera)
    inputs, size_files = _inputs(dataset)
    targets = check_output_folders(args, inputs, f"an input folder of {dataset.root}")
    model = built["model"] = build_model(args)
    total = len(dataset)
    with_std = args.out_std_dir is not None or args.vis is not None
    record = run_record(args, model, with_std)
    if isinstance(dataset, KittiDrive):
        record["camera"] = dataset.camera  # decides the files as the model does
    finished = _finished(args, dataset, targets, record, with_std) if args.resume else set()
    todo = [i for i in range(total) if i not in finished]
    bad = _check_frames(dataset, args, todo)
    skipped = skipped_frames(bad, len(todo), f"--input-dir {args.input_dir}", args.skip_bad)
    good = [i for i in range(total) if i not in skipped]
    # the uninterrupted run's batches; a resumed run redoes each one holding an unfinished frame, whole
    plan = [[good[k] for k in batch] for batch in batch_plan([size_files[i] for i in good], args.batch_size)
            if any(good[k] not in finished for k in batch)]
    created = stack.enter_context(output_folders(targets))
    folders = (created[0], created[1], created[2] if args.vis is not None else None)
    others = _other_pngs(folders[0], [dataset.names[i] for i in range(total)])
    if others:
        logger.warning("--out-dir %s already holds %d PNG file(s) that this run does not write (an earlier "
                       "run on other frames?); they stay", folders[0], others)
    skipped_csv = write_skipped(folders[0], [(dataset.names[i], m) for i, m in skipped.items()])
    earlier_record = earlier_run_record(folders[0])  # an earlier run's, which a run that writes no frame leaves
    if eager_record and plan:
        write_run_record(folders[0], record)
    return {"dataset": dataset, "plan": plan, "folders": folders, "with_std": with_std, "record": record,
            "finished": finished, "good": good, "skipped": skipped, "skipped_csv": skipped_csv, "total": total,
            "earlier_record": earlier_record}


def _summary(args: argparse.Namespace, run: dict, written: int, failed: list, failed_csv, seconds: float) -> None:
    out_dir, std_dir, vis_dir = run["folders"]
    finished, good, skipped, total = run["finished"], run["good"], run["skipped"], run["total"]
    print(f"wrote {written} depth PNG(s) to {out_dir}" + (f", std to {std_dir}" if std_dir else "")
          + (f", pictures to {vis_dir}" if vis_dir else "") + f" in {seconds:.1f} s")
    if finished:
        redone = sum(map(len, run["plan"])) - (len(good) - len(finished & set(good)))
        print(f"{len(finished)} of {total} frame(s) were finished by an earlier run (--resume)"
              + (f"; {redone} of them done again with the unfinished frames of their batch" if redone else ""))
    if skipped:
        print(f"skipped {len(skipped)} bad frame(s) of {total} (--skip-bad), listed with the reasons in "
              f"{run['skipped_csv']}")
    if failed:
        print(f"{len(failed)} frame(s) failed (--skip-bad), listed with the reasons in {failed_csv}; "
              f"--resume completes them once fixed")


def _finished(args, dataset, targets, record: dict, with_std: bool) -> set[int]:
    """``--resume``: the frames whose outputs an earlier run of this model and options left complete."""
    folders = dict(targets)
    out_dir = Path(folders["--out-dir"])
    if not out_dir.is_dir():
        return set()
    std_dir = Path(folders["--out-std-dir"]) if folders.get("--out-std-dir") else None
    vis_dir = Path(folders["--vis"]) if folders.get("--vis") is not None else None
    check_resumable(out_dir, record)
    return finished_frames(dataset.names, out_dir, std_dir, vis_dir, with_std)


def complete_planned(args, model, dataset, plan: list[list[int]], folders: tuple, with_std: bool,
                     failed: list[tuple[str, str]], counts: dict, first_write=None) -> None:
    """Complete and write the frames of ``plan`` (batches of indices into the folder ``dataset``), each batch
    as planned (:func:`_complete_frames`); ``counts["written"]`` counts the frames written as they are."""
    run = [i for batch in plan for i in batch]
    starts = set(itertools.accumulate(len(batch) for batch in plan[:-1]))
    check = functools.partial(_check_frame, total=len(dataset), positions=run, files=_frame_files(dataset))
    _complete_frames(args, model, Subset(dataset, run), [dataset.names[i] for i in run], len(dataset), run, folders,
                     with_std, starts, first_write, failed, counts, check)


def complete_share(args, model, share: tuple, partial: dict) -> None:
    """One process's part of a ``--devices`` run (:func:`crfdepth.cli.processes.in_processes`): its batches of
    the folder completed and written; ``partial`` counts them (``written``) and lists the ``failed`` frames."""
    dataset, batches, folders, with_std = share
    partial["written"] = 0
    if batches:
        complete_planned(args, model, dataset, batches, folders, with_std, partial.setdefault("failed", []), partial)


def _stopped(stopped: list[tuple[str, bool]], written: int, planned: int, out_dir: Path) -> BaseException:
    """The error of a run whose processes stopped early (``stopped``: (message, interrupted) of each):
    KeyboardInterrupt when one was interrupted, else an InputError; the other processes' frames stay written."""
    note = f"{written} of {planned} frame(s) written to {out_dir}; --resume completes the others"
    if any(interrupted for _, interrupted in stopped):
        return KeyboardInterrupt(f"after {note}")
    return InputError(f"{stopped[0][0]} [{len(stopped)} process(es) stopped; {note}]")


def _complete_frames(args, model, frames, names: list[str], total: int, positions: list[int], folders: tuple,
                     with_std: bool, starts: set[int], first_write, failed: list[tuple[str, str]], counts: dict,
                     check) -> int:
    """Pass 2 of folder mode: complete and write ``frames`` in batches that start at ``starts`` besides
    size changes and ``--batch-size`` (frame ``k`` is frame ``positions[k]`` of the folder's ``total``),
    each checked by ``check(sample, k)`` (:func:`_check_frame`); returns the number written, counted in
    ``counts["written"]`` as each frame's files are in place.
    ``first_write()`` runs before the first file is written.

    A failure now (the frame changed since pass 1, a non-finite model output, a batch too large for the
    memory) is added to ``failed`` (name, reason) for each frame of its batch; with ``--skip-bad`` the
    run goes on, without it the run stops saying how many frames were written, as Ctrl-C does."""
    out_dir, std_dir, vis_dir = folders
    progress = tqdm(total=len(names), unit="frame", desc="complete", disable=args.quiet or not sys.stderr.isatty())
    batches = frame_batches(frames, args.batch_size, args.workers, check, starts)
    done = 0
    # the frames a failure concerns: those of the batch not yet written, or the next frame to read
    where, unwritten = _where(positions[0], total, names[0]), names[:1]
    try:
        for batch in batches:  # a frame that fails to read or check is raised here, after the frames before it
            unwritten = list(batch.names)
            if len(batch) > 1:
                where = (f"frames {positions[done] + 1}-{positions[done + len(batch) - 1] + 1}/{total} "
                         f"({', '.join(batch.names)})")
            try:
                _complete_batch(args, model, batch, with_std, folders, first_write if not counts["written"] else None,
                                counts, unwritten)
            except BAD_INPUT as exc:
                if not args.skip_bad:
                    raise
                failed.extend((name, f"{where}: {exc}") for name in unwritten)
            done += len(batch)
            progress.update(len(batch))
            if done < len(names):
                where, unwritten = _where(positions[done], total, names[done]), names[done:done + 1]
    except (*BAD_INPUT, FileError) as exc:  # FileError: an output that cannot be written stops even --skip-bad
        failed.extend((name, f"{where}: {exc}") for name in unwritten)
        raise type(exc)(f"{exc} [stopped at {where}; {counts['written']} of {len(names)} frame(s) written to "
                        f"{out_dir}; --resume completes the others]") from None
    except KeyboardInterrupt:
        raise KeyboardInterrupt(f"after {counts['written']} of {len(names)} frame(s) written to {out_dir}; "
                                f"--resume completes the others") from None
    finally:
        batches.close()  # stops the DataLoader workers
        progress.close()
    return counts["written"]


def _complete_batch(args, model, batch, with_std: bool, folders: tuple, first_write, counts: dict,
                    unwritten: list[str]) -> None:
    """Complete and write one batch, each frame counted in ``counts["written"]`` and taken off ``unwritten`` as
    soon as its files are in place (a failure on a later frame of the batch leaves the earlier ones written)."""
    out_dir, std_dir, vis_dir = folders
    depth, std = complete_batch_with_cli_advice(model, batch, with_std)
    depth = depth.cpu().numpy()  # float32, as the one-frame mode writes it
    std = std.cpu().numpy() if std is not None else [None] * len(batch)
    if first_write is not None:
        first_write()
    for k, name in enumerate(batch.names):
        write_frame(depth[k], std[k], out_dir / f"{name}.png", std_dir / f"{name}.png" if std_dir else None,
                    vis_dir, name, args.vis_range, FOLDER_FLAGS)  # the frame's files: all of them or none
        counts["written"] += 1
        unwritten.remove(name)
        if args.recorder is not None:  # --rerun
            args.recorder.complete_frame(batch.image[k], depth[k], std[k], sparse=batch.sparse[k], K=batch.K[k])
