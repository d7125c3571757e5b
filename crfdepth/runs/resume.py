"""Resuming a run over a folder (``complete --input-dir --resume``): what an earlier run into the same folders already finished, and the
batches of a run planned so that a resumed run writes the same files as an uninterrupted one.

- :func:`finished_frames`: the frames whose every output (depth PNG, std PNG, pictures, as this run
  would write them) exists. Each file is written atomically (:mod:`crfdepth.io.files`), so one that
  exists is whole; a frame cut short has some of its files and is done again.
- :func:`run_record` / :func:`check_resumable` / :func:`write_run_record`: ``<out-dir>/.crfdepth-run.json``,
  what decides the files' bytes (the model's configuration and a digest of its weights, the dtype, the
  device type, the batch size, the std and the pictures asked for), written before a run's first file and
  marked ``"finished": true`` when the run has written every frame (a hidden file: ``zip *.png`` of the
  folder, a KITTI submission, leaves it out). A resumed run that would write other bytes than the run
  before it, stopped or finished, is refused, naming what differs; a folder without the record was
  written by hand (or by a version before the record), and its outputs are taken as they are.
- :func:`batch_plan`: the batches of the uninterrupted run (consecutive frames of one size, up to
  ``--batch-size``: :func:`crfdepth.runs.batches.frame_batches`' rule, the size read from each PNG's
  header). A resumed run redoes every batch that holds an unfinished frame, whole, so each frame is
  solved in the batch it would have had: CG iterations of a batch run together, and a frame's depth
  depends on its batch within the solver tolerance (docs/design.md section 10).
"""

from __future__ import annotations

import hashlib
import json
from pathlib import Path

import torch

from crfdepth.errors import InputError
from crfdepth.io.image_size import read_image_size
from crfdepth.runs.outputs import write_files

__all__ = ["RUN_RECORD", "batch_plan", "check_resumable", "earlier_run_record", "finish_run_record", "finished_frames",
           "restore_run_record", "run_record", "write_run_record"]

RUN_RECORD = ".crfdepth-run.json"
FINISHED = "finished"  # the record's mark of a run that wrote every frame


def frame_outputs(name: str, out_dir: Path, std_dir: Path | None, vis_dir: Path | None, with_std: bool
                  ) -> list[Path]:
    """The files a run writes for frame ``name`` (:func:`crfdepth.runs.outputs.write_frame`)."""
    paths = [out_dir / f"{name}.png"]
    if std_dir is not None:
        paths.append(std_dir / f"{name}.png")
    if vis_dir is not None:
        paths.append(vis_dir / f"{name}_vis_depth.png")
        if with_std:
            paths.append(vis_dir / f"{name}_vis_std.png")
    return paths


def finished_frames(names: list[str], out_dir: Path, std_dir: Path | None, vis_dir: Path | None,
                    with_std: bool) -> set[int]:
    """Indices of ``names`` whose every output exists."""
    return {i for i, name in enumerate(names)
            if all(p.is_file() for p in frame_outputs(name, out_dir, std_dir, vis_dir, with_std))}


def run_record(model, with_std: bool, *, device: str, batch_size: int, vis: bool,
               vis_range: tuple[float, float] | None) -> dict:
    """What decides the bytes of a run's files: the model (configuration and SHA-256 of its weights), the
    dtype and ``device`` type it runs in, the ``batch_size``, and the outputs asked for (the std, pictures
    (``vis``) and their fixed depth range in metres, ``vis_range``)."""
    digest = hashlib.sha256()
    for key, tensor in sorted(model.state_dict().items()):
        digest.update(key.encode())
        digest.update(tensor.detach().cpu().contiguous().numpy().tobytes())
    param = next(model.parameters())
    return {"model": json.loads(json.dumps(model.config)), "weights_sha256": digest.hexdigest(),
            "dtype": str(param.dtype).removeprefix("torch."), "device": torch.device(device).type,
            "batch_size": batch_size, "std": with_std, "vis": vis,
            "vis_range": list(vis_range) if vis_range is not None else None}


def check_resumable(out_dir: Path, record: dict) -> None:
    """Refuse ``--resume`` into ``out_dir`` when the run that wrote it, stopped or finished, would write other
    bytes than this one (its record differs from ``record``)."""
    path = out_dir / RUN_RECORD
    if not path.is_file():
        return
    try:
        earlier = json.loads(path.read_text())
    except (OSError, ValueError) as exc:
        raise InputError(f"--resume: cannot read {path} ({exc}); remove it to write every frame again") from None
    if not isinstance(earlier, dict):
        raise InputError(f"--resume: cannot read {path} (not a run record); remove it to write every frame again")
    finished = earlier.pop(FINISHED, False) is True
    differ = sorted(key for key in record.keys() | earlier.keys() if record.get(key) != earlier.get(key))
    if differ:
        what = ", ".join(f"{key} {earlier.get(key)!r} -> {record.get(key)!r}" if key != "model" else "model"
                         for key in differ)
        run = "finished" if finished else "unfinished"
        raise InputError(f"--resume: {out_dir} holds the {run} run of another model or options ({what}; "
                         f"{path}); resume with its options, or complete into another --out-dir")


def write_run_record(out_dir: Path, record: dict) -> None:
    """``<out-dir>/.crfdepth-run.json``, written atomically (errors name ``--out-dir``)."""
    write_files([("--out-dir", out_dir / RUN_RECORD, (json.dumps(record, indent=1, sort_keys=True) + "\n").encode())])


def earlier_run_record(out_dir: Path) -> bytes | None:
    """The record in ``out_dir`` before this run writes its own, as it is on disk (None: there is none; ``b""``:
    there is one that cannot be read), so that a run that writes no frame can put it back
    (:func:`restore_run_record`)."""
    try:
        return (out_dir / RUN_RECORD).read_bytes()
    except FileNotFoundError:
        return None
    except OSError:
        return b""


def restore_run_record(out_dir: Path, earlier: bytes | None) -> None:
    """The run wrote no frame: the folder's record is put back as :func:`earlier_run_record` found it (none, or
    the earlier run's, whose outputs the folder still holds; one that could not be read is left as it is)."""
    path = out_dir / RUN_RECORD
    if earlier is None:
        path.unlink(missing_ok=True)
    elif earlier and (not path.is_file() or path.read_bytes() != earlier):
        write_files([("--out-dir", path, earlier)])


def finish_run_record(out_dir: Path, record: dict) -> None:
    """The run has written every frame: its record says so (``"finished": true``), and a later ``--resume`` with
    other options is refused. A record that says so already is left untouched."""
    finished = {**record, FINISHED: True}
    try:
        if json.loads((out_dir / RUN_RECORD).read_text()) == finished:
            return
    except (OSError, ValueError):
        pass
    write_run_record(out_dir, finished)


def batch_plan(sparse_files: list[Path], batch_size: int) -> list[list[int]]:
    """The batches (lists of indices into ``sparse_files``) of consecutive frames of one size, up to
    ``batch_size`` each; a frame whose PNG header does not parse starts and ends a batch of its own (the
    reader says why when it is read)."""
    batches: list[list[int]] = []
    size = None
    for index, path in enumerate(sparse_files):
        here = read_image_size(path)
        if not batches or here is None or here != size or len(batches[-1]) == batch_size:
            batches.append([])
        batches[-1].append(index)
        size = here if here is not None else object()
    return batches
