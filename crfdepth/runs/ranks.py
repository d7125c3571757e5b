"""Runs over many frames (``complete --input-dir`` / ``--input-list``, ``evaluate``) as ranks of a
``torch.distributed`` group (gloo): one process per device, started on every node by torchrun (or SLURM's srun
with torchrun's environment), or on one machine by crfdepth itself (``--strategy ddp``: :mod:`crfdepth.runs.launch`).

A :class:`Spread` says how (the command's ``--devices``, ``--num-nodes``, ``--strategy``, ``--device``).
:func:`run_in_group` (or :func:`launches_ranks` then :func:`joined_group`) decides by ``--strategy`` how a run is
spread: ``auto`` (default) joins the
launcher's group when there is one (``WORLD_SIZE`` > 1), else runs ``--devices`` local processes
(:mod:`crfdepth.runs.processes`) or this one alone; ``spawn`` always runs local processes, and is refused
under a launcher or with ``--num-nodes`` > 1; ``ddp`` joins the launcher's group, or without a launcher
starts the ``--devices`` ranks on this machine (``--devices 1``: this process alone).

Rank 0 does what decides the files (the checks of every frame, ``--skip-bad``, ``--resume``, the batch
plan), creates and locks the output folders, and shares the outcome with the other ranks: the plan, or
the error that stops the run, which every rank then raises alike. The planned batches are dealt to the
ranks in turn, as to local processes (:mod:`crfdepth.runs.processes`); each rank completes its share on
``cuda:LOCAL_RANK`` (or the CPU) and writes its files into the shared folders; what each wrote and what
failed is gathered on every rank, and rank 0 lists the failed frames and prints the summary. An
``--input-list`` joins the group once and runs its inputs in turn, each shared out so
(``crfdepth.cli.complete_list``).

The environment torchrun sets is read: ``WORLD_SIZE``, ``RANK``, ``LOCAL_RANK``, ``LOCAL_WORLD_SIZE``,
``MASTER_ADDR``, ``MASTER_PORT``. ``--num-nodes M --devices N`` must describe the same group
(``WORLD_SIZE = M * N``); the output folders must be one shared file system.
"""

from __future__ import annotations

import contextlib
import datetime
import logging
import os
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from typing import Any

import torch
import torch.distributed as dist

from crfdepth.errors import BAD_INPUT, InputError
from crfdepth.runs.launch import launch_ranks
from crfdepth.runs.processes import check_devices

__all__ = ["Ranks", "Spread", "joined_group", "launcher_world_size", "launches_ranks", "ranks_from_environment",
           "run_in_group"]

logger = logging.getLogger(__name__)

# Rank 0 reads and checks every frame before the others get the plan (about 40 ms a KITTI frame:
# half an hour for a 47,000-frame archive), so the group waits that long without giving up.
PLAN_TIMEOUT = datetime.timedelta(hours=24)

# What rank 0 shares instead of a value (Ranks.share): bad input and Ctrl-C, raised alike on every rank.
_SHARED_ERRORS = (*BAD_INPUT, KeyboardInterrupt)
_ERRORS = {cls.__name__: cls for cls in _SHARED_ERRORS}


@dataclass(frozen=True)
class Spread:
    """How a run is spread over processes: ``devices`` (one per device: CUDA GPUs 0..N-1 for ``device`` "cuda", CPU
    processes sharing the cores for "cpu") on each of ``num_nodes`` machines, started as ``strategy`` ("auto",
    "spawn" or "ddp") says; ``argv``: the ``crfdepth`` command line each rank runs when this process starts the
    ranks itself (None: this process's own)."""

    devices: int = 1
    num_nodes: int = 1
    strategy: str = "auto"
    device: str = "cpu"
    argv: tuple[str, ...] | None = None


@dataclass
class Ranks:
    """This process's place in the group: ``rank`` of ``world``, ``local_rank`` of ``local_world`` on its node."""

    rank: int
    world: int
    local_rank: int
    local_world: int

    @property
    def is_main(self) -> bool:
        return self.rank == 0

    def share(self, make: Callable[[], Any]) -> Any:
        """``make()`` run on rank 0 and its value given to every rank; an error it raises (bad input, Ctrl-C) is
        raised on every rank, with its message."""
        box: list[Any] = [None]
        if self.is_main:
            try:
                box[0] = ("value", make())
            except _SHARED_ERRORS as exc:
                box[0] = ("error", type(exc).__name__ if type(exc).__name__ in _ERRORS else "InputError", str(exc))
        dist.broadcast_object_list(box, src=0)
        if box[0][0] == "error":
            _, kind, message = box[0]
            raise _ERRORS[kind](message)
        return box[0][1]

    def gather(self, value: Any) -> list[Any]:
        """Every rank's ``value``, in rank order, on every rank."""
        values: list[Any] = [None] * self.world
        dist.all_gather_object(values, value)
        return values

    def close(self) -> None:
        """Leave the group once every rank has come here, so that rank 0 reports (its summary, or the error that
        every rank raises alike) before any rank ends: a launcher stops the other ranks as soon as one ends with
        an error (:mod:`crfdepth.runs.launch`)."""
        if dist.is_initialized():
            try:
                dist.barrier()
            except RuntimeError:  # a rank is gone (killed, or failed on a bug); its launcher reports it
                pass
            dist.destroy_process_group()


