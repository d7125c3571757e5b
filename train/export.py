"""Turn a trainer checkpoint into a crfdepth weights file (JSON, :mod:`crfdepth.checkpoints`).

::

    python -m train.export lightning_logs/kitti_weights/version_0/checkpoints/best.ckpt \\
        --out crfdepth/weights/kitti.json --config configs/kitti_weights.yaml \\
        --command "python -m train fit --config configs/kitti_weights.yaml"

The file holds the model's complete configuration with the learned values, and an
``"about"`` record written from the checkpoint: the epoch and step, the monitored
validation score of the checkpoint, the training arguments (``hyper_parameters``), the
data module's arguments (``datamodule_hyper_parameters``: layout, root, split, hold-out),
the YAML config given with ``--config`` (verbatim) and the ``--command`` text. That is
what ``crfdepth/weights/README.md`` refers to for the shipped weights.

``--calibrate-std`` (needs ``--config``) first fits the std to the config's training
frames (:func:`train.calibrate.calibrate_std`, whole frames, no flip): the predictive std's
weights, or the posterior std's scale; ``about`` records the frames and the values before
and after.
"""

from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path
from typing import Any, Sequence

import torch

from crfdepth.checkpoints import load_model, read_trainer_checkpoint, save_weights
from crfdepth.errors import BAD_INPUT, InputError
from crfdepth.io.file_errors import FileError
from train.calibrate import calibrate_std


def _plain(value: Any) -> Any:
    """``value`` with tensors, paths and tuples made JSON-friendly."""
    if isinstance(value, dict):
        return {str(k): _plain(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_plain(v) for v in value]
    if isinstance(value, torch.Tensor):
        return value.item() if value.numel() == 1 else value.tolist()
    if isinstance(value, (str, int, float, bool)) or value is None:
        return value
    return str(value)


def describe_checkpoint(path: Path) -> dict[str, Any]:
    """The ``about`` record of a Lightning checkpoint (see the module docstring)."""
    ckpt = torch.load(path, map_location="cpu", weights_only=True)
    about: dict[str, Any] = {"checkpoint": path.name, "epoch": ckpt.get("epoch"), "global_step": ckpt.get("global_step")}
    for key, state in (ckpt.get("callbacks") or {}).items():
        if str(key).startswith("ModelCheckpoint") and isinstance(state, dict):
            about["monitor"] = state.get("monitor")
            about["best_model_score"] = _plain(state.get("best_model_score"))
            about["best_model_path"] = Path(str(state.get("best_model_path") or "")).name or None
    about["hyper_parameters"] = _plain(ckpt.get("hyper_parameters") or {})
    about["datamodule_hyper_parameters"] = _plain(ckpt.get("datamodule_hyper_parameters") or {})
    return about


def calibrate(model, config: Path) -> dict[str, Any]:
    """Calibrate ``model``'s std scale on the training frames of ``config``'s ``data`` section."""
    import yaml

    from train.data import CRFDataModule

    if not config.is_file():
        raise InputError(f"--config: no such file: {config}")
    data = dict((yaml.safe_load(config.read_text(encoding="utf-8")) or {}).get("data") or {})
    datamodule = CRFDataModule(**{**data, "flip": 0.0, "crop": None, "thin": None})  # whole frames, all points
    train, _ = datamodule.build_datasets()
    record = calibrate_std(model, (train[i] for i in range(len(train))))
    print(f"{record['uncertainty']} std fitted on {record['frames']} training frames: {record['before']} -> "
          f"{record['after']}")
    return record


def same_file(a: Path, b: Path) -> bool:
    """Whether paths ``a`` and ``b`` name one file: the same path once resolved (``./x``, ``d/../x``, a
    symlink), or, both existing, the same inode (a hard link)."""
    try:
        if Path(a).resolve() == Path(b).resolve():
            return True
        return Path(a).exists() and Path(b).exists() and os.path.samefile(a, b)
    except (OSError, RuntimeError):  # a symlink loop, an unreadable folder: not provably the same
        return False


def check_out(out: Path, inputs: dict[str, Path | None]) -> None:
    """Refuse an ``--out`` that would replace one of the ``inputs`` (``{option name: path}``) it is written from,
    or that is a folder."""
    for name, path in inputs.items():
        if path is not None and same_file(out, path):
            raise InputError(f"--out: expected a file other than the {name} it is written from, got {out}, which "
                             f"is {name} {path}; writing it would replace its input")
    if out.is_dir():
        raise InputError(f"--out: expected the path of a .json file to write, got {out}, which is a folder")


class _Parser(argparse.ArgumentParser):
    """Usage errors in one line, ``train.export: error: --out: ...``, exit status 2."""

    def error(self, message: str):
        self.exit(2, f"train.export: error: {message.removeprefix('argument ')}\n")


def main(argv: Sequence[str] | None = None) -> int:
    parser = _Parser(prog="python -m train.export", description=__doc__.split("\n\n")[0])
    parser.add_argument("checkpoint", type=Path, help="a Lightning .ckpt of the trainer")
    parser.add_argument("--out", type=Path, required=True, help="the weights file to write (.json)")
    parser.add_argument("--config", type=Path, default=None, help="the training YAML, stored verbatim")
    parser.add_argument("--command", default=None, help="the command that trained the checkpoint")
    parser.add_argument("--note", default=None, help="free text stored as about.note (e.g. validation numbers)")
    parser.add_argument("--uncertainty", choices=("predictive", "posterior"), default=None,
                        help="the std the exported model computes (default: the checkpoint's; one saved before "
                             "the predictive std existed has the posterior)")
    parser.add_argument("--calibrate-std", action="store_true",
                        help="fit the std (predictive: its weights; posterior: its scale) to --config's training frames")
    args = parser.parse_args(argv)
    try:
        check_out(args.out, {"checkpoint": args.checkpoint, "--config": args.config})
        if args.calibrate_std and args.config is None:
            raise InputError("--calibrate-std: needs --config (its data section names the training frames)")
        read_trainer_checkpoint(args.checkpoint, name="checkpoint")  # a bad file in one line, nothing of it run
        model = load_model(args.checkpoint, overrides=None if args.uncertainty is None
                           else {"uncertainty": args.uncertainty})
        about = describe_checkpoint(args.checkpoint)
        if args.calibrate_std:
            about["std_calibration"] = calibrate(model, args.config)
        if args.config is not None:
            if not args.config.is_file():
                raise InputError(f"--config: no such file: {args.config}")
            about["config_file"] = str(args.config)
            about["config"] = args.config.read_text(encoding="utf-8")
        if args.command is not None:
            about["command"] = args.command
        if args.note is not None:
            about["note"] = args.note
        out = save_weights(model, args.out, about)
    except (*BAD_INPUT, FileError) as exc:
        print(f"train.export: error: {exc}", file=sys.stderr)
        return 2
    print(f"wrote {out}: " + ", ".join(f"{k} {v:.4g}" for k, v in model.weights().items()))
    return 0


if __name__ == "__main__":
    sys.exit(main())
