"""Resuming training from a mid-epoch checkpoint (``--ckpt_path``) gives the weights of an uninterrupted run.

Six synthetic frames in batches of two (three optimiser steps an epoch), two epochs, shuffled, with
every augmentation on (flip, crop, thinning), checkpointed every step: step 2 stops in epoch 0, step
3 at its end, step 4 in epoch 1. Resumed from any of them, the run ends with the uninterrupted run's weights: the loader
goes on after the trained batches in the same order (:class:`train.sampling.EpochOrder`) with the same
draws (seeded by seed, epoch and frame), and Lightning restores the optimiser. On one CPU the runs are
the same computations in the same order, so they agree to rounding; the test allows 1e-6. The control
resumes from the same checkpoint without the loader's saved position (what Lightning does with a plain
``DataLoader``: the epoch starts again from its first batch) and ends measurably elsewhere.
"""

from __future__ import annotations

import sys

import pytest
import torch

from tests.train.conftest import CONFIGS

pytestmark = pytest.mark.filterwarnings("ignore::DeprecationWarning:lightning.pytorch.cli",
                                        "ignore:.*does not have many workers:UserWarning",
                                        "ignore:.*log_every_n_steps.*:UserWarning",
                                        "ignore:.*resuming from a checkpoint that ended before the epoch.*",
                                        "ignore:The dirpath has changed.*")


def _fit(log_dir, ckpt_path=None, extra=()):
    """The trained parameters of a two-epoch run (module docstring), and its checkpoint folder."""
    from train.__main__ import CRFDepthCLI
    from train.data import CRFDataModule
    from train.module import CRFDepthModule

    args = ["--config", str(CONFIGS / "synthetic.yaml"), "--config", str(CONFIGS / "debug.yaml"),
            "--data.train_options", "{count: 6, height: 48, width: 128}",
            "--data.val_options", "{count: 1, seed: 1000, height: 48, width: 128}",
            "--data.batch_size", "2", "--data.crop", "[40, 112]", "--data.thin", "[0.5, 0.9]",
            "--trainer.max_epochs", "2", "--trainer.limit_train_batches", "1.0", "--trainer.limit_val_batches", "0",
            "--trainer.num_sanity_val_steps", "0", "--trainer.logger", "false",
            "--trainer.default_root_dir", str(log_dir), "--trainer.enable_progress_bar", "false",
            "--checkpoint.monitor", "null", "--checkpoint.save_last", "false", "--checkpoint.save_top_k", "-1",
            "--checkpoint.every_n_train_steps", "1", "--checkpoint.dirpath", str(log_dir / "ckpt"),
            "--checkpoint.filename", "step{step}", *extra]
    cli = CRFDepthCLI(CRFDepthModule, CRFDataModule, args=args, run=False, seed_everything_default=0)
    cli.trainer.fit(cli.model, cli.datamodule, ckpt_path=None if ckpt_path is None else str(ckpt_path))
    assert cli.trainer.global_step == 6
    return {n: p.detach().clone() for n, p in cli.model.named_parameters() if p.requires_grad}


def _largest_difference(a, b) -> float:
    return max(float((a[n] - b[n]).abs().max()) for n in a)


@pytest.fixture(scope="module")
def uninterrupted(tmp_path_factory):
    argv, sys.argv = sys.argv, ["python -m train"]  # the CLI reads only its args
    try:
        folder = tmp_path_factory.mktemp("uninterrupted")
        return _fit(folder), folder / "ckpt"
    finally:
        sys.argv = argv


@pytest.mark.parametrize("step", [2, 3, 4])
def test_resuming_mid_epoch_gives_the_uninterrupted_weights(tmp_path, monkeypatch, uninterrupted, step):
    monkeypatch.setattr(sys, "argv", ["python -m train"])
    weights, checkpoints = uninterrupted
    checkpoint = checkpoints / f"step{step}.ckpt"
    saved = torch.load(checkpoint, weights_only=True)
    (loader,) = saved["loops"]["fit_loop"]["state_dict"]["combined_loader"]
    assert (loader["epoch"], loader["batches"]) == {2: (0, 2), 3: (0, 3), 4: (1, 1)}[step]
    resumed = _fit(tmp_path, checkpoint)
    worst = _largest_difference(resumed, weights)
    print(f"\nresumed from step {step}: largest weight difference to the uninterrupted run {worst:.2e}")
    assert worst < 1e-6
    if step == 3:
        return  # the end of an epoch: the next one starts at its first batch either way
    # Control: the same checkpoint without the loader's position restarts the epoch at its first batch.
    del saved["loops"]["fit_loop"]["state_dict"]["combined_loader"]
    torch.save(saved, tmp_path / "plain.ckpt")
    plain = _fit(tmp_path / "plain", tmp_path / "plain.ckpt")
    missed = _largest_difference(plain, weights)
    print(f"without the loader's position: {missed:.2e}")
    assert missed > 1e-3