def launcher_world_size() -> int:
    """The size of the launcher's group this process is a rank of (torchrun, srun: ``WORLD_SIZE``); 1 without one."""
    return int(os.environ.get("WORLD_SIZE", "1") or 1)


def run_in_group(spread: Spread, run: Callable[[Ranks | None], int]) -> int:
    """``run(ranks)`` as ``--strategy`` says (module docstring): alone (``ranks`` None; ``--devices`` local
    processes checked against the machine), as this process's rank of the launcher's group, which it leaves
    again afterwards, or (``ddp`` without a launcher) in ``--devices`` ranks started here, whose exit status
    is returned."""
    if launches_ranks(spread):
        return launch_ranks(spread.argv, spread.devices)
    with joined_group(spread) as ranks:
        return run(ranks)


def launches_ranks(spread: Spread) -> bool:
    """Whether this process starts the ranks itself (``--strategy ddp --devices N``, N > 1, on one node without a
    launcher; the devices checked against the machine): then :func:`crfdepth.runs.launch.launch_ranks` runs the
    command, else :func:`joined_group`. Refuses ``--strategy spawn`` with ``--num-nodes`` > 1 or under a
    launcher."""
    launcher = launcher_world_size()
    if spread.strategy == "spawn" and spread.num_nodes > 1:
        raise InputError(f"--strategy spawn: starts the --devices processes on this machine only, got --num-nodes "
                         f"{spread.num_nodes}; give --strategy ddp (or auto) and start the command on every node with "
                         f"torchrun")
    if spread.strategy == "spawn" and launcher > 1:
        raise InputError(f"--strategy spawn: expected a command started alone (spawn starts the --devices processes "
                         f"itself), got WORLD_SIZE={launcher} from a launcher (torchrun, srun); give --strategy ddp "
                         f"or auto under a launcher")
    starts = spread.strategy == "ddp" and launcher == 1 and spread.num_nodes == 1 and spread.devices > 1
    if starts:
        check_devices(spread.devices, spread.device)
    return starts


@contextlib.contextmanager
def joined_group(spread: Spread) -> Iterator[Ranks | None]:
    """For the ``with`` block: this process's rank of the launcher's group (:func:`ranks_from_environment`), left
    again when the block ends, or None when it runs alone (``--devices`` local processes checked against the
    machine)."""
    ranks = ranks_from_environment(spread)
    if ranks is None and spread.devices > 1:
        check_devices(spread.devices, spread.device)
    try:
        yield ranks
    finally:
        if ranks is not None:
            ranks.close()


def ranks_from_environment(spread: Spread) -> Ranks | None:
    """The group this process belongs to when torchrun started it (``WORLD_SIZE`` > 1), joined; None when it
    runs alone. Refuses ``--num-nodes`` > 1 without such a launcher, and a group of another size than
    ``--num-nodes`` x ``--devices``."""
    world = launcher_world_size()
    expected = spread.num_nodes * spread.devices
    if world == 1:
        if spread.num_nodes > 1:
            raise InputError(f"--num-nodes {spread.num_nodes}: start the command on every node with torchrun "
                             f"(torchrun --nnodes {spread.num_nodes} --nproc-per-node {spread.devices} --rdzv-endpoint "
                             f"HOST:PORT -m crfdepth complete ...) or srun under torchrun; this process has no "
                             f"WORLD_SIZE, RANK, MASTER_ADDR and MASTER_PORT to join the others by")
        return None
    if world != expected:
        raise InputError(f"--num-nodes {spread.num_nodes} --devices {spread.devices}: expected {expected} process(es) in "
                         f"all, the launcher started {world} (WORLD_SIZE); give torchrun --nnodes {spread.num_nodes} "
                         f"--nproc-per-node {spread.devices}")
    missing = [name for name in ("RANK", "MASTER_ADDR", "MASTER_PORT") if not os.environ.get(name)]
    if missing:
        raise InputError(f"--num-nodes {spread.num_nodes}: WORLD_SIZE is {world} but {', '.join(missing)} is not set; "
                         f"start the command with torchrun")
    rank = int(os.environ["RANK"])
    local_rank = int(os.environ.get("LOCAL_RANK", rank % spread.devices))
    local_world = int(os.environ.get("LOCAL_WORLD_SIZE", spread.devices))
    if spread.device == "cuda":
        if local_rank >= torch.cuda.device_count():
            raise InputError(f"--devices {spread.devices}: process {local_rank} of this node has no CUDA GPU of its "
                             f"own (this node has {torch.cuda.device_count()})")
        torch.cuda.set_device(local_rank)
    else:
        torch.set_num_threads(max(1, torch.get_num_threads() // local_world))
    dist.init_process_group("gloo", init_method="env://", rank=rank, world_size=world, timeout=PLAN_TIMEOUT)
    logger.info("joined the group as rank %d/%d (process %d/%d of this node)", rank + 1, world, local_rank + 1,
                local_world)
    return Ranks(rank, world, local_rank, local_world)
