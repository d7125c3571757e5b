"""The two passes of a folder run over its frames (:mod:`crfdepth.runs.folder`): every frame read and checked
(pass 1, :func:`find_bad_frames`), then the planned batches completed and written (pass 2,
:func:`complete_frames`).

Messages name each frame as ``frame 2/5 <name>`` and, for a check, the frame's file
(``frame 2/5 <name> (velodyne_raw/<name>.png): ...``); a batch too large for the memory is refused with the
caller's advice (``FolderRun.memory_advice``).
"""

from __future__ import annotations

import functools
import itertools
from pathlib import Path

from torch.utils.data import Subset

from crfdepth.api import complete_checked
from crfdepth.data.kitti import KittiDrive
from crfdepth.errors import BAD_INPUT, InputError
from crfdepth.io.file_errors import FileError
from crfdepth.memory import MemoryRefusal
from crfdepth.runs.batches import bad_frames, check_sample, flag_names, frame_batches
from crfdepth.runs.outputs import write_frame
from crfdepth.runs.progress import bar

__all__ = ["FOLDER_FLAGS", "complete_frames", "complete_share", "find_bad_frames"]

# What names a frame's depth PNG, std PNG and pictures in a write error (crfdepth.runs.outputs.write_frame).
FOLDER_FLAGS = ("--out-dir", "--out-std-dir", "--vis")


def _where(index: int, total: int, name: str) -> str:
    """How folder mode names a frame: ``frame 2/5 <name>``."""
    return f"frame {index + 1}/{total} {name}"


_SELECTION_FILES = {"K": "intrinsics/", "sparse": "velodyne_raw/{name}.png", "image": "image/"}


def _check_frame(sample, index: int, *, total: int, positions: list[int] | None = None,
                 files: dict[str, str] = _SELECTION_FILES) -> None:
    """:func:`~crfdepth.runs.batches.check_sample` in the DataLoader workers, naming the frame's files
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


def find_bad_frames(dataset, run, positions: list[int]) -> list[tuple[int, type[BaseException], str]]:
    """Pass 1 of folder mode: frames ``positions`` of the folder ``dataset`` read and checked
    (:func:`~crfdepth.runs.batches.bad_frames`, ``run.workers`` processes; ``run``: the
    :class:`~crfdepth.runs.folder.FolderRun`); each message names its frame (``frame 3/6 <name>: ...``; a check
    names the file too). Returns (folder index, error, message) of the bad ones."""
    total = len(dataset)
    progress = bar(run, "check", len(positions))
    checked = []

    def step(index: int) -> None:
        checked.append(index)
        progress.update(1)

    frames = dataset if len(positions) == total else Subset(dataset, positions)
    try:
        check = functools.partial(_check_frame, total=total, positions=positions, files=_frame_files(dataset))
        bad = bad_frames(frames, run.workers, check, step)
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


def complete_share(run, model, share: tuple, partial: dict) -> None:
    """One process's part of a ``--devices`` run (:func:`crfdepth.runs.processes.in_processes`): its batches of
    the folder completed and written; ``partial`` counts them (``written``) and lists the ``failed`` frames."""
    dataset, batches, folders, with_std = share
    partial["written"] = 0
    if batches:
        complete_frames(run, model, dataset, batches, folders, with_std, partial.setdefault("failed", []), partial)


def complete_frames(run, model, dataset, plan: list[list[int]], folders: tuple, with_std: bool,
                    failed: list[tuple[str, str]], counts: dict, first_write=None) -> int:
    """Pass 2 of folder mode: complete and write the frames of ``plan`` (batches of indices into the folder
    ``dataset``), each batch as planned (a batch also ends at a size change), each frame checked again as it is
    read (:func:`_check_frame`); returns the number written, counted in ``counts["written"]`` as each frame's
    files are in place. ``run`` is the :class:`~crfdepth.runs.folder.FolderRun`; ``first_write()`` runs before
    the first file is written.

    A failure now (the frame changed since pass 1, a non-finite model output, a batch too large for the
    memory) is added to ``failed`` (name, reason) for each frame of its batch; with ``--skip-bad`` the
    run goes on, without it the run stops saying how many frames were written, as Ctrl-C does."""
    positions = [i for batch in plan for i in batch]
    starts = set(itertools.accumulate(len(batch) for batch in plan[:-1]))
    names, total = [dataset.names[i] for i in positions], len(dataset)
    check = functools.partial(_check_frame, total=total, positions=positions, files=_frame_files(dataset))
    progress = bar(run, "complete", len(names))
    batches = frame_batches(Subset(dataset, positions), run.batch_size, run.workers, check, starts)
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
                try:  # the frames were checked as they were read (check), so the API checks nothing again
                    depth, std = complete_checked(model, batch.image, batch.sparse, batch.K, return_std=with_std)
                except MemoryRefusal as exc:
                    raise exc.retold("image", run.memory_advice(len(batch))) if run.memory_advice else exc from None
                _write_batch(run, batch, depth, std, folders, first_write if not counts["written"] else None,
                             counts, unwritten)
            except BAD_INPUT as exc:
                if not run.skip_bad:
                    raise
                failed.extend((name, f"{where}: {exc}") for name in unwritten)
            done += len(batch)
            progress.update(len(batch))
            if done < len(names):
                where, unwritten = _where(positions[done], total, names[done]), names[done:done + 1]
    except (*BAD_INPUT, FileError) as exc:  # FileError: an output that cannot be written stops even --skip-bad
        failed.extend((name, f"{where}: {exc}") for name in unwritten)
        raise type(exc)(f"{exc} [stopped at {where}; {counts['written']} of {len(names)} frame(s) written to "
                        f"{folders[0]}; --resume completes the others]") from None
    except KeyboardInterrupt:
        raise KeyboardInterrupt(f"after {counts['written']} of {len(names)} frame(s) written to {folders[0]}; "
                                f"--resume completes the others") from None
    finally:
        batches.close()  # stops the DataLoader workers
        progress.close()
    return counts["written"]


def _write_batch(run, batch, depth, std, folders: tuple[Path, Path | None, Path | None], first_write, counts: dict,
                 unwritten: list[str]) -> None:
    """Write one completed batch ((B, H, W) float32 ``depth`` and ``std`` in metres, std None when not asked), each
    frame counted in ``counts["written"]`` and taken off ``unwritten`` as soon as its files are in place (a failure
    on a later frame of the batch leaves the earlier ones written)."""
    out_dir, std_dir, vis_dir = folders
    depth = depth.cpu().numpy()  # float32, as the one-frame mode writes it
    std = std.cpu().numpy() if std is not None else [None] * len(batch)
    if first_write is not None:
        first_write()
    for k, name in enumerate(batch.names):
        write_frame(depth[k], std[k], out_dir / f"{name}.png", std_dir / f"{name}.png" if std_dir else None,
                    vis_dir, name, run.vis_range, FOLDER_FLAGS)  # the frame's files: all of them or none
        counts["written"] += 1
        unwritten.remove(name)
        if run.recorder is not None:  # --rerun
            run.recorder.complete_frame(batch.image[k], depth[k], std[k], sparse=batch.sparse[k], K=batch.K[k])
