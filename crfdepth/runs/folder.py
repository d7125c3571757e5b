"""Completing a folder of frames (``crfdepth complete --input-dir``): every frame of a KITTI ``val_selection_cropped``
or ``test_depth_completion_anonymous`` folder, or of a KITTI raw drive folder, checked first, then completed in
batches and written (``crfdepth.cli.complete`` tells the options and files).

A raw drive (``<day>/<day>_drive_<NNNN>_sync``: ``velodyne_points/data/<frame>.bin``, ``image_0X/data/<frame>.png``, the
day's ``calib_cam_to_cam.txt`` and ``calib_velo_to_cam.txt`` in the folder above) is read by
:class:`~crfdepth.data.kitti.KittiDrive`: each scan projected whole into the ``--camera`` image (2 or 3), uncropped, as
``--points SCAN --calib DAY`` does for one frame; outputs ``<out-dir>/<frame>.png``; a day folder holding drives is
refused, naming them. The rest (batches, ``--resume``, ``--skip-bad``, ``--devices``, ``--rerun``) is the same for both;
resume's batch plan reads a frame's size from its image (a drive's scan is a ``.bin``), the run record holds the camera.

:func:`complete_folder` takes the run as a typed :class:`FolderRun` (the command line builds it from its flags, whose
names the messages keep) and reports the outcome to ``FolderRun.report`` (a :class:`FolderResult`). Its frames go
from the DataLoader workers' checks straight to the API's model step (:func:`crfdepth.api.complete_checked`,
docs/design.md section 8).
"""

from __future__ import annotations

import contextlib
import logging
import os
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

from crfdepth.data.kitti import KittiDrive, is_raw_drive, open_completion_folder, raw_drives
from crfdepth.errors import InputError
from crfdepth.io.file_errors import flagged
from crfdepth.runs.folder_frames import complete_frames, complete_share, find_bad_frames
from crfdepth.runs.launch import launch_ranks
from crfdepth.runs.outputs import check_output_folders, output_folders
from crfdepth.runs.processes import deal, in_processes, run_share
from crfdepth.runs.ranks import Ranks, Spread, joined_group, launches_ranks
from crfdepth.runs.resume import (
    batch_plan,
    check_resumable,
    earlier_run_record,
    finish_run_record,
    finished_frames,
    restore_run_record,
    run_record,
    write_run_record,
)
from crfdepth.runs.skip_bad import skipped_frames, write_failed, write_skipped

logger = logging.getLogger("crfdepth.cli.complete")  # the command's logger, whichever mode runs

__all__ = ["FolderResult", "FolderRun", "check_folder_run", "complete_folder"]


@dataclass(frozen=True)
class FolderRun:
    """A run over the folder ``input_dir`` (picklable: ``--devices`` processes receive it).

    Args:
        input_dir: a KITTI depth-completion folder or raw drive folder; ``camera``: a drive's camera, 2 or 3.
        out_dir, out_std_dir: the folders of the depth and std PNGs (KITTI depth PNGs, metres * 256; std None:
            not written).
        vis: the pictures' folder (None: none; ``""``: ``<out-dir>_vis``); ``vis_range``: their fixed depth colour
            scale in metres (None: each frame's 2nd-98th percentile).
        batch_size: frames per model call (>= 1); ``workers``: DataLoader processes reading ahead (0: this one).
        skip_bad: leave bad frames out (``skipped.csv``) instead of refusing the run; ``resume``: leave out the
            frames an earlier run of the same model and options finished (:mod:`crfdepth.runs.resume`).
        quiet: no progress and no report; ``device``: "cpu" or "cuda" (the run record's device type).
        spread: how the run is spread over processes and ranks (:class:`~crfdepth.runs.ranks.Spread`).
        make_model: ``make_model(quiet)`` builds the model (quiet: without telling which); module-level, picklable.
        memory_advice: the fix a memory refusal of a batch of ``n`` frames advises (``memory_advice(n)``; None: the
            API's); progress: the caller's progress factory (:mod:`crfdepth.runs.progress`); report: called with
            the :class:`FolderResult` on the main process unless ``quiet``; recorder: a
            :class:`~crfdepth.pictures.rerun_recording.Recorder` that logs each frame written, or None.
    """

    input_dir: str
    out_dir: str
    make_model: Callable
    out_std_dir: str | None = None
    vis: str | None = None
    vis_range: tuple[float, float] | None = None
    camera: int = 2
    batch_size: int = 1
    workers: int = 0
    skip_bad: bool = False
    resume: bool = False
    quiet: bool = False
    device: str = "cpu"
    spread: Spread = field(default_factory=Spread)
    memory_advice: Callable[[int], str] | None = None
    progress: Callable | None = None
    report: Callable[["FolderResult"], None] | None = None
    recorder: object = None


