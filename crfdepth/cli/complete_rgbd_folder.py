"""``crfdepth complete --input-dir`` on a folder of RGB-D pairs: every depth image's holes filled, its measured
pixels kept (:mod:`crfdepth.cli.complete_rgbd` tells the frame, its units and files; docs/rgbd.md).

The folder holds the pairs in one of :data:`~crfdepth.cli.complete_rgbd.RGBD_LAYOUTS`: NYU Depth v2's
``rgb_XXXXX.jpg`` + ``sync_depth_XXXXX.png`` (one scene folder: a folder of scene folders is refused, naming
them), or ``image/<stem>.png|jpg`` + ``depth/<stem>.png``. Each frame is written as ``<out-dir>/<depth file's
stem>.png`` (``sync_depth_00000.png``, ``<stem>.png``), its std as ``<out-std-dir>/<stem>.png`` and its pictures
as ``<vis>/<stem>_vis_depth.png`` / ``_vis_std.png``, so that the output folder reads as the input's depth.

As the LiDAR folder mode (:mod:`crfdepth.runs.folder`) does, with its pieces: the output folders are checked
(not among the inputs, writable, not locked) and the model built before any frame is read; then every frame is
read and checked (image and depth readable, the depth in ``--depth-units``, the same size, a camera for the
size); a bad frame makes the run write nothing and exit 2, naming each bad frame, unless ``--skip-bad``
(``<out-dir>/skipped.csv``, :mod:`crfdepth.runs.skip_bad`). The folders are then created and locked
(:func:`crfdepth.runs.outputs.output_folders`), and each frame's files written together through temporary files
(:func:`crfdepth.runs.outputs.write_files`). A run stopped midway (Ctrl-C, a failure only the model reveals, a
full disk) keeps the frames written and says how many; ``--resume`` completes the others
(:mod:`crfdepth.runs.resume`: the run record also holds the depth unit, which decides the bytes). The frames are
completed one at a time in this process: ``--batch-size``, ``--workers``, ``--devices``, ``--num-nodes`` and
``--strategy`` apply to LiDAR folders and are refused here, as is ``--input-list``.
"""

from __future__ import annotations

