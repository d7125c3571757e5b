"""Frames read and checked by DataLoader workers, then batched by size (``complete --input-dir``, ``evaluate``).

:func:`check_sample` refuses a frame as :func:`crfdepth.api.complete_depth` would; :func:`bad_frames`
is the check pass that keeps nothing; :func:`frame_batches` yields the
:class:`~crfdepth.data.sample.Batch` es that one model call each completes (:func:`crfdepth.api.complete_checked`).
"""

from __future__ import annotations

from collections.abc import Callable, Iterator
from dataclasses import dataclass

from torch.utils.data import DataLoader, Dataset

from crfdepth import api
from crfdepth.data.sample import Batch, Sample, collate_samples
from crfdepth.errors import BAD_INPUT, InputError
from crfdepth.io.decoder_noise import quiet_decoders

__all__ = ["bad_frames", "check_sample", "flag_names", "frame_batches"]


def flag_names(exc: InputError, flags: dict[str, str]) -> InputError:
    """The API's message with its argument name (``K``, ``sparse`` ...) replaced by the user's name for it
    (``flags``: a flag, or a frame and its file); ``flags["*"]``, when given, leads a message about the inputs
    together (e.g. no point lands in the image)."""
    text = str(exc)
    head, sep, rest = text.partition(":")
    if sep and head.strip() in flags:
        return InputError(f"{flags[head.strip()]}:{rest}")
    if "*" in flags:  # a message about the inputs together (e.g. no point lands in the image)
        return InputError(f"{flags['*']}: {text}")
    return exc


def check_sample(sample: Sample) -> None:
    """Refuse a frame that :func:`crfdepth.api.complete_depth` would refuse, with its checks and
    messages (:func:`crfdepth.api.check_frame`; names ``image``, ``sparse``, ``K``)."""
    api.check_frame(sample.image, sample.sparse, sample.K)


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
    (a resumed run's plan, :func:`crfdepth.runs.resume.batch_plan`). Results do not depend on how the frames are batched
    beyond the solver's tolerance.
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
