"""Fixtures of the trainer tests: run ``python -m train`` and read what it logged.

The folder is named like the ``train`` package it tests; ``pythonpath = ["."]`` in
pyproject.toml puts the repository root first on ``sys.path`` so that ``import train``
finds the package, not this folder.
"""

from __future__ import annotations

import os
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]

CONFIGS = ROOT / "configs"


@dataclass
class Run:
    """A finished ``python -m train`` subprocess."""

    returncode: int
    output: str
    seconds: float
    log_dir: Path

    def version_dir(self) -> Path:
        """The single ``<save_dir>/<name>/version_N`` folder the run logged to."""
        found = sorted({p.parent for p in self.log_dir.rglob("events.out.tfevents.*")})
        assert len(found) == 1, f"expected one TensorBoard run under {self.log_dir}, got {found}\n{self.output[-3000:]}"
        return found[0]

    def scalars(self) -> dict[str, list[tuple[int, float]]]:
        """``{tag: [(step, value), ...]}`` of the run's TensorBoard scalars, in logging order."""
        from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

        acc = EventAccumulator(str(self.version_dir()))
        acc.Reload()
        return {tag: [(e.step, e.value) for e in acc.Scalars(tag)] for tag in acc.Tags()["scalars"]}

    def checkpoints(self) -> list[Path]:
        return sorted(self.version_dir().glob("checkpoints/*.ckpt"))


def subprocess_env() -> dict[str, str]:
    env = dict(os.environ)
    env.setdefault("OMP_NUM_THREADS", "1")  # 2-core CI machines; DDP runs 2 processes
    env["PYTHONUNBUFFERED"] = "1"
    return env


def run_train(args: list[str], log_dir: Path, timeout: float = 600) -> Run:
    """``python -m train <args>`` from the repository root, logging under ``log_dir``."""
    cmd = [sys.executable, "-m", "train", *args,
           "--trainer.logger.init_args.save_dir", str(log_dir),
           "--trainer.default_root_dir", str(log_dir),
           "--trainer.enable_progress_bar", "false"]
    start = time.perf_counter()
    proc = subprocess.run(cmd, cwd=ROOT, env=subprocess_env(), capture_output=True, text=True, timeout=timeout)
    return Run(proc.returncode, proc.stdout + proc.stderr, time.perf_counter() - start, log_dir)


@pytest.fixture(scope="session")
def configs() -> Path:
    """The repository's ``configs/`` folder."""
    return CONFIGS


@pytest.fixture(scope="session")
def train_cli():
    """:func:`run_train`: ``python -m train <args>`` in a subprocess."""
    return run_train


@pytest.fixture(scope="session")
def env() -> dict[str, str]:
    """Environment for subprocesses (one OpenMP thread unless set)."""
    return subprocess_env()