import argparse
import logging
import os
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from crfdepth.cli.complete_folder import summary
from crfdepth.cli.complete_rgbd import Camera, complete_holes, frame_files
from crfdepth.cli.completion import cli_advice
from crfdepth.cli.decoder_noise import quiet_decoders
from crfdepth.cli.file_errors import FileError, flagged
from crfdepth.cli.model_options import build_model
from crfdepth.cli.progress import FrameBars
from crfdepth.errors import BAD_INPUT, InputError
from crfdepth.io.depth_image import check_depth_matches_image, read_depth_image
from crfdepth.io.kitti import read_rgb
from crfdepth.memory import MemoryRefusal
from crfdepth.runs.batches import flag_names
from crfdepth.runs.folder import FolderResult
from crfdepth.runs.outputs import check_output_folders, output_folders, write_files
from crfdepth.runs.resume import (
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

__all__ = ["RgbdPair", "complete_rgbd_folder", "rgbd_pairs"]

_IMAGE_SUFFIXES = (".jpg", ".png", ".jpeg")
# Options of the LiDAR folder runs that an RGB-D folder does not take: (flag, attribute, default).
_LIDAR_FOLDER_ONLY = (("--batch-size", "batch_size", 1), ("--workers", "workers", 0), ("--devices", "devices", 1),
                      ("--num-nodes", "num_nodes", 1), ("--strategy", "strategy", "auto"))


@dataclass(frozen=True)
class RgbdPair:
    """One frame of a folder of RGB-D pairs: ``name`` (the depth file's stem, the outputs' name), the ``depth``
    PNG, the colour ``image`` (None: none found, ``expected`` names the file looked for); ``root``: the folder."""

    name: str
    depth: Path
    image: Path | None
    expected: str
    root: Path

    def shown(self, path: Path) -> str:
        """``path`` (a file of the folder) relative to the folder, for messages."""
        return Path(os.path.relpath(path, self.root)).as_posix()


def rgbd_pairs(root: Path, layout: str) -> list[RgbdPair]:
    """The frames of the folder ``root`` in ``layout`` (a key of :data:`~crfdepth.cli.complete_rgbd.RGBD_LAYOUTS`),
    sorted by name: one per depth PNG, with the colour image of the same frame (None where it is missing, a
    bad frame)."""
    pairs = []
    if layout == "nyu_sync":
        for depth in sorted(root.glob("sync_depth_*.png")):
            stem = f"rgb_{depth.stem.removeprefix('sync_depth_')}"
            pairs.append(_pair(root, depth, [root / f"{stem}{suffix}" for suffix in _IMAGE_SUFFIXES]))
    else:
        for depth in sorted((root / "depth").glob("*.png")):
            pairs.append(_pair(root, depth, [root / "image" / f"{depth.stem}{s}" for s in _IMAGE_SUFFIXES]))
    return pairs


def _pair(root: Path, depth: Path, images: list[Path]) -> RgbdPair:
    image = next((path for path in images if path.is_file()), None)
    return RgbdPair(depth.stem, depth, image, Path(os.path.relpath(images[0], root)).as_posix(), root)


def _where(index: int, total: int, name: str) -> str:
    """How the run names a frame: ``frame 2/5 <name>``, as the LiDAR folder mode does."""
    return f"frame {index + 1}/{total} {name}"


def _read_pair(pair: RgbdPair, index: int, total: int, units: str, camera: Camera
               ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The frame's (H, W, 3) uint8 image, (H, W) float32 depth in metres (0 = hole) and (3, 3) intrinsics, read
    and checked; every error names the frame and its file (``frame 2/5 <name> (sync_depth_00001.png): ...``)."""
    where = _where(index, total, pair.name)
    depth_where = f"{where} ({pair.shown(pair.depth)})"
    if pair.image is None:
        raise FileNotFoundError(f"{where}: no colour image for {pair.shown(pair.depth)}: expected {pair.expected} "
                                f"(or .png / .jpeg)")
    image_where = f"{where} ({pair.shown(pair.image)})"
    with flagged(image_where, pair.image, labels=("image",)), quiet_decoders():
        rgb = read_rgb(pair.image)
    with quiet_decoders():  # its errors name depth_where, an OS error included
        depth = read_depth_image(pair.depth, units, argument=depth_where)
    check_depth_matches_image(depth.shape, rgb.shape[:2], depth_argument=depth_where, image_argument=image_where)
    try:
        K = camera.K(rgb.shape[1], rgb.shape[0])
    except InputError as exc:
        raise InputError(f"{where}: {exc}") from None
    return rgb, depth, K


def _check_options(args: argparse.Namespace) -> None:
    """The options an RGB-D folder run takes: ``--out-dir`` needed, no one-frame option, none of
    :data:`_LIDAR_FOLDER_ONLY` other than its default."""
    if args.out_dir is None:
        raise InputError("--input-dir needs --out-dir (the folder for the output PNGs)")
    stray = [flag for flag, value in (("--image", args.image), ("--out", args.out), ("--out-std", args.out_std))
             if value is not None]
    if stray:
        raise InputError(f"{', '.join(stray)}: one-frame options cannot be combined with --input-dir")
    lidar = [f"{flag} {getattr(args, name)}" for flag, name, default in _LIDAR_FOLDER_ONLY
             if getattr(args, name) != default]
    if lidar:
        raise InputError(f"{', '.join(lidar)}: appl{'ies' if len(lidar) == 1 else 'y'} to LiDAR folders; a folder of "
                         f"RGB-D pairs is completed one frame at a time in this process")


def complete_rgbd_folder(args: argparse.Namespace, layout: str) -> int:
    """Fill the holes of every frame of ``--input-dir`` (module docstring); returns 0.

    Bad input raises InputError / FileNotFoundError / PermissionError naming the flag or the frame and file,
    before anything is written; a run stopped midway says how many frames it wrote (they stay)."""
    _check_options(args)
    start = time.perf_counter()
    root = Path(args.input_dir)
    with flagged("--input-dir", args.input_dir):
        pairs = rgbd_pairs(root, layout)
    if not pairs:
        raise InputError(f"--input-dir {args.input_dir}: no depth image in it (expected {layout} pairs)")
    units = args.depth_units or "mm"
    camera = Camera.from_args(args)
    inputs = [root, *((root / "image", root / "depth") if layout == "image_depth" else ())]
    targets = check_output_folders(args.out_dir, args.out_std_dir, args.vis, inputs, f"the input folder {root}")
    model = build_model(args, registered_depth=True)
    with_std = args.out_std_dir is not None or args.vis is not None
    record = run_record(model, with_std, device=args.device, batch_size=1, vis=args.vis is not None,
                        vis_range=args.vis_range)
    record.update(input="rgbd", depth_units=units)  # the unit decides the PNGs' bytes
    names = [pair.name for pair in pairs]
    total = len(pairs)
    finished = _finished(targets, names, record, with_std) if args.resume else set()
    todo = [i for i in range(total) if i not in finished]
    bad = _bad_frames(args, pairs, todo, units, camera)
    skipped = skipped_frames(bad, len(todo), f"--input-dir {args.input_dir}", args.skip_bad)
    good = [i for i in range(total) if i not in skipped]
    plan = [i for i in good if i not in finished]
    with output_folders(targets) as created:
        folders = (created[0], created[1], created[2] if args.vis is not None else None)
        out_dir = folders[0]
        mine = {f"{name}.png" for name in names}
        others = sum(1 for entry in os.scandir(out_dir) if entry.name.endswith(".png") and entry.name not in mine)
        if others:
            logger.warning("--out-dir %s already holds %d PNG file(s) that this run does not write (an earlier "
                           "run on other frames?); they stay", out_dir, others)
        skipped_csv = write_skipped(out_dir, [(names[i], message) for i, message in skipped.items()])
        earlier = earlier_run_record(out_dir)
        failed: list[tuple[str, str]] = []
        counts = {"written": 0}
        stopped = False
        try:
            _complete_pairs(args, model, pairs, plan, units, camera, folders, with_std, record, failed, counts)
        except BaseException:
            stopped = True
            raise
        finally:
            failed_csv = _close_run(args, out_dir, earlier, skipped_csv, failed, counts["written"], stopped)
        if not failed and (plan or (args.resume and earlier is not None)):
            finish_run_record(out_dir, record)
    if not args.quiet:
        summary(FolderResult(counts["written"], folders, total, finished, good, skipped, skipped_csv, failed,
                             failed_csv, len(plan), time.perf_counter() - start))
    return 0


def _finished(targets: list[tuple[str, str | None]], names: list[str], record: dict, with_std: bool) -> set[int]:
    """``--resume``: the frames whose outputs an earlier run of this model and options left complete."""
    folders = dict(targets)
    out_dir = Path(folders["--out-dir"])
    if not out_dir.is_dir():
        return set()
    std_dir = Path(folders["--out-std-dir"]) if folders.get("--out-std-dir") else None
    vis_dir = Path(folders["--vis"]) if folders.get("--vis") is not None else None
    check_resumable(out_dir, record)
    return finished_frames(names, out_dir, std_dir, vis_dir, with_std)


def _bad_frames(args: argparse.Namespace, pairs: list[RgbdPair], todo: list[int], units: str, camera: Camera
                ) -> list[tuple[int, type[BaseException], str]]:
    """The check pass: frames ``todo`` read and checked; (index, error type, message) of the bad ones."""
    bad = []
    progress = FrameBars()("check", len(todo)) if not args.quiet else None
    try:
        for index in todo:
            try:
                _read_pair(pairs[index], index, len(pairs), units, camera)
            except BAD_INPUT as exc:
                where = _where(index, len(pairs), pairs[index].name)
                message = str(exc)
                bad.append((index, type(exc), message if message.startswith(where) else f"{where}: {message}"))
            if progress is not None:
                progress.update(1)
    except KeyboardInterrupt:
        raise KeyboardInterrupt("while checking the frames; nothing written") from None
    finally:
        if progress is not None:
            progress.close()
    return bad


def _complete_pairs(args: argparse.Namespace, model, pairs: list[RgbdPair], plan: list[int], units: str,
                    camera: Camera, folders: tuple, with_std: bool, record: dict, failed: list[tuple[str, str]],
                    counts: dict) -> None:
    """The frames ``plan`` read again, completed and written one by one, each counted in ``counts["written"]``
    once its files are in place; a frame that fails now is listed in ``failed`` and stops the run (with
    ``--skip-bad``: the run goes on), an output that cannot be written or Ctrl-C stops it."""
    out_dir, std_dir, vis_dir = folders
    total = len(pairs)
    progress = FrameBars()("complete", len(plan)) if not args.quiet else None
    where, name = "", ""
    try:
        for index in plan:
            pair = pairs[index]
            where, name = _where(index, total, pair.name), pair.name
            try:
                rgb, depth, K = _read_pair(pair, index, total, units, camera)
                try:
                    filled, std = complete_holes(model, rgb, depth, K, device=args.device, return_std=with_std)
                except MemoryRefusal as exc:
                    raise exc.retold(f"{where} ({pair.shown(pair.image)})", cli_advice(args.device, 1)) from None
                except InputError as exc:
                    raise flag_names(exc, {"image": f"{where} ({pair.shown(pair.image)})",
                                           "sparse": f"{where} ({pair.shown(pair.depth)})",
                                           "K": f"{where} ({camera.flag})"}) from None
                files = frame_files(filled, std, units, out_dir / f"{pair.name}.png",
                                    std_dir / f"{pair.name}.png" if std_dir else None, vis_dir, pair.name,
                                    args.vis_range, ("--out-dir", "--out-std-dir", "--vis"))
                if not counts["written"]:
                    write_run_record(out_dir, record)  # before the first file: --resume reads it
                write_files(files)  # the frame's files: all of them or none
            except BAD_INPUT as exc:
                if not args.skip_bad:
                    raise
                failed.append((name, f"{where}: {exc}" if not str(exc).startswith(where) else str(exc)))
                continue
            counts["written"] += 1
            if args.recorder is not None:  # --rerun
                args.recorder.complete_frame(rgb, filled, std, sparse=depth, K=K)
            if progress is not None:
                progress.update(1)
    except (*BAD_INPUT, FileError) as exc:  # FileError: an output that cannot be written stops even --skip-bad
        failed.append((name, str(exc)))
        raise type(exc)(f"{exc} [stopped at {where}; {counts['written']} of {len(plan)} frame(s) written to "
                        f"{out_dir}; --resume completes the others]") from None
    except KeyboardInterrupt:
        raise KeyboardInterrupt(f"after {counts['written']} of {len(plan)} frame(s) written to {out_dir}; "
                                f"--resume completes the others") from None
    finally:
        if progress is not None:
            progress.close()


def _close_run(args: argparse.Namespace, out_dir: Path, earlier: bytes | None, skipped_csv: Path | None,
               failed: list[tuple[str, str]], written: int, stopped: bool) -> Path | None:
    """``failed.csv`` of a run that wrote frames (or ran with ``--skip-bad``); a run stopped before its first
    frame leaves nothing of its own (as :mod:`crfdepth.runs.folder` does), so that the folders it created are
    removed empty. Returns ``failed.csv`` or None."""
    try:
        if stopped and not written:
            restore_run_record(out_dir, earlier)
            if skipped_csv is not None:
                skipped_csv.unlink(missing_ok=True)
            return None
        return write_failed(out_dir, failed if written or args.skip_bad else [])
    except OSError:
        if not stopped:
            raise
        return None