@dataclass
class FolderResult:
    """What a folder run did: ``written`` frames into ``folders`` (depth, std, pictures; None where not written)
    in ``seconds``; of the folder's ``total`` frames, ``finished`` (indices) an earlier run had finished
    (``--resume``), ``good`` passed the checks, ``skipped`` ({index: reason}) were left out (listed in
    ``skipped_csv``), ``failed`` ((name, reason)) failed when completed (listed in ``failed_csv``); ``planned``:
    frames in the batches run (unfinished ones and the finished ones of their batches)."""

    written: int
    folders: tuple[Path, Path | None, Path | None]
    total: int
    finished: set[int]
    good: list[int]
    skipped: dict[int, str]
    skipped_csv: Path | None
    failed: list[tuple[str, str]]
    failed_csv: Path | None
    planned: int
    seconds: float


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
    """The input folders of ``dataset`` (no output folder may be one or lie inside one: the folder itself and the
    subfolders it reads) and, per frame, the PNG whose header gives its size (resume's batch plan: a drive's sparse
    input is a ``.bin`` scan, so its image)."""
    if isinstance(dataset, KittiDrive):
        cam = f"image_0{dataset.camera}"
        subs = (cam, f"{cam}/data", "velodyne_points", "velodyne_points/data")
        return [dataset.root, *(dataset.root / sub for sub in subs)], [dataset.image_path(i) for i in
                                                                       range(len(dataset))]
    subs = ("image", "velodyne_raw", "intrinsics", "groundtruth_depth")
    return [dataset.root, *(dataset.root / sub for sub in subs)], [dataset.sparse_path(i) for i in
                                                                   range(len(dataset))]


def check_folder_run(options: FolderRun) -> None:
    """What :func:`complete_folder` checks before it reads a frame, without writing anything: the folder opened
    (its layout, at least one frame, ``--camera``) and the output folders (not among the inputs, writable, not
    locked). ``--input-list`` checks every line so before it completes any."""
    dataset = _open_folder(options.input_dir, options.camera)
    inputs, _ = _inputs(dataset)
    check_output_folders(options.out_dir, options.out_std_dir, options.vis, inputs,
                         f"an input folder of {dataset.root}")


def _other_pngs(out_dir: Path, names: list[str]) -> int:
    """PNG files in ``out_dir`` that this run does not write (an earlier run's, on other frames)."""
    mine = {f"{name}.png" for name in names}
    return sum(1 for entry in os.scandir(out_dir) if entry.name.endswith(".png") and entry.name not in mine)


def complete_folder(options: FolderRun, ranks: Ranks | None = None) -> int:
    """Complete the folder ``options.input_dir`` (module docstring) and return the exit status (0; a group of ranks
    started here: theirs). ``ranks``: the group the caller has joined (``--input-list`` joins it once for the whole
    list), else the run is spread here as ``options.spread`` says (:mod:`crfdepth.runs.ranks`): alone, with
    ``--devices`` local processes, or as one rank of a group.

    Bad input raises InputError / FileNotFoundError / PermissionError naming the flag, before anything is
    written; an output that cannot be written, a failure that only the model reveals or Ctrl-C stops the run
    midway, saying how many frames were written (they stay)."""
    if ranks is None and launches_ranks(options.spread):
        return launch_ranks(options.spread.argv, options.spread.devices)
    built: dict = {}
    start = time.perf_counter()
    with contextlib.ExitStack() as group:  # left after the report, as the ranks end together (Ranks.close)
        if ranks is None:
            ranks = group.enter_context(joined_group(options.spread))  # None: this process alone
        main = ranks is None or ranks.is_main
        with contextlib.ExitStack() as stack:
            # what decides the files: checked and planned once (rank 0), the folders created and locked there
            run = _prepare(options, stack, built, eager_record=False) if ranks is None else \
                ranks.share(lambda: _prepare(options, stack, built, eager_record=True))
            dataset, plan, folders, with_std = run["dataset"], run["plan"], run["folders"], run["with_std"]
            out_dir = folders[0]
            failed: list[tuple[str, str]] = []
            counts = {"written": 0}
            failing = False
            try:
                if ranks is not None or (options.spread.devices > 1 and plan):
                    if ranks is None:
                        write_run_record(out_dir, run["record"])
                        done = in_processes(options, [(dataset, batches, folders, with_std)
                                                      for batches in deal(plan, options.spread.devices)], complete_share,
                                            devices=options.spread.devices, device=options.device)
                    else:
                        shares = deal(plan, ranks.world)
                        mine = shares[ranks.rank] if ranks.rank < len(shares) else []
                        done = ranks.gather(run_share(f"rank {ranks.rank + 1}/{ranks.world}", options, complete_share,
                                                      (dataset, mine, folders, with_std), built.get("model")))
                    counts["written"] = sum(partial.get("written", 0) for partial, _ in done)
                    failed[:] = [row for partial, _ in done for row in partial.get("failed", [])]
                    stopped = [stop for _, stop in done if stop is not None]
                    if stopped:
                        raise _stopped(stopped, counts["written"], sum(map(len, plan)), out_dir)
                elif plan:
                    complete_frames(options, built["model"], dataset, plan, folders, with_std, failed, counts,
                                    lambda: write_run_record(out_dir, run["record"]))
            except BaseException:
                failing = True
                raise
            finally:  # also when a run stops after writing frames: the failed ones are listed for --resume (a run
                # stopped before its first frame leaves nothing: its error names the frame)
                failed_csv = _close_run(options, run, out_dir, failed, counts["written"], failing) if main else None
            if main and not failed and (plan or (options.resume and run["earlier_record"] is not None)):
                finish_run_record(out_dir, run["record"])  # a run that wrote nothing leaves the record it found
        if main and not options.quiet and options.report is not None:
            options.report(FolderResult(counts["written"], folders, run["total"], run["finished"], run["good"],
                                        run["skipped"], run["skipped_csv"], failed, failed_csv, sum(map(len, plan)),
                                        time.perf_counter() - start))
    return 0


