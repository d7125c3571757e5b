"""Evaluating a model over a data set (``crfdepth evaluate``): each batch completed, scored against its ground
truth (per-frame KITTI metrics, docs/design.md section 7; with ``std`` the uncertainty metrics, section 5), and
with a PNG folder written; alone, in ``--devices`` processes or as ranks of a group (:mod:`crfdepth.runs.ranks`).
The run is a typed :class:`EvaluationRun`; ``crfdepth.cli.evaluate`` builds it from its flags."""

from __future__ import annotations

import itertools
import logging
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch.utils.data import Subset

from crfdepth.api import complete_checked
from crfdepth.errors import BAD_INPUT, InputError
from crfdepth.memory import MemoryRefusal
from crfdepth.metrics import METRICS, depth_metrics, uncertainty_metrics
from crfdepth.runs.batches import frame_batches
from crfdepth.runs.outputs import write_depth_png
from crfdepth.runs.processes import deal, in_processes, run_share
from crfdepth.runs.progress import bar
from crfdepth.runs.ranks import Spread

logger = logging.getLogger("crfdepth.cli.evaluate")  # the command's logger

__all__ = ["EvaluationRun", "evaluate_dataset", "evaluate_frames", "evaluate_in_processes", "evaluate_share", "frame_chunks",
           "merge_shares"]


@dataclass(frozen=True)
class EvaluationRun:
    """How a data set is evaluated (picklable: ``--devices`` processes receive it): ``batch_size`` frames per model
    call, ``workers`` DataLoader processes reading ahead, ``std``: the uncertainty metrics too; ``quiet``: no
    progress; ``spread``, ``make_model``, ``memory_advice`` and ``progress`` as for
    :class:`crfdepth.runs.folder.FolderRun`."""

    make_model: Callable
    batch_size: int = 1
    workers: int = 0
    std: bool = False
    quiet: bool = False
    spread: Spread = field(default_factory=Spread)
    memory_advice: Callable[[int], str] | None = None
    progress: Callable | None = None

_MIN_DEPTH = 1.0 / 256.0  # smallest non-zero code of a KITTI depth PNG, metres


def evaluate_frames(model, dataset, run: EvaluationRun, png_dir: Path | None, starts: set[int] | None = None
                    ) -> tuple[list[dict[str, Any]], list[str]]:
    """Per-frame metrics rows (in dataset order) and the names of skipped frames (no ground-truth pixel); with
    ``png_dir``, each depth written there as ``<name>.png``; ``starts``: frames that start a batch besides size
    changes and ``--batch-size`` (:func:`~crfdepth.runs.batches.frame_batches`)."""
    batches = frame_batches(dataset, run.batch_size, run.workers, starts=starts)
    rows: list[dict[str, Any]] = []
    skipped: list[str] = []
    progress = bar(run, "evaluate", len(dataset))
    done = 0
    try:
        with torch.no_grad():
            for batch in _batches(batches, dataset):
                where = f"frame(s) {done + 1}-{done + len(batch)} of {len(dataset)} ({', '.join(batch.names)})"
                if not bool(batch.has_target.all()):
                    missing = [n for n, t in zip(batch.names, batch.has_target.tolist()) if not t]
                    raise InputError(f"{where}: no ground truth for {', '.join(missing)}, so nothing to "
                                     f"evaluate; for benchmark submissions use 'crfdepth complete --input-dir'")
                depth, std = _predict(model, batch, where, run)
                batch = batch.to(device=depth.device, dtype=depth.dtype)
                counts = (batch.target > 0).flatten(1).sum(1)
                keep = counts > 0
                for name in (n for n, k in zip(batch.names, keep.tolist()) if not k):
                    logger.warning("%s has no ground-truth pixel (> 0); skipped", name)
                    skipped.append(name)
                if bool(keep.any()):
                    try:
                        per_frame = depth_metrics(depth[keep], batch.target[keep])
                    except InputError as exc:
                        raise InputError(f"{where}: {exc}") from None
                    frames = [i for i, k in enumerate(keep.tolist()) if k]
                    for j, i in enumerate(frames):
                        row: dict[str, Any] = {"name": batch.names[i]}
                        row.update({m: float(per_frame[m][j]) for m in METRICS})
                        row["pixels"] = int(per_frame["pixels"][j])
                        if std is not None:
                            row.update(_frame_uncertainty(depth[i, 0], std[i, 0], batch.target[i, 0],
                                                          f"{where}, {batch.names[i]}"))
                        rows.append(row)
                if png_dir is not None:
                    _write_pngs(depth, batch.names, png_dir, where)
                done += len(batch)
                progress.update(len(batch))
    finally:
        batches.close()  # stops the DataLoader workers
        progress.close()
    return rows, skipped


