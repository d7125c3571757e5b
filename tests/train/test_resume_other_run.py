"""A resumed run is the run it resumes: ``python -m train fit --ckpt_path`` refuses the checkpoint of another
training run (other frames, batch size or model options) whatever point it was saved at, the middle of an
epoch, its end or the end of the run, in one line and before Lightning makes a log folder. The same
checkpoint resumes its own run, and ``validate`` takes it on any data.

The run: two synthetic frames of 64 x 192 (pixel mode), one frame a batch, checkpointed after every step:
``step1`` stops in the middle of epoch 0, ``step2`` at its end, ``last.ckpt`` is the finished run.
"""

from __future__ import annotations

import logging
import sys
from pathlib import Path

import pytest
import torch

from crfdepth.errors import InputError
from tests.train.conftest import CONFIGS

pytestmark = pytest.mark.filterwarnings("ignore::DeprecationWarning:lightning.pytorch.cli",
                                        "ignore:.*does not have many workers:UserWarning",
                                        "ignore:.*log_every_n_steps.*:UserWarning",
                                        "ignore:The dirpath has changed.*")

FRAMES = "{count: 2, height: 64, width: 192}"
VAL = "{count: 1, seed: 1000, height: 64, width: 192}"
DEBUG = ["--config", str(CONFIGS / "synthetic.yaml"), "--config", str(CONFIGS / "debug.yaml")]
QUIET = ["--trainer.limit_val_batches", "1", "--trainer.num_sanity_val_steps", "0",
         "--trainer.enable_progress_bar", "false"]
ANOTHER_RUN = "train: error: --ckpt_path: the checkpoint stopped in epoch 0 after {batches} batch(es) of another training run"


def _fit(args: list[str]) -> int:
    from train.__main__ import main

    try:
        return main(["fit", *args])
    except SystemExit as exc:
        return exc.code


@pytest.fixture(scope="module")
def run(tmp_path_factory) -> Path:
    """The checkpoints folder of the finished one-epoch run (module docstring)."""
    logs = tmp_path_factory.mktemp("run")
    argv, sys.argv = sys.argv, ["python -m train"]
    try:
        status = _fit([*DEBUG, "--data.train_options", FRAMES, "--data.val_options", VAL, *QUIET,
                       "--trainer.max_epochs", "1", "--trainer.logger.init_args.save_dir", str(logs),
                       "--trainer.default_root_dir", str(logs), "--checkpoint.every_n_train_steps", "1",
                       "--checkpoint.save_top_k", "-1", "--checkpoint.monitor", "null",
                       "--checkpoint.filename", "step{step}"])
    finally:
        sys.argv = argv
    assert status == 0
    (folder,) = {p.parent for p in logs.rglob("last.ckpt")}
    return folder


@pytest.fixture
def workdir(tmp_path, monkeypatch, caplog):
    monkeypatch.chdir(tmp_path)
    monkeypatch.setattr(sys, "argv", ["python -m train"])
    caplog.set_level(logging.INFO)
    return tmp_path


def _refusal(args: list[str], capsys, caplog, folder: Path) -> str:
    """The one line of a refused fit (status 2, nothing logged before it, no log folder)."""
    status = _fit(args)
    err = capsys.readouterr().err.splitlines()
    assert status == 2 and len(err) == 1, err
    assert not [r.getMessage() for r in caplog.records if r.name.startswith("lightning")]
    assert not (folder / "lightning_logs").exists()
    return err[0]


def test_the_checkpoints_are_where_the_docstring_says(run):
    for name, (epoch, batches) in {"step1.ckpt": (0, 1), "step2.ckpt": (0, 2), "last.ckpt": (0, 2)}.items():
        saved = torch.load(run / name, weights_only=True)["CRFDataModule"]["training_run"]
        assert (saved["epoch"], saved["batches"], saved["frames"], saved["batch_size"]) == (epoch, batches, 2, 1)


@pytest.mark.kitti
def test_a_finished_synthetic_run_does_not_train_on_over_kitti_raw(run, workdir, capsys, caplog, kitti_root):
    """The issue's case: the same model options (debug.yaml's), other data."""
    line = _refusal([*DEBUG[:1], str(CONFIGS / "kitti_raw.yaml"), *DEBUG[2:], "--data.root", str(kitti_root / "raw"),
                     "--trainer.max_epochs", "2", "--ckpt_path", str(run / "last.ckpt")], capsys, caplog, workdir)
    assert line.startswith(ANOTHER_RUN.format(batches=2) + " (frames 2 then, 13 now)")


