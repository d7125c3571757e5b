"""The training frames' order and random draws: functions of (seed, epoch, frame), so that a run
stopped mid-epoch and resumed from its checkpoint trains on the batches an uninterrupted run trains
on, with the same flips, crops and thinning (docs/design.md section 10, "Resuming training").

- :class:`EpochOrder` orders the frames of an epoch: shuffled by ``(seed, epoch)`` as
  :class:`~torch.utils.data.DistributedSampler` shuffles (it is one, so Lightning leaves it in place under
  DDP and each rank reads its own share), and started, in the epoch a checkpoint stopped in, after the
  frames already trained.
- Each index comes with the seed of that frame's random draws in that epoch (:class:`Draw`). The
  dataset (:class:`~train.data.TransformedDataset`) reads and augments the frame under torch's CPU
  generator seeded with it, so the draws depend neither on the ``DataLoader`` worker that reads the
  frame nor on what was drawn before.
- :class:`ResumableLoader` is the ``DataLoader`` whose position Lightning saves in a checkpoint and
  gives back on ``--ckpt_path`` (its ``state_dict`` / ``load_state_dict``): the epoch, the batches the
  trainer has trained in it (the trainer's count, not the loader's: the loader reads ahead), and the
  seed. A checkpoint of another training set, batch size or number of processes is refused
  (:func:`check_same_run`; the data module checks the same at the end of an epoch, where Lightning does not
  give the loader its state back: :meth:`train.data.CRFDataModule.load_state_dict`).
"""

from __future__ import annotations

import contextlib
import hashlib
from collections.abc import Callable, Iterator, Mapping
from typing import Any, NamedTuple

import numpy as np
import torch
from torch.utils.data import DataLoader, Dataset, DistributedSampler

from crfdepth.errors import InputError

__all__ = ["Draw", "EpochOrder", "ResumableLoader", "check_same_run", "draw_seed", "frames_digest", "seeded_draws"]


class Draw(NamedTuple):
    """A frame to read (``index`` into the dataset) and the ``seed`` of its random draws."""

    index: int
    seed: int


def draw_seed(seed: int, epoch: int, index: int) -> int:
    """The seed of frame ``index``'s random draws in ``epoch`` of a run seeded with ``seed``."""
    return int(np.random.SeedSequence([int(seed), int(epoch), int(index)]).generate_state(1)[0])


@contextlib.contextmanager
def seeded_draws(seed: int) -> Iterator[None]:
    """Torch's CPU generator seeded with ``seed`` inside the block, and as it was again after it.
    (Only the CPU generator: ``torch.manual_seed`` would reseed the CUDA generators too.)"""
    state = torch.default_generator.get_state()
    torch.default_generator.manual_seed(seed)
    try:
        yield
    finally:
        torch.default_generator.set_state(state)


class EpochOrder(DistributedSampler):
    """The training frames of one process in one epoch, as :class:`Draw` items (module docstring).

    The order is :class:`~torch.utils.data.DistributedSampler`'s: a permutation by ``(seed, epoch)``
    (or the dataset's order when ``shuffle`` is False), padded to a multiple of ``num_replicas`` and
    dealt to the ranks in turn. ``resume(epoch, frames)`` starts that epoch after its first ``frames``
    items; other epochs start at their first.
    """

    def __init__(self, dataset: Dataset, *, num_replicas: int = 1, rank: int = 0, shuffle: bool = True,
                 seed: int = 0) -> None:
        super().__init__(dataset, num_replicas=num_replicas, rank=rank, shuffle=shuffle, seed=seed, drop_last=False)
        self.resume_at: tuple[int, int] | None = None

    def resume(self, epoch: int, frames: int) -> None:
        self.resume_at = (int(epoch), int(frames))

    def __iter__(self) -> Iterator[Draw]:
        indices = list(super().__iter__())
        start = self.resume_at[1] if self.resume_at is not None and self.resume_at[0] == self.epoch else 0
        return iter([Draw(i, draw_seed(self.seed, self.epoch, i)) for i in indices[start:]])


def frames_digest(names: list[str]) -> str:
    """SHA-256 of the training frames' names in order: which frames a run trains on, in a checkpoint."""
    return hashlib.sha256("\n".join(names).encode()).hexdigest()


def check_same_run(saved: Mapping[str, Any], now: Mapping[str, Any]) -> None:
    """Refuse to resume a run from the checkpoint of another one.

    ``saved`` is what a checkpoint holds of the run that wrote it (the loader's or the data module's
    state: ``epoch``, ``batches``, ``frames``, ``batch_size``, ``processes`` and, in checkpoints written
    since it exists, ``frames_sha256``, :func:`frames_digest`); ``now`` the same keys of this run. A
    checkpoint from the middle of an epoch, from its end or from the end of the run is refused alike:
    the run it resumes is the run that wrote it. A key ``saved`` lacks (an older checkpoint) is not compared.

    Raises:
        InputError: ``--ckpt_path: the checkpoint stopped in epoch E after B batch(es) of another training
            run (frames 32 then, 13 now, ...); ...``.
    """
    differ = []
    for key, value in now.items():
        then = saved.get(key)
        if key == "frames_sha256":
            if then is not None and then != value and saved.get("frames") == now.get("frames"):
                differ.append(f"other frames, {then[:12]} then, {value[:12]} now (SHA-256 of their names)")
        elif then != value:
            differ.append(f"{key} {then} then, {value} now")
    if differ:
        raise InputError(f"--ckpt_path: the checkpoint stopped in epoch {saved.get('epoch')} after "
                         f"{saved.get('batches')} batch(es) of another training run ({', '.join(differ)}); resume with "
                         f"the data, data.batch_size and trainer.devices x trainer.num_nodes it was saved with, or "
                         f"train afresh without --ckpt_path")


class ResumableLoader(DataLoader):
    """A ``DataLoader`` over :class:`EpochOrder` whose position Lightning checkpoints (module docstring).

    Args:
        dataset: the training set; its items are read by :class:`Draw` (``TransformedDataset``).
        order: the sampler.
        trained: the number of batches the trainer has trained in the current epoch (0 outside a fit).
        **options: the other ``DataLoader`` arguments (``batch_size``, ``num_workers``, ...).
    """

    def __init__(self, dataset: Dataset, *, order: EpochOrder, trained: Callable[[], int], **options: Any) -> None:
        super().__init__(dataset, sampler=order, **options)
        self.trained = trained

    def _shape(self) -> dict[str, int]:
        return {"frames": len(self.dataset), "batch_size": self.batch_size, "processes": self.sampler.num_replicas}

    def state_dict(self) -> dict[str, Any]:
        return {"epoch": self.sampler.epoch, "batches": int(self.trained()), "seed": self.sampler.seed,
                "shuffle": self.sampler.shuffle, **self._shape()}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        check_same_run(state, self._shape())
        self.sampler.seed = int(state["seed"])
        self.sampler.shuffle = bool(state["shuffle"])
        self.sampler.resume(state["epoch"], int(state["batches"]) * self.batch_size)