def evaluate_in_processes(dataset, run: EvaluationRun, png_dir: Path | None) -> tuple[list[dict[str, Any]], list[str]]:
    """:func:`evaluate_frames` with ``--devices`` processes (:func:`crfdepth.runs.processes.in_processes`): runs of
    ``--batch-size`` consecutive frames dealt to them in turn, each evaluated as one batch (or split where the
    size changes), the rows and skipped frames merged back into input order. Every metric is per frame and
    the report's means are taken over the merged rows, so the CSV and JSON are those of one process."""
    chunks = frame_chunks(len(dataset), run.batch_size)
    shares = [(dataset, batches, png_dir) for batches in deal(chunks, run.spread.devices)]
    return merge_shares(chunks, in_processes(run, shares, evaluate_share, devices=run.spread.devices,
                                             device=run.spread.device))


def evaluate_dataset(model, dataset, run: EvaluationRun, png_dir: Path | None, ranks=None
                     ) -> tuple[list[dict[str, Any]], list[str]]:
    """:func:`evaluate_frames` of ``dataset`` as ``run.spread`` says: here with ``model``, in ``--devices``
    processes (:func:`evaluate_in_processes`), or (``ranks``: the group this process has joined,
    :class:`~crfdepth.runs.ranks.Ranks`) the runs of frames dealt to the ranks in turn, gathered on every rank.
    Returns the rows (in dataset order) and the skipped frames."""
    if ranks is not None:
        chunks = frame_chunks(len(dataset), run.batch_size)
        shares = deal(chunks, ranks.world)
        share = (dataset, shares[ranks.rank] if ranks.rank < len(shares) else [], png_dir)
        return merge_shares(chunks, ranks.gather(run_share(f"rank {ranks.rank + 1}/{ranks.world}", run,
                                                           evaluate_share, share, model)))
    if run.spread.devices > 1:
        return evaluate_in_processes(dataset, run, png_dir)
    return evaluate_frames(model, dataset, run, png_dir)


def frame_chunks(count: int, batch_size: int) -> list[list[int]]:
    """Runs of ``batch_size`` consecutive frames of ``count``, the units dealt to processes and ranks."""
    return [list(range(i, min(i + batch_size, count))) for i in range(0, count, batch_size)]


def merge_shares(chunks: list[list[int]], done: list[tuple[dict, tuple[str, bool] | None]]
                 ) -> tuple[list[dict[str, Any]], list[str]]:
    """The rows and skipped frames the processes (or ranks) reported, in input order; the first stop raised."""
    stopped = [stop for _, stop in done if stop is not None]
    if any(interrupted for _, interrupted in stopped):
        raise KeyboardInterrupt("while evaluating; nothing written")
    if stopped:
        raise InputError(stopped[0][0])
    order = {index: position for position, index in enumerate(i for chunk in chunks for i in chunk)}
    rows = sorted((row for partial, _ in done for row in partial["rows"]), key=lambda row: order[row["index"]])
    skipped = sorted((item for partial, _ in done for item in partial["skipped"]), key=lambda item: order[item[0]])
    return [{k: v for k, v in row.items() if k != "index"} for row in rows], [name for _, name in skipped]


