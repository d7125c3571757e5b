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

Bad input never ends in a traceback or the parser's 90-line usage: it is one line on stderr,
``train: error: <name>: expected <what>, got <what>`` (the option named as the user gives it,
:mod:`train.messages`), and exit status 2. What can be checked before Lightning starts is checked
then, so that a refused run leaves no log folder behind:

- the parser's errors: an unknown key (``--model.crf.gate.windw``: the model's ``crf`` is typed,
  :class:`crfdepth.config.CRFConfig`, so the parser knows every field of its five groups), a value of the
  wrong type, a missing ``--config`` file;
- the values the CRF's groups refuse (``--model.crf.gate.window 4``, :func:`train.options.check_crf`). The CRF's
  flat names of older commands, config files and checkpoints (``--model.crf "{mode: pixel}"``) are moved into
  their groups before the parser reads them (:func:`train.options.grouped_args`);
- the subcommand: ``fit`` or ``validate`` (Lightning's ``test`` and ``predict`` are not offered: the module
  has no test or predict step; ``validate`` scores a checkpoint on any data set);
- ``--seed_everything`` outside [0, 2**32 - 1] (:func:`train.messages.check_seed`), a ``fit`` of 0 epochs or
  steps (:func:`train.messages.check_fit_length`), an output folder that is a file
  (:func:`train.options.check_output_folders`);
- the ``trainer:`` values Lightning would refuse (``--trainer.max_epochs -3``,
  :func:`train.messages.check_trainer_values`) and an accelerator the machine does not have
  (``configs/ddp.yaml`` without a CUDA GPU, more GPUs than it has: :func:`train.options.check_accelerator`);
- the model's and the data's options (their constructors), and the data itself (no frames under the
  root, a bad split: the datasets are built before ``fit`` / ``validate`` starts);
