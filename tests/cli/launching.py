"""``python -m crfdepth`` in processes of its own, as a user or a launcher starts it: alone (without a
launcher's environment) or as the two ranks of a group, one process per node, as torchrun starts them
(its environment; the ranks join by gloo)."""

from __future__ import annotations

import os
import socket
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
# What a launcher sets; a test started under one must not pass it on.
_LAUNCHER = ("WORLD_SIZE", "RANK", "LOCAL_RANK", "LOCAL_WORLD_SIZE", "MASTER_ADDR", "MASTER_PORT", "GROUP_RANK",
             "ROLE_RANK", "TORCHELASTIC_RUN_ID")


def _environment(**group: str) -> dict[str, str]:
    """This environment without a launcher's variables, one thread per process, and ``group``."""
    return {**{k: v for k, v in os.environ.items() if k not in _LAUNCHER}, "OMP_NUM_THREADS": "1", **group}


def _command(argv: list) -> list[str]:
    return [sys.executable, "-m", "crfdepth", *map(str, argv)]


def alone(argv: list) -> subprocess.CompletedProcess:
    """``python -m crfdepth`` with ``argv`` started as a user starts it (no launcher)."""
    return subprocess.run(_command(argv), cwd=ROOT, env=_environment(), capture_output=True, text=True, timeout=300)


def two_ranks(argv: list) -> list[subprocess.CompletedProcess]:
    """``python -m crfdepth`` twice, as rank 0 and 1 of a group of 2 (one process per node), as torchrun starts
    them."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = str(s.getsockname()[1])
    procs = [subprocess.Popen(_command(argv), cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                              env=_environment(WORLD_SIZE="2", RANK=str(rank), LOCAL_RANK="0", LOCAL_WORLD_SIZE="1",
                                               MASTER_ADDR="127.0.0.1", MASTER_PORT=port))
             for rank in range(2)]
    done = []
    for proc in procs:
        out, err = proc.communicate(timeout=300)
        done.append(subprocess.CompletedProcess(proc.args, proc.returncode, out, err))
    return done
