"""Frames read and checked by DataLoader workers, then batched by size (``complete --input-dir``, ``evaluate``).

:func:`add_batch_arguments` registers ``--batch-size`` and ``--workers``; :func:`bad_frames`
is the check pass that keeps nothing; :func:`frame_batches` yields the
:class:`~crfdepth.data.sample.Batch` es that one model call each completes
(:func:`crfdepth.cli.completion.complete_batch_with_cli_advice`).
"""

from __future__ import annotations

import argparse
from collections.abc import Callable, Iterator
from dataclasses import dataclass

from torch.utils.data import DataLoader, Dataset

from crfdepth.cli.arguments import BAD_INPUT, int_at_least
from crfdepth.cli.completion import check_sample
from crfdepth.cli.decoder_noise import quiet_decoders
from crfdepth.data.sample import Batch, Sample, collate_samples

__all__ = ["MAX_WORKERS", "STRATEGIES", "add_batch_arguments", "bad_frames", "frame_batches"]

# More reading processes than this cannot keep up better with a solve that takes seconds per
# frame; the cap turns a typo (--workers 400) into a usage error instead of 400 processes.
MAX_WORKERS = 64
# How --devices processes are started (crfdepth.cli.ranks.run_in_group), named after Lightning's strategies.
STRATEGIES = ("auto", "spawn", "ddp")


def add_batch_arguments(group: argparse._ActionsContainer) -> None:
    """``--batch-size B`` and ``--workers N`` (read by :func:`frame_batches`), and ``--devices N``, ``--num-nodes
    M`` and ``--strategy`` (:mod:`crfdepth.cli.processes`, :mod:`crfdepth.cli.ranks`, :mod:`crfdepth.cli.launch`),
    shared by ``complete --input-dir`` / ``--input-list`` and ``evaluate``."""
    group.add_argument("--batch-size", type=int_at_least(1), default=1, metavar="B",
                       help="frames per model call (default 1, the fastest on CPU as measured; batches are "
                            "meant for --device cuda); consecutive frames of the same size go together, a size "
                            "change starts a new batch. Each frame's solve stops when it has converged, so "
                            "depths differ from batch 1 by the solver tolerance only (measured: at most 1/256 m, "
                            "one unit of a depth PNG)")
    group.add_argument("--workers", type=int_at_least(0, MAX_WORKERS), default=0, metavar="N",
                       help=f"processes that read and check frames ahead of the model (DataLoader "
                            f"num_workers, 0 to {MAX_WORKERS}; default 0: this process, enough for local KITTI "
                            f"frames, which read in about 20 ms; more help when reading is slow, e.g. from "
                            f"network storage)")
    group.add_argument("--devices", type=int_at_least(1), default=1, metavar="N",
                       help="N processes, one per device (--device cuda: GPUs 0..N-1; cpu: N processes sharing the "
                            "cores), the batches dealt to them in turn: the outputs are one process's (depth within "
                            "one PNG code: the threads' summation order)")
    group.add_argument("--num-nodes", type=int_at_least(1), default=1, metavar="M",
                       help="M machines of N --devices each: start the same command on every node with torchrun "
                            "--nnodes M --nproc-per-node N (or srun under torchrun); rank 0 checks, plans and "
                            "reports, every rank does its dealt batches (the output folder shared)")
    group.add_argument("--strategy", choices=STRATEGIES, default="auto",
                       help="how the --devices processes are started, named after Lightning's strategies: auto "
                            "(default) = a rank of the launcher's group when started by torchrun or srun, else "
                            "spawn for --devices N > 1; spawn = N local processes started by torch.multiprocessing "
                            "(one machine, no launcher); ddp = one rank per device in a torch.distributed group "
                            "(gloo): under torchrun it joins the launcher's group, and without one it starts the N "
                            "ranks on this machine itself with torch's elastic launcher (the same command in each; "
                            "--devices 1: one process)")


@dataclass(frozen=True)
class _Failure:
    """A frame that could not be read or checked: its exception's type and one-line message.

    Returned by the workers instead of raising: DataLoader re-raises a worker's exception
    with the worker's traceback in its message.
    """

    error: type[BaseException]
    message: str