- ``--ckpt_path``: read with ``torch.load(weights_only=True)`` only (a pickle that would run code is
  refused and never loaded; ``--weights_only false`` is refused), and it must be a checkpoint of this
  trainer (:func:`crfdepth.checkpoints.read_trainer_checkpoint`). A fit resumed from it must be the run
  that wrote it, whatever point it was saved at (mid-epoch, end of an epoch, end of the run): the same
  training frames, batch size and number of processes (:meth:`train.data.CRFDataModule.check_resumable`)
  and the same model options (:func:`train.options.check_model_options`; Lightning would otherwise replace them with
  the checkpoint's without a word). ``validate`` takes a checkpoint of any training run.
"""

from __future__ import annotations

import inspect
import logging
import os
import sys
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import torch
from jsonargparse import ArgumentError
from lightning.fabric.utilities.exceptions import MisconfigurationException
from lightning.pytorch.callbacks import ModelCheckpoint
from lightning.pytorch.cli import LightningArgumentParser, LightningCLI

from crfdepth.checkpoints import read_trainer_checkpoint
from crfdepth.errors import InputError
from train.data import CRFDataModule
from train.messages import (
    SUBCOMMANDS,
    check_checkpoint_values,
    check_fit_length,
    check_seed,
    check_trainer_values,
    parser_message,
    section_message,
    trainer_message,
)
from train.module import CRFDepthModule
from train.options import (
    OptionError,
    check_accelerator,
    check_crf,
    check_model_options,
    check_output_folders,
    grouped_args,
    grouped_crf,
)


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
            trainer.save_checkpoint(path, weights_only=self.save_weights_only)  # said: Lightning logs its default
            self.last_model_path = path  # a later save of "last" this epoch overwrites it, no "-v1"


#: The logger of Lightning's ``seed_everything``.
_SEED_LOGGER = "lightning.fabric.utilities.seed"

#: Lightning's ``ckpt_path`` keywords: resolved by the Trainer, nothing to read before it starts.
_CKPT_KEYWORDS = ("last", "hpc", "registry", "best")


def saved_training_run(checkpoint: Mapping[str, Any]) -> dict[str, Any] | None:
    """The training run a checkpoint belongs to: what :class:`~train.data.CRFDataModule` stored in it, or, in
    a checkpoint written before it stored it, the training loader's state (frames, batch size, processes)."""
    stored = checkpoint.get(CRFDataModule.__qualname__)
    if isinstance(stored, Mapping) and isinstance(stored.get("training_run"), Mapping):
        return dict(stored["training_run"])
    try:
        (loader,) = checkpoint["loops"]["fit_loop"]["state_dict"]["combined_loader"]
    except (KeyError, TypeError, ValueError):
        return None
    return dict(loader) if isinstance(loader, Mapping) else None


def _raised_in(exc: BaseException, *functions: Any) -> bool:
    """Whether one of ``functions`` is on the traceback of ``exc``."""
    codes = {f.__code__ for f in functions}
    tb = exc.__traceback__
    while tb is not None:
        if tb.tb_frame.f_code in codes:
            return True
        tb = tb.tb_next
    return False


class CRFDepthCLI(LightningCLI):
    """LightningCLI with a ``checkpoint:`` section for the always-present ModelCheckpoint, and the checks of
    the module docstring before Lightning starts. Its parser raises instead of printing the usage and
    exiting (``exit_on_error: false``); every refusal is an :class:`~crfdepth.errors.InputError`."""

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        kwargs["parser_kwargs"] = {"exit_on_error": False, **(kwargs.get("parser_kwargs") or {})}
        self._checkpoint: dict[str, Any] | None = None
        super().__init__(*args, **kwargs)

    @staticmethod
    def subcommands() -> dict[str, set[str]]:
        """Lightning's ``fit`` and ``validate``. Its ``test`` and ``predict`` are left out: the module has no
        test or predict step, so they would end in a traceback; ``validate`` scores any data set (one line
        naming the two, :func:`train.messages.parser_message`)."""
        return {name: skip for name, skip in LightningCLI.subcommands().items() if name in SUBCOMMANDS}

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
        if args is None or isinstance(args, (list, tuple)):  # the CRF's flat names by groups, for the typed parser
            args = grouped_args(list(sys.argv[1:] if args is None else args))
        try:
            if isinstance(args, list):
                self.config = parser.parse_args(args)  # Lightning's, without its warning about args and sys.argv
            else:
                super().parse_arguments(parser, args)
        except ArgumentError as exc:
            raise OptionError(parser_message(str(exc), *self._known_options(parser, args))) from None
        # Checked here, before Lightning seeds, logs or builds anything.
        subcommand = self.config.get("subcommand")
        config = self.config[subcommand] if subcommand else self.config
        check_accelerator(config.get("trainer") or {})
        check_trainer_values(config.get("trainer") or {})
        if subcommand == "fit":
            check_fit_length(config.get("trainer") or {})
        check_seed(config.get("seed_everything"))
        check_output_folders(config)
        check_checkpoint_values(config.get("checkpoint") or {})
        if config.get("model") is not None:
            check_crf(config["model"].get("crf"))
        if "weights_only" in config:
            if config["weights_only"] is False:
                raise InputError("--weights_only: expected true (checkpoints are read with torch.load(weights_only=True) "
                                 "only, so that reading one never runs code), got false")
            config["weights_only"] = True  # said, so Lightning neither guesses nor logs its default

    @staticmethod
    def _known_options(parser: LightningArgumentParser, args: Any) -> tuple[list[str], str | None]:
        """The option names of the subcommand in ``args`` (for "did you mean"), and the subcommand."""
        words = list(args) if isinstance(args, (list, tuple)) else sys.argv[1:]
        action = getattr(parser, "_subcommands_action", None)
        choices = getattr(action, "_name_parser_map", {}) if action is not None else {}
        subcommand = next((w for w in words if w in choices), None)
        sub = choices.get(subcommand, parser)
        return [o for a in sub._actions for o in a.option_strings if o.startswith("--")], subcommand

    def _parse_ckpt_path(self) -> None:
        """``--ckpt_path`` read and checked before anything starts (module docstring), then its model options
        taken over as Lightning's CLI does."""
        subcommand = self.config.get("subcommand")
        path = self.config[subcommand].get("ckpt_path") if subcommand else None
        if not path or (str(path) in _CKPT_KEYWORDS and not Path(str(path)).is_file()):
            return
        fitting = subcommand == "fit"
        checkpoint = read_trainer_checkpoint(path, name="--ckpt_path", lightning=True, resume=fitting)
        stored = {k: v for k, v in checkpoint["hyper_parameters"].items() if k != "_instantiator"}
        if "crf" in stored:  # flat names in a checkpoint written before the groups
            stored["crf"] = grouped_crf(stored["crf"])
        if fitting:
            check_model_options(self.config[subcommand].get("model"), stored)
        known = set(inspect.signature(CRFDepthModule.__init__).parameters) - {"self"}
        unknown = sorted(set(stored) - known)
        if unknown:
            raise InputError(f"--ckpt_path: expected a checkpoint of this trainer's model (hyper_parameters among "
                             f"{', '.join(sorted(known))}), got {path} with {', '.join(unknown)}")
        try:
            self.config = self.parser.parse_object({subcommand: {"model": stored}}, self.config)
        except ArgumentError as exc:
            raise InputError(f"--ckpt_path: expected a checkpoint of this trainer's model, got {path}, whose "
                             f"hyper_parameters do not parse: {parser_message(str(exc))}") from None
        self._checkpoint = checkpoint

    def instantiate_classes(self) -> None:
        """Lightning's, with a constructor's refusal named by its section (``--data.crop: ...``)."""
        try:
            super().instantiate_classes()
        except InputError as exc:
            for section, cls in (("model", CRFDepthModule), ("data", CRFDataModule), ("checkpoint", EpochCheckpoint)):
                if _raised_in(exc, cls.__init__):
                    parameters = inspect.signature(cls.__init__).parameters
                    raise InputError(section_message(section, exc, parameters)) from None
            raise
        except (MisconfigurationException, ValueError, TypeError) as exc:
            if _raised_in(exc, ModelCheckpoint.__init__):
                raise InputError(trainer_message(exc, "checkpoint", ModelCheckpoint)) from None
            raise

    def instantiate_trainer(self, **kwargs: Any):
        """Lightning's, after the datasets are built and a resumed run's data compared with the checkpoint's
        (so that their errors come before the Trainer's banner), with its refusals in one line."""
        if self.subcommand in SUBCOMMANDS:
            try:
                self.datamodule.setup(self.subcommand)
            except InputError as exc:  # "val_options: ..." is --data.val_options
                raise InputError(section_message("data", exc, inspect.signature(CRFDataModule.__init__).parameters)
                                 ) from None
            self._check_resumed_run(processes=None)
        try:
            return super().instantiate_trainer(**kwargs)
        except (MisconfigurationException, ValueError, TypeError) as exc:
            raise InputError(trainer_message(exc)) from None

    def _check_resumed_run(self, processes: int | None) -> None:
        """A fit from ``--ckpt_path`` trains the checkpoint's run: frames, batch size and (once the Trainer
        says how many) processes (:meth:`train.data.CRFDataModule.check_resumable`)."""
        saved = saved_training_run(self._checkpoint) if self._checkpoint is not None else None
        if saved is not None and self.subcommand == "fit":
            self.datamodule.check_resumable(saved, processes=processes)

    def before_fit(self) -> None:
        self._check_resumed_run(processes=self.trainer.world_size)
        self._say_seed()

    def before_validate(self) -> None:
        self._say_seed()

    def _set_seed(self) -> None:
        """Lightning's, without its "Seed set to N" line: said once the run starts (:meth:`_say_seed`), so that
        a refused run's first line on stderr is its error."""
        logger = logging.getLogger(_SEED_LOGGER)
        level = logger.level
        logger.setLevel(logging.WARNING)
        try:
            super()._set_seed()
        finally:
            logger.setLevel(level)

    def _say_seed(self) -> None:
        seed = self._get(self.config, "seed_everything")
        if seed is not False and seed is not None:
            logging.getLogger(_SEED_LOGGER).info("Seed set to %s", seed)


def main(args: list[str] | None = None) -> int:
    """Run the CLI on ``args`` (None = ``sys.argv[1:]``); the exit status.

    Every refusal is one line on stderr, ``train: error: ...``: the parser's (unknown keys, bad values)
    then exits through ``SystemExit(2)`` as the parser itself does; the others
    (:class:`~crfdepth.errors.InputError` from the checks, the model, the data, ``--ckpt_path``) return 2.
    """
    try:
        CRFDepthCLI(CRFDepthModule, CRFDataModule, args=args, seed_everything_default=0)
    except OptionError as exc:
        print(f"train: error: {exc}", file=sys.stderr)
        raise SystemExit(2) from None
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
