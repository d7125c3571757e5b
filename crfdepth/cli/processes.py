"""``complete --input-dir --devices N``: the planned batches of a folder run completed by N processes, one
per device (CUDA GPUs, or CPU processes sharing the cores).

The launching process does everything that decides what is written (the checks of every frame,
``--skip-bad``, ``--resume``, the batch plan: :mod:`crfdepth.cli.complete_folder`) and holds the output
folders' locks; it then deals the planned batches to the processes in turn (batch ``j`` to process
``j mod N``), so each frame is solved in the batch it has in a one-process run and no frame is done
twice or left out. Each process (``torch.multiprocessing``, started by spawn) builds the model on its
device, completes its batches and writes their files (each atomically), and reports what it wrote and
what failed. A process that fails on a frame does not stop the others: their frames stay written, the
failed frames are listed (``failed.csv``) and ``--resume`` completes the rest.
"""

from __future__ import annotations

import argparse
import copy
import os
import queue as queue_module
from collections.abc import Callable

import torch
import torch.multiprocessing as mp

from crfdepth.errors import InputError

__all__ = ["check_devices", "complete_in_processes"]


def check_devices(devices: int, device: str) -> None:
    """Refuse ``--devices`` beyond what this machine has: CUDA GPUs for ``--device cuda``, CPU cores for cpu."""
    if device == "cuda":
        have = torch.cuda.device_count() if torch.cuda.is_available() else 0
        if devices > have:
            raise InputError(f"--devices {devices}: this machine has {have} CUDA GPU(s); give at most {have}, or "
                             f"--device cpu for CPU processes")
    else:
        cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)
        if devices > cores:
            raise InputError(f"--devices {devices}: with --device cpu each process needs a CPU core of its own and "
                             f"this machine has {cores}; give at most {cores}")


def complete_in_processes(args: argparse.Namespace, dataset, batches: list[list[int]], folders: tuple,
                          with_std: bool, complete: Callable
                          ) -> tuple[int, list[tuple[str, str]], list[tuple[str, bool]]]:
    """Complete the frames ``batches`` (lists of indices into the folder ``dataset``, which is sent to the
    processes as it is: they read the frames the launching process checked) by ``complete`` (the one-process
    step, :func:`crfdepth.cli.complete_folder.complete_planned`, a module-level function the processes import) with
    ``args.devices`` processes. Returns (frames written, failed frames as (name, reason), (message, interrupted)
    of each process that stopped early)."""
    count = min(args.devices, len(batches))
    shares = [batches[rank::count] for rank in range(count)]
    context = mp.get_context("spawn")
    results = context.SimpleQueue()
    threads = max(1, torch.get_num_threads() // count) if args.device != "cuda" else torch.get_num_threads()
    try:
        mp.start_processes(_complete_share, nprocs=count, join=True, start_method="spawn",
                           args=(count, args, dataset, shares, folders, with_std, threads, complete, results))
    except mp.ProcessRaisedException as exc:  # an error the process could not report (a bug): its last line
        raise RuntimeError(f"a completion process failed: {str(exc).strip().splitlines()[-1]}") from None
    except mp.ProcessExitedException as exc:  # killed (out of memory, a signal) before it could report
        raise InputError(f"--devices {args.devices}: a completion process ended without reporting ({exc}); the "
                         f"frames the others wrote stay; --resume completes the rest") from None
    written, failed, stopped = 0, [], []
    for _ in range(count):
        rank_written, rank_failed, stop = results.get()
        written += rank_written
        failed += rank_failed
        if stop is not None:
            stopped.append(stop)
    return written, failed, stopped


def _complete_share(rank: int, count: int, args: argparse.Namespace, dataset, shares: list, folders: tuple,
                    with_std: bool, threads: int, complete: Callable, results) -> None:
    """One process: its share of the batches on its device; puts (written, failed, stop message) on ``results``."""
    from crfdepth.cli.arguments import BAD_INPUT
    from crfdepth.cli.model_options import build_model

    torch.set_num_threads(threads)
    mine = copy.copy(args)
    mine.quiet = True  # one model line and one summary, from the launching process
    if args.device == "cuda":
        torch.cuda.set_device(rank)
    failed: list[tuple[str, str]] = []
    counts, stop = {"written": 0}, None
    try:
        complete(mine, build_model(mine), dataset, shares[rank], folders, with_std, failed, counts)
    except BAD_INPUT as exc:
        stop = (f"process {rank + 1}/{count}: {exc}", False)
    except KeyboardInterrupt as exc:
        stop = (f"process {rank + 1}/{count}: interrupted {exc}", True)
    finally:
        try:
            results.put((counts["written"], failed, stop))
        except (OSError, queue_module.Full):  # the launching process is gone
            pass