def evaluate_share(run: EvaluationRun, model, share: tuple, partial: dict) -> None:
    """One process's part of :func:`evaluate_in_processes`: its batches of ``dataset`` evaluated; ``partial``
    gets the ``rows`` and ``skipped`` frames, each with its index in ``dataset``."""
    dataset, batches, png_dir = share
    partial.update(rows=[], skipped=[])
    if not batches:
        return
    indices = [i for batch in batches for i in batch]
    starts = set(itertools.accumulate(len(batch) for batch in batches[:-1]))
    rows, skipped = evaluate_frames(model, Subset(dataset, indices), run, png_dir, starts)
    index_of = {name: i for i, name in zip(indices, _names(Subset(dataset, indices)) or [])}
    partial["rows"] = [{**row, "index": index_of[row["name"]]} for row in rows]
    partial["skipped"] = [(index_of[name], name) for name in skipped]


def _predict(model, batch, where: str, run: EvaluationRun) -> tuple[torch.Tensor, torch.Tensor | None]:
    """(B, 1, H, W) depth of a batch and, with ``run.std``, its (B, 1, H, W) std in metres
    (else None), in the model's dtype: one model call for the batch
    (:func:`crfdepth.api.complete_checked`, the batched ``complete_depth``, on frames the workers checked);
    a memory refusal advises ``run.memory_advice``."""
    return_std = run.std
    try:
        try:
            depth, std = complete_checked(model, batch.image, batch.sparse, batch.K, return_std=return_std)
        except MemoryRefusal as exc:
            raise exc.retold("image", run.memory_advice(len(batch))) if run.memory_advice else exc from None
    except InputError as exc:
        raise InputError(f"{where}: {exc}") from None
    if return_std and std is None:
        raise InputError(f"--std: expected the model to return a standard deviation, got none for {where}")
    dtype = next(model.parameters()).dtype
    return depth[:, None].to(dtype), (std[:, None].to(dtype) if return_std else None)


def _frame_uncertainty(depth: torch.Tensor, std: torch.Tensor, target: torch.Tensor, where: str) -> dict[str, float]:
    """:func:`crfdepth.metrics.uncertainty_metrics` of one (H, W) frame over its ground-truth
    pixels (target > 0), errors and std in metres; ``ause`` and ``ause_random`` in mm."""
    valid = target > 0
    error = (depth.double() - target.double())[valid].cpu().numpy()
    try:
        metrics = uncertainty_metrics(error, std.double()[valid].cpu().numpy())
    except InputError as exc:
        raise InputError(f"{where}: --std: {exc}") from None
    metrics["ause"] *= 1000.0  # linear in the unit of the errors and std; the ratio is unitless
    metrics["ause_random"] *= 1000.0
    return metrics


def _batches(batches, dataset):
    """The batches of :func:`~crfdepth.runs.batches.frame_batches`; a frame that fails to read
    or check (in a worker or here) is named in its one-line error."""
    total, names, done = len(dataset), _names(dataset), 0
    while True:
        try:
            batch = next(batches, None)
        except BAD_INPUT as exc:
            name = f" ({names[done]})" if names is not None else ""
            raise type(exc)(f"frame {done + 1} of {total}{name}: {exc}") from None
        if batch is None:
            return
        done += len(batch)
        yield batch


def _names(dataset) -> list[str] | None:
    """The frame names of ``dataset`` (a ``Subset`` for ``--limit`` included), if it has them."""
    if isinstance(dataset, Subset):
        names = _names(dataset.dataset)
        return None if names is None else [names[i] for i in dataset.indices]
    return getattr(dataset, "names", None)


def _write_pngs(depth: torch.Tensor, names: list[str], png_dir: Path, where: str) -> None:
    for name, frame in zip(names, depth[:, 0].double().cpu().numpy()):
        if not np.all(np.isfinite(frame)):
            raise InputError(f"{where}: the model returned {int(np.sum(~np.isfinite(frame)))} non-finite "
                             f"depth value(s) for {name}; PNG not written")
        write_depth_png(png_dir / f"{name}.png", np.maximum(frame, _MIN_DEPTH), "--out-dir")
