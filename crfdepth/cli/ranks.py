"""``complete --input-dir`` on several machines: one process per device, started on every node by torchrun
(or SLURM's srun with torchrun's environment), joined in a ``torch.distributed`` group (gloo).

Rank 0 does what decides the files (the checks of every frame, ``--skip-bad``, ``--resume``, the batch
plan), creates and locks the output folders, and shares the outcome with the other ranks: the plan, or
the error that stops the run, which every rank then raises alike. The planned batches are dealt to the
ranks in turn, as to local processes (:mod:`crfdepth.cli.processes`); each rank completes its share on
``cuda:LOCAL_RANK`` (or the CPU) and writes its files into the shared folders; what each wrote and what
failed is gathered on every rank, and rank 0 lists the failed frames and prints the summary.

The environment torchrun sets is read: ``WORLD_SIZE``, ``RANK``, ``LOCAL_RANK``, ``LOCAL_WORLD_SIZE``,
``MASTER_ADDR``, ``MASTER_PORT``. ``--num-nodes M --devices N`` must describe the same group
(``WORLD_SIZE = M * N``); the output folders must be one shared file system.
"""

from __future__ import annotations

import argparse
import datetime
import os
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import torch
import torch.distributed as dist

from crfdepth.cli.processes import check_devices
from crfdepth.errors import InputError

__all__ = ["Ranks", "ranks_from_environment", "run_in_group"]

# Rank 0 reads and checks every frame before the others get the plan (about 40 ms a KITTI frame:
# half an hour for a 47,000-frame archive), so the group waits that long without giving up.
PLAN_TIMEOUT = datetime.timedelta(hours=24)

_ERRORS = {cls.__name__: cls for cls in (InputError, FileNotFoundError, PermissionError, KeyboardInterrupt)}


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
            except (InputError, FileNotFoundError, PermissionError, KeyboardInterrupt) as exc:
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
        if dist.is_initialized():
            dist.destroy_process_group()


def run_in_group(args: argparse.Namespace, run: Callable[[argparse.Namespace, Ranks | None], int]) -> int:
    """``run(args, ranks)``: alone (``ranks`` None; ``--devices`` local processes checked against the machine)
    or as this process's rank of the torchrun group, which it leaves again afterwards."""
    ranks = ranks_from_environment(args)
    if ranks is None and args.devices > 1:
        check_devices(args.devices, args.device)
    try:
        return run(args, ranks)
    finally:
        if ranks is not None:
            ranks.close()


def ranks_from_environment(args: argparse.Namespace) -> Ranks | None:
    """The group this process belongs to when torchrun started it (``WORLD_SIZE`` > 1), joined; None when it
    runs alone. Refuses ``--num-nodes`` > 1 without such a launcher, and a group of another size than
    ``--num-nodes`` x ``--devices``."""
    world = int(os.environ.get("WORLD_SIZE", "1") or 1)
    expected = args.num_nodes * args.devices
    if world == 1:
        if args.num_nodes > 1:
            raise InputError(f"--num-nodes {args.num_nodes}: start the command on every node with torchrun "
                             f"(torchrun --nnodes {args.num_nodes} --nproc-per-node {args.devices} --rdzv-endpoint "
                             f"HOST:PORT -m crfdepth complete ...) or srun under torchrun; this process has no "
                             f"WORLD_SIZE, RANK, MASTER_ADDR and MASTER_PORT to join the others by")
        return None
    if world != expected:
        raise InputError(f"--num-nodes {args.num_nodes} --devices {args.devices}: expected {expected} process(es) in "
                         f"all, the launcher started {world} (WORLD_SIZE); give torchrun --nnodes {args.num_nodes} "
                         f"--nproc-per-node {args.devices}")
    missing = [name for name in ("RANK", "MASTER_ADDR", "MASTER_PORT") if not os.environ.get(name)]
    if missing:
        raise InputError(f"--num-nodes {args.num_nodes}: WORLD_SIZE is {world} but {', '.join(missing)} is not set; "
                         f"start the command with torchrun")
    rank = int(os.environ["RANK"])
    local_rank = int(os.environ.get("LOCAL_RANK", rank % args.devices))
    local_world = int(os.environ.get("LOCAL_WORLD_SIZE", args.devices))
    if args.device == "cuda":
        if local_rank >= torch.cuda.device_count():
            raise InputError(f"--devices {args.devices}: process {local_rank} of this node has no CUDA GPU of its "
                             f"own (this node has {torch.cuda.device_count()})")
        torch.cuda.set_device(local_rank)
    else:
        torch.set_num_threads(max(1, torch.get_num_threads() // local_world))
    dist.init_process_group("gloo", init_method="env://", rank=rank, world_size=world, timeout=PLAN_TIMEOUT)
    return Ranks(rank, world, local_rank, local_world)