class _CheckedFrames(Dataset):
    """The frames of ``dataset``, each passed through ``check(sample, index)``; picklable
    (workers started by spawn or forkserver receive it pickled) when both are. With
    ``keep=False`` a frame that passes gives None instead of the sample (:func:`bad_frames`:
    nothing is sent back from the workers, nothing held)."""

    def __init__(self, dataset: Dataset, check: Callable[[Sample, int], None], keep: bool = True) -> None:
        self.dataset, self.check, self.keep = dataset, check, keep

    def __len__(self) -> int:
        return len(self.dataset)

    def __getitem__(self, index: int) -> Sample | _Failure | None:
        try:
            with quiet_decoders():  # a damaged image is told by its reader's message alone, not libpng's too
                sample = self.dataset[index]
            self.check(sample, index)
        except BAD_INPUT as exc:
            return _Failure(type(exc), str(exc))
        return sample if self.keep else None


def _check_any(sample: Sample, index: int) -> None:
    """The default check of :func:`frame_batches`: :func:`check_sample`."""
    check_sample(sample)


def _as_is(item):
    """``collate_fn`` of the one-frame loader: no conversion (batches are formed afterwards)."""
    return item


def bad_frames(dataset: Dataset, workers: int, check: Callable[[Sample, int], None] = _check_any,
               progress: Callable[[int], None] | None = None) -> list[tuple[int, type[BaseException], str]]:
    """Read and check every frame of ``dataset`` (``workers`` DataLoader processes, as :func:`frame_batches`)
    without keeping any: ``(index, exception type, one-line message)`` of each frame that fails (``BAD_INPUT``),
    in order. ``progress(i)`` is called after frame ``i``. The first pass of ``complete --input-dir``, so that a
    bad frame is found before anything is written; it costs one extra read of each frame (measured: 23-56 ms
    for a 1216x352 KITTI frame on a 2-core machine, under 10% of its completion; docs/design.md section 10)."""
    loader = DataLoader(_CheckedFrames(dataset, check, keep=False), batch_size=None, shuffle=False,
                        num_workers=workers, collate_fn=_as_is)
    bad = []
    for index, item in enumerate(loader):
        if isinstance(item, _Failure):
            bad.append((index, item.error, item.message))
        if progress is not None:
            progress(index)
    return bad


def frame_batches(dataset: Dataset, batch_size: int, workers: int,
                  check: Callable[[Sample, int], None] = _check_any, starts: set[int] | None = None
                  ) -> Iterator[Batch]:
    """The frames of ``dataset`` in order, as :class:`~crfdepth.data.sample.Batch` es of up
    to ``batch_size`` consecutive frames of one size (a size change starts a new batch).

    ``workers`` DataLoader processes (0: this process) read each frame and run ``check``
    on it (default :func:`check_sample`). A frame that fails (``BAD_INPUT``) ends the
    iteration: the frames before it are yielded first, then its exception is raised with
    the type and message it had where it was read, so the error reads the same for any
    ``workers`` and ``batch_size``. ``starts``: indices of frames that start a batch besides
    (a resumed run's plan, :func:`crfdepth.cli.resume.batch_plan`). Results do not depend on how the frames are batched
    beyond :func:`~crfdepth.cli.completion.complete_batch_with_cli_advice`'s solver tolerance.
    """
    loader = DataLoader(_CheckedFrames(dataset, check), batch_size=None, shuffle=False, num_workers=workers,
                        collate_fn=_as_is)
    pending: list[Sample] = []
    for index, item in enumerate(loader):
        if isinstance(item, _Failure):
            if pending:
                yield collate_samples(pending)
            raise item.error(item.message)
        if pending and (item.size != pending[0].size or (starts is not None and index in starts)):
            yield collate_samples(pending)
            pending = []
        pending.append(item)
        if len(pending) == batch_size:
            yield collate_samples(pending)
            pending = []
    if pending:
        yield collate_samples(pending)
