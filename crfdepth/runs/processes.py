"""``--devices N`` of ``complete --input-dir`` (and of each folder of ``--input-list``) and ``evaluate`` with
``--strategy spawn``, or ``auto`` without a launcher: the planned batches of a run done by N processes on
this machine, one per device (CUDA GPUs, or CPU processes sharing the cores). Ranks of a group instead
(``--strategy ddp``, ``--num-nodes``): :mod:`crfdepth.runs.ranks`.

The launching process does everything that decides what is written (the checks of every frame,
``--skip-bad``, ``--resume``, the batch plan: :mod:`crfdepth.runs.folder`) and holds the output
folders' locks; it then deals the planned batches to the processes in turn (batch ``j`` to process
``j mod N``), so each frame is solved in the batch it has in a one-process run and no frame is done
twice or left out. Each process (``torch.multiprocessing``, started by spawn) builds the model on its
device, completes its batches and writes their files (each atomically), and reports what it wrote and
what failed. A process that fails on a frame does not stop the others: their frames stay written, the
failed frames are listed (``failed.csv``) and ``--resume`` completes the rest.
"""

from __future__ import annotations

import dataclasses
import os
import queue as queue_module
from collections.abc import Callable

import torch
import torch.multiprocessing as mp

from crfdepth.errors import BAD_INPUT, InputError

__all__ = ["check_devices", "deal", "in_processes", "run_share"]


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


def in_processes(options, shares: list, work: Callable, *, devices: int, device: str
                 ) -> list[tuple[dict, tuple[str, bool] | None]]:
    """``work(options, model, share, partial)`` for each of ``shares`` in a process of its own (``device`` "cuda": on
    GPU ``rank``; cpu: the threads divided among the processes), the model built there by ``options.make_model``.
    ``options`` is a picklable dataclass with the fields ``quiet`` and ``make_model`` (a module-level callable of
    ``quiet``); ``work`` is a module-level function (the processes import it) that fills the dict ``partial`` as it
    goes, so that what a process did before it stopped is known; ``devices`` names the run's ``--devices`` in
    messages. Returns, in share order, ``(partial, stop)``: ``stop`` is None, or the one-line message of the error
    that stopped the process and whether it was an interrupt."""
    count = len(shares)
    context = mp.get_context("spawn")
    results = context.SimpleQueue()
    threads = max(1, torch.get_num_threads() // count) if device != "cuda" else torch.get_num_threads()
    try:
        mp.start_processes(_run_share, nprocs=count, join=True, start_method="spawn",
                           args=(count, options, shares, work, threads, device, results))
    except mp.ProcessRaisedException as exc:  # an error the process could not report (a bug): its last line
        raise RuntimeError(f"a process of --devices {devices} failed: {str(exc).strip().splitlines()[-1]}") \
            from None
    except mp.ProcessExitedException as exc:  # killed (out of memory, a signal) before it could report
        raise InputError(f"--devices {devices}: a process ended without reporting ({exc}); what the others "
                         f"wrote stays") from None
    reported = dict(results.get() for _ in range(count))
    return [reported[rank] for rank in range(count)]


def deal(batches: list[list[int]], devices: int) -> list[list[list[int]]]:
    """The batches dealt to ``devices`` processes in turn (batch ``j`` to process ``j mod devices``)."""
    count = min(devices, len(batches))
    return [batches[rank::count] for rank in range(count)]


def run_share(who: str, options, work: Callable, share, model=None) -> tuple[dict, tuple[str, bool] | None]:
    """``work(options, model, share, partial)`` for one process or rank (``who``, for messages), quietly (one model
    line and one summary, from the launching process or rank 0), the model built here
    (``options.make_model(True)``) unless given. Returns ``(partial, stop)``: what ``work`` recorded, and None or
    the one-line error that stopped it and whether it was an interrupt."""
    quiet = dataclasses.replace(options, quiet=True)
    partial: dict = {}
    try:
        work(quiet, model if model is not None else options.make_model(True), share, partial)
    except (*BAD_INPUT, OSError) as exc:  # OSError: an output that cannot be written (FileError names its flag)
        return partial, (f"{who}: {exc}", False)
    except KeyboardInterrupt as exc:
        return partial, (f"{who}: interrupted {exc}", True)
    return partial, None


def _run_share(rank: int, count: int, options, shares: list, work: Callable, threads: int, device: str,
               results) -> None:
    """One process of :func:`in_processes`: puts ``(rank, (partial, stop))`` on ``results``."""
    torch.set_num_threads(threads)
    if device == "cuda":
        torch.cuda.set_device(rank)
    done = run_share(f"process {rank + 1}/{count}", options, work, shares[rank])
    try:
        results.put((rank, done))
    except (OSError, queue_module.Full):  # the launching process is gone
        pass