def test_resuming_with_another_batch_size_is_refused_in_one_line(tmp_path, monkeypatch, capsys, uninterrupted):
    from train.__main__ import main

    monkeypatch.setattr(sys, "argv", ["python -m train"])
    _, checkpoints = uninterrupted
    status = main(["fit", "--config", str(CONFIGS / "synthetic.yaml"), "--config", str(CONFIGS / "debug.yaml"),
                   "--data.train_options", "{count: 6, height: 48, width: 128}",
                   "--data.val_options", "{count: 1, seed: 1000, height: 48, width: 128}",
                   "--data.batch_size", "3", "--trainer.max_epochs", "2", "--trainer.limit_train_batches", "1.0",
                   "--trainer.limit_val_batches", "0", "--trainer.num_sanity_val_steps", "0",
                   "--trainer.logger", "false", "--trainer.default_root_dir", str(tmp_path),
                   "--trainer.enable_progress_bar", "false", "--checkpoint.monitor", "null",
                   "--ckpt_path", str(checkpoints / "step2.ckpt")])
    message = capsys.readouterr().err.strip().splitlines()[-1]
    assert status == 2
    assert message.startswith("train: error: --ckpt_path: the checkpoint stopped in epoch 0 after 2 batch(es)")
    assert "batch_size 2 then, 3 now" in message


@pytest.mark.slow
def test_ddp_over_two_cpu_processes_resumes_mid_epoch_to_the_same_weights(tmp_path, env):
    """Each rank reads its share of the epoch (EpochOrder is a DistributedSampler); the position saved by
    rank 0 holds for both, their shares being equal. 8 frames, 4 steps an epoch per rank."""
    import subprocess

    def fit(out, *extra):
        args = [sys.executable, "-m", "train", "fit", "--config", str(CONFIGS / "synthetic.yaml"),
                "--config", str(CONFIGS / "debug.yaml"), "--data.train_options", "{count: 8, height: 48, width: 128}",
                "--data.val_options", "{count: 1, seed: 1000, height: 48, width: 128}", "--data.crop", "[40, 112]",
                "--data.thin", "[0.5, 0.9]", "--trainer.max_epochs", "2", "--trainer.limit_train_batches", "1.0",
                "--trainer.limit_val_batches", "0", "--trainer.num_sanity_val_steps", "0", "--trainer.logger", "false",
                "--trainer.default_root_dir", str(out), "--trainer.enable_progress_bar", "false",
                "--trainer.accelerator", "cpu", "--trainer.devices", "2", "--trainer.strategy", "ddp",
                "--checkpoint.monitor", "null", "--checkpoint.save_last", "false", "--checkpoint.save_top_k", "-1",
                "--checkpoint.every_n_train_steps", "1", "--checkpoint.dirpath", str(out / "ckpt"),
                "--checkpoint.filename", "step{step}", *extra]
        proc = subprocess.run(args, cwd=CONFIGS.parent, env=env, capture_output=True, text=True, timeout=600)
        assert proc.returncode == 0, proc.stdout[-2000:] + proc.stderr[-3000:]
        return torch.load(out / "ckpt" / "step8.ckpt", weights_only=True)

    whole = fit(tmp_path / "whole")
    saved = torch.load(tmp_path / "whole" / "ckpt" / "step6.ckpt", weights_only=True)
    (loader,) = saved["loops"]["fit_loop"]["state_dict"]["combined_loader"]
    assert (loader["epoch"], loader["batches"], loader["processes"]) == (1, 2, 2)
    resumed = fit(tmp_path / "resumed", "--ckpt_path", str(tmp_path / "whole" / "ckpt" / "step6.ckpt"))
    worst = max(float((whole["state_dict"][k].float() - resumed["state_dict"][k].float()).abs().max())
                for k in whole["state_dict"])
    print(f"\nDDP, 2 CPU processes, resumed from step 6: largest weight difference {worst:.2e}")
    assert worst < 1e-6
