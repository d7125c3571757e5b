"""Command line of the trainer: ``python -m train {fit,validate} --config configs/....yaml``.

A :class:`~lightning.pytorch.cli.LightningCLI` over :class:`~train.module.CRFDepthModule`
(``model:``) and :class:`~train.data.CRFDataModule` (``data:``); the YAML files under
``configs/`` name classes and values only (later ``--config`` files and ``--key value``
flags override earlier ones). A ``checkpoint:`` section configures the
:class:`~lightning.pytorch.callbacks.ModelCheckpoint` that is always added: by default it
keeps the best epoch by ``val/rmse`` (mode min) and the last one.

Examples::

    python -m train fit --config configs/synthetic.yaml --config configs/debug.yaml
    python -m train fit --config configs/kitti_raw.yaml --data.root /data/kitti/raw
    python -m train fit --config configs/kitti_raw.yaml --config configs/ddp.yaml
    python -m train fit --print_config --config configs/synthetic.yaml

Bad input in the data (no frames under the root, a bad split) ends with exit status 2 and
a one-line message; unknown config keys are reported by the CLI parser (status 2). So does
an accelerator the machine does not have (``configs/ddp.yaml`` on a machine without a CUDA
GPU, or more GPUs than it has), checked before Lightning starts
(:func:`check_accelerator`).
"""

from __future__ import annotations

import os
import sys
from collections.abc import Mapping
from typing import Any

import torch
from lightning.pytorch.callbacks import ModelCheckpoint
from lightning.pytorch.cli import LightningArgumentParser, LightningCLI

from crfdepth.errors import InputError
from train.data import CRFDataModule
from train.module import CRFDepthModule


class EpochCheckpoint(ModelCheckpoint):
    """``ModelCheckpoint`` whose ``last.ckpt`` is always the latest epoch's.

    Lightning (2.6) writes ``last.ckpt`` only when a top-k checkpoint is saved, so with a
    monitored score it holds the best epoch, not the last: a recipe that ships "the last
    epoch of a fixed schedule" would silently ship the best-validation one. This writes it
    after every validation (not the sanity check) as well.
    """

    @property
    def state_key(self) -> str:  # ModelCheckpoint's key: a checkpoint resumes with either class
        return super().state_key.replace(type(self).__qualname__, ModelCheckpoint.__qualname__, 1)

    def on_validation_end(self, trainer, pl_module) -> None:
        super().on_validation_end(trainer, pl_module)
        if self.save_last and not trainer.sanity_checking and self.dirpath is not None:
            path = os.path.join(self.dirpath, self.CHECKPOINT_NAME_LAST + self.FILE_EXTENSION)
            trainer.save_checkpoint(path)
            self.last_model_path = path  # a later save of "last" this epoch overwrites it, no "-v1"


_CPU_DDP = "--trainer.accelerator cpu --trainer.devices 2"


def _requested_gpus(devices: Any) -> int | None:
    """How many GPUs Lightning's ``devices`` value asks for (an index list: the highest + 1);
    None = any number ("auto", -1) or a value Lightning itself will report."""
    try:
        if isinstance(devices, str):
            text = devices.strip()
            if text in ("auto", "-1"):
                return None
            if "," in text:  # "0,1": device indices
                devices = [int(i) for i in text.split(",") if i.strip()]
            else:
                devices = int(text)
        if isinstance(devices, (list, tuple)):
            return max(int(i) for i in devices) + 1 if devices else None
        if isinstance(devices, int) and not isinstance(devices, bool):
            return None if devices == -1 else devices
    except (TypeError, ValueError):
        pass
    return None


def check_accelerator(trainer: Mapping[str, Any]) -> None:
    """Refuse a ``trainer.accelerator`` / ``trainer.devices`` this machine does not have.

    Lightning would fail later with a traceback (``MisconfigurationException``); this is one
    line that names the option and the way to run the same DDP on CPU processes.

    Raises:
        InputError: ``gpu`` / ``cuda`` without a CUDA GPU, more GPUs (or a higher GPU index)
            than there are, or ``mps`` without Apple's Metal backend.
    """
    accelerator = trainer.get("accelerator")
    if not isinstance(accelerator, str):
        return  # "auto" by default; an Accelerator object is Lightning's to check
    name = accelerator.strip().lower()
    if name in ("gpu", "cuda"):
        available = torch.cuda.device_count() if torch.cuda.is_available() else 0
        if available == 0:
            ddp = "ddp" in str(trainer.get("strategy") or "").lower()
            fix = f"{_CPU_DDP} (DDP over 2 CPU processes)" if ddp else "--trainer.accelerator cpu"
            raise InputError(f"--trainer.accelerator: expected a device this machine has, got {accelerator!r} "
                             f"on a machine without a CUDA GPU; likely fix: {fix}")
        wanted = _requested_gpus(trainer.get("devices"))
        if wanted is not None and wanted > available:
            raise InputError(
                f"--trainer.devices: expected at most {available} GPU{'s' if available != 1 else ''} "
                f"(the CUDA GPUs of this machine), got {trainer.get('devices')!r}; likely fix: "
                "--trainer.devices -1 (all of them)")
    elif name == "mps" and not torch.backends.mps.is_available():
        raise InputError(
            f"--trainer.accelerator: expected a device this machine has, got {accelerator!r} without Apple's "
            "Metal backend (torch.backends.mps.is_available() is False); likely fix: --trainer.accelerator cpu")


class CRFDepthCLI(LightningCLI):
    """LightningCLI with a ``checkpoint:`` section for the always-present ModelCheckpoint."""

    def add_arguments_to_parser(self, parser: LightningArgumentParser) -> None:
        parser.add_lightning_class_args(EpochCheckpoint, "checkpoint")
        parser.set_defaults({
            "checkpoint.monitor": "val/rmse",
            "checkpoint.mode": "min",
            "checkpoint.save_last": True,
            "checkpoint.filename": "epoch{epoch:03d}-rmse{val/rmse:.1f}",
            "checkpoint.auto_insert_metric_name": False,
        })

    def parse_arguments(self, parser: LightningArgumentParser, args: Any) -> None:
        super().parse_arguments(parser, args)
        # Checked here, before Lightning seeds, logs or builds anything.
        subcommand = self.config.get("subcommand")
        config = self.config[subcommand] if subcommand else self.config
        check_accelerator(config.get("trainer") or {})


def main(args: list[str] | None = None) -> int:
    """Run the CLI on ``args`` (None = ``sys.argv[1:]``); the exit status.

    Parser errors (unknown keys, bad values) exit through ``SystemExit`` as the CLI
    parser does; :class:`~crfdepth.errors.InputError` from the data, the model or
    :func:`check_accelerator` becomes a one-line message on stderr and status 2.
    """
    try:
        CRFDepthCLI(CRFDepthModule, CRFDataModule, args=args, seed_everything_default=0)
    except InputError as exc:
        print(f"train: error: {exc}", file=sys.stderr)
        return 2
    # Lightning leaves DDP's process group up; gloo's threads outliving the interpreter can abort the
    # process at exit (SIGABRT after a finished run). Left after success only: on an error a rank may
    # still be inside a collective.
    if torch.distributed.is_available() and torch.distributed.is_initialized():
        torch.distributed.destroy_process_group()
    return 0


if __name__ == "__main__":
    sys.exit(main())