@pytest.mark.parametrize("checkpoint, batches", [("step1.ckpt", 1), ("step2.ckpt", 2), ("last.ckpt", 2)])
def test_other_frames_are_refused_at_every_save_point(run, workdir, capsys, caplog, checkpoint, batches):
    other = "{count: 2, seed: 10, height: 64, width: 192}"  # as many frames, other scenes
    line = _refusal([*DEBUG, "--data.train_options", other, "--data.val_options", VAL, *QUIET,
                     "--trainer.max_epochs", "2", "--ckpt_path", str(run / checkpoint)], capsys, caplog, workdir)
    assert line.startswith(ANOTHER_RUN.format(batches=batches) + " (other frames, ")
    assert "(SHA-256 of their names)" in line


def test_another_batch_size_is_refused_at_the_end_of_the_run(run, workdir, capsys, caplog):
    line = _refusal([*DEBUG, "--data.train_options", FRAMES, "--data.val_options", VAL, *QUIET,
                     "--data.batch_size", "2", "--trainer.max_epochs", "2", "--ckpt_path", str(run / "last.ckpt")],
                    capsys, caplog, workdir)
    assert line == (ANOTHER_RUN.format(batches=2) + " (batch_size 1 then, 2 now); resume with the data, "
                    "data.batch_size and trainer.devices x trainer.num_nodes it was saved with, or train afresh "
                    "without --ckpt_path")


def test_other_model_options_are_refused(run, workdir, capsys, caplog):
    line = _refusal([*DEBUG, "--data.train_options", FRAMES, "--data.val_options", VAL, *QUIET,
                     "--model.crf.gate.enabled", "true", "--trainer.max_epochs", "2",
                     "--ckpt_path", str(run / "last.ckpt")], capsys, caplog, workdir)
    assert line.startswith("train: error: --model.crf.gate.enabled: expected the checkpoint's False when resuming "
                           "its run with --ckpt_path (a resumed run is the run it resumes), got True")


def test_the_run_itself_resumes_from_its_end(run, workdir, capsys):
    logs = workdir / "logs"
    status = _fit([*DEBUG, "--data.train_options", FRAMES, "--data.val_options", VAL, *QUIET,
                   "--trainer.max_epochs", "2", "--trainer.logger.init_args.save_dir", str(logs),
                   "--trainer.default_root_dir", str(logs), "--ckpt_path", str(run / "last.ckpt")])
    assert status == 0, capsys.readouterr().err[-3000:]
    (last,) = logs.rglob("last.ckpt")
    assert torch.load(last, weights_only=True)["global_step"] == 4  # two more steps: epoch 1


def test_validate_takes_a_checkpoint_of_any_run(run, workdir, capsys):
    from train.__main__ import main

    status = main(["validate", *DEBUG, "--data.val_options", "{count: 1, seed: 77, height: 64, width: 192}",
                   *QUIET, "--trainer.logger", "false", "--ckpt_path", str(run / "last.ckpt")])
    assert status == 0, capsys.readouterr().err[-3000:]


def test_the_data_module_refuses_it_in_lightnings_restore_too(run, workdir):
    """Without the command line (``trainer.fit(ckpt_path=...)``), the data module's ``load_state_dict``
    refuses the finished run's checkpoint of other frames."""
    from train.__main__ import CRFDepthCLI
    from train.data import CRFDataModule
    from train.module import CRFDepthModule

    cli = CRFDepthCLI(CRFDepthModule, CRFDataModule, run=False, args=[
        *DEBUG, "--data.train_options", "{count: 3, height: 64, width: 192}", "--data.val_options", VAL, *QUIET,
        "--trainer.max_epochs", "2", "--trainer.logger", "false", "--trainer.default_root_dir", str(workdir)])
    with pytest.raises(InputError, match=r"^--ckpt_path: the checkpoint stopped in epoch 0 after 2 batch\(es\) of "
                                         r"another training run \(frames 2 then, 3 now\)"):
        cli.trainer.fit(cli.model, cli.datamodule, ckpt_path=str(run / "last.ckpt"), weights_only=True)


def test_another_number_of_processes_is_named():
    from train.data import CRFDataModule

    data = CRFDataModule(train_options={"count": 2, "height": 64, "width": 192}, flip=0.0)
    data.setup("fit")
    saved = {**data.training_run(processes=1), "epoch": 3, "batches": 0}
    data.check_resumable(saved, processes=1)  # the same run
    with pytest.raises(InputError, match=r"stopped in epoch 3 after 0 batch\(es\) of another training run "
                                         r"\(processes 1 then, 2 now\)"):
        data.check_resumable(saved, processes=2)
    data.check_resumable({k: v for k, v in saved.items() if k != "frames_sha256"}, processes=1)  # older checkpoints
