"""Fixtures of the trainer tests: run ``python -m train`` and read what it logged; build the
same CLI in this process and take one optimiser step.

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
import torch
from lightning.pytorch.callbacks import Callback

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


class GradientAtStep(Callback):
    """Records every trainable parameter's gradient just before each optimiser step."""

    def __init__(self) -> None:
        self.grads: list[dict[str, torch.Tensor]] = []

    def on_before_optimizer_step(self, trainer, pl_module, optimizer) -> None:
        self.grads.append({n: p.grad.detach().clone() for n, p in pl_module.named_parameters() if p.requires_grad})


@dataclass
class Step:
    """What :func:`one_step` leaves: the gradients at each optimiser step, the parameters after."""

    grads: list[dict[str, torch.Tensor]]
    params: dict[str, torch.Tensor]
    cli: object


def one_step(log_dir: Path, args: list[str]) -> Step:
    """``python -m train fit`` built in this process (``CRFDepthCLI(..., run=False)``) on two synthetic
    frames of 64 x 192 (pixel mode, no flip, no shuffle, no validation) with ``args`` last, fitted
    until one optimiser step."""
    from train.__main__ import CRFDepthCLI
    from train.data import CRFDataModule
    from train.module import CRFDepthModule

    base = ["--config", str(CONFIGS / "synthetic.yaml"), "--config", str(CONFIGS / "debug.yaml"),
            "--data.train_options", "{count: 2, height: 64, width: 192}",
            "--data.val_options", "{count: 1, seed: 1000, height: 64, width: 192}",
            "--data.flip", "0", "--data.shuffle", "false",
            "--trainer.max_steps", "1", "--trainer.limit_val_batches", "0", "--trainer.num_sanity_val_steps", "0",
            "--trainer.logger", "false", "--trainer.default_root_dir", str(log_dir),
            "--trainer.enable_progress_bar", "false", "--checkpoint.monitor", "null", "--checkpoint.save_last", "false"]
    cli = CRFDepthCLI(CRFDepthModule, CRFDataModule, args=[*base, *args], run=False, seed_everything_default=0)
    recorder = GradientAtStep()
    cli.trainer.callbacks.append(recorder)
    cli.trainer.fit(cli.model, cli.datamodule)
    assert cli.trainer.global_step == 1
    params = {n: p.detach().clone() for n, p in cli.model.named_parameters() if p.requires_grad}
    return Step(recorder.grads, params, cli)


@pytest.fixture
def train_step(monkeypatch):
    """:func:`one_step`, with ``sys.argv`` cleared (the CLI reads only its ``args``)."""
    monkeypatch.setattr(sys, "argv", ["python -m train"])
    return one_step