def _close_run(options: FolderRun, run: dict, out_dir: Path, failed: list[tuple[str, str]], written: int,
               stopped: bool) -> Path | None:
    """``failed.csv`` of a run that wrote frames (or ran with ``--skip-bad``), for ``--resume``; returns it. A run
    ``stopped`` by an error or Ctrl-C before its first frame was written leaves nothing of its own: no
    ``failed.csv``, no ``skipped.csv`` and no run record that it wrote (the record of an earlier run, stopped or
    finished, is put back as it was, for ``--resume``: a group of ranks writes its record before the first
    frame), so that the output folders it created are empty and removed
    (:func:`~crfdepth.runs.outputs.output_folders`). When the run is stopped by an error, a file that cannot be
    written now (a full disk) does not hide it."""
    try:
        if stopped and not written:
            restore_run_record(out_dir, run["earlier_record"])
            if run["skipped_csv"] is not None:
                run["skipped_csv"].unlink(missing_ok=True)
            return None
        return write_failed(out_dir, failed if written or options.skip_bad else [])
    except OSError:
        if not stopped:
            raise
        return None


def _prepare(options: FolderRun, stack: contextlib.ExitStack, built: dict, eager_record: bool) -> dict:
    """The folder opened and checked, the model built (kept in ``built``), the frames checked and the batches
    planned (``--resume``, ``--skip-bad``), the output folders created and locked (on ``stack``) and
    ``skipped.csv`` written; with ``eager_record``, the run's record too. Returns what the ranks share."""
    dataset = _open_folder(options.input_dir, options.camera)
    inputs, size_files = _inputs(dataset)
    targets = check_output_folders(options.out_dir, options.out_std_dir, options.vis, inputs,
                                   f"an input folder of {dataset.root}")
    model = built["model"] = options.make_model(options.quiet)
    total = len(dataset)
    with_std = options.out_std_dir is not None or options.vis is not None
    record = run_record(model, with_std, device=options.device, batch_size=options.batch_size,
                        vis=options.vis is not None, vis_range=options.vis_range)
    if isinstance(dataset, KittiDrive):
        record["camera"] = dataset.camera  # decides the files as the model does
    finished = _finished(dataset, targets, record, with_std) if options.resume else set()
    todo = [i for i in range(total) if i not in finished]
    bad = find_bad_frames(dataset, options, todo)
    skipped = skipped_frames(bad, len(todo), f"--input-dir {options.input_dir}", options.skip_bad)
    good = [i for i in range(total) if i not in skipped]
    # the uninterrupted run's batches; a resumed run redoes each one holding an unfinished frame, whole
    plan = [[good[k] for k in batch] for batch in batch_plan([size_files[i] for i in good], options.batch_size)
            if any(good[k] not in finished for k in batch)]
    created = stack.enter_context(output_folders(targets))
    folders = (created[0], created[1], created[2] if options.vis is not None else None)
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


def _finished(dataset, targets, record: dict, with_std: bool) -> set[int]:
    """``--resume``: the frames whose outputs an earlier run of this model and options left complete."""
    folders = dict(targets)
    out_dir = Path(folders["--out-dir"])
    if not out_dir.is_dir():
        return set()
    std_dir = Path(folders["--out-std-dir"]) if folders.get("--out-std-dir") else None
    vis_dir = Path(folders["--vis"]) if folders.get("--vis") is not None else None
    check_resumable(out_dir, record)
    return finished_frames(dataset.names, out_dir, std_dir, vis_dir, with_std)


def _stopped(stopped: list[tuple[str, bool]], written: int, planned: int, out_dir: Path) -> BaseException:
    """The error of a run whose processes stopped early (``stopped``: (message, interrupted) of each):
    KeyboardInterrupt when one was interrupted, else an InputError; the other processes' frames stay written."""
    note = f"{written} of {planned} frame(s) written to {out_dir}; --resume completes the others"
    if any(interrupted for _, interrupted in stopped):
        return KeyboardInterrupt(f"after {note}")
    return InputError(f"{stopped[0][0]} [{len(stopped)} process(es) stopped; {note}]")
