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
a one-line message; unknown config keys are reported by the CLI parser (status 2).
"""

from __future__ import annotations

import os
import sys

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
    def state_key(self) -> str:  # ModelCheckpoint's key, so checkpoints read the same as before
        return super().state_key.replace(type(self).__qualname__, ModelCheckpoint.__qualname__, 1)

    def on_validation_end(self, trainer, pl_module) -> None:
        super().on_validation_end(trainer, pl_module)
        if self.save_last and not trainer.sanity_checking and self.dirpath is not None:
            path = os.path.join(self.dirpath, self.CHECKPOINT_NAME_LAST + self.FILE_EXTENSION)
            trainer.save_checkpoint(path)
            self.last_model_path = path  # a later save of "last" this epoch overwrites it, no "-v1"


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


def main(args: list[str] | None = None) -> int:
    """Run the CLI on ``args`` (None = ``sys.argv[1:]``); the exit status.

    Parser errors (unknown keys, bad values) exit through ``SystemExit`` as the CLI
    parser does; :class:`~crfdepth.errors.InputError` from the data or the model becomes a
    one-line message on stderr and status 2.
    """
    try:
        CRFDepthCLI(CRFDepthModule, CRFDataModule, args=args, seed_everything_default=0)
    except InputError as exc:
        print(f"train: error: {exc}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
