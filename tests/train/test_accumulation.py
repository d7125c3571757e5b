"""Gradient accumulation through the CLI: ``--trainer.accumulate_grad_batches N``.

The module uses Lightning's automatic optimisation (no manual ``optimizer_step``, no
scheduler stepped per batch), so accumulation is Lightning's alone: it scales each
batch's loss by ``1 / N`` and steps once every ``N`` batches. The training loss is the
mean over a batch's images of a per-image mean (``depth_loss``), so with every image
holding target pixels

    grad(batch of frames a, b) = (g_a + g_b) / 2 = grad(a) / 2 + grad(b) / 2

which is what two accumulated batches of one frame sum to. The two runs can differ only
where a batch of two differs from two batches of one: the batched CG freezes each frame
when it converges, so a frame's solve agrees with its solve alone within the solver's
tolerance (docs/design.md section 10, "Batched inference"). Training solves run in
float64 to ``grad_rtol`` = 1e-10, the adjoint to ``rtol`` (section 4), so gradients agree
to about 1e-5 relative; the test allows 1e-4.
"""

from __future__ import annotations

import sys

import pytest
import torch
from lightning.pytorch.callbacks import Callback

from train.__main__ import CRFDepthCLI
from train.data import CRFDataModule
from train.module import CRFDepthModule

pytestmark = pytest.mark.filterwarnings("ignore::DeprecationWarning:lightning.pytorch.cli",
                                        "ignore:.*does not have many workers:UserWarning",
                                        "ignore:.*log_every_n_steps.*:UserWarning")


class GradientAtStep(Callback):
    """Records every trainable parameter's gradient and value just before each optimiser step."""

    def __init__(self) -> None:
        self.grads: list[dict[str, torch.Tensor]] = []

    def on_before_optimizer_step(self, trainer, pl_module, optimizer) -> None:
        self.grads.append({n: p.grad.detach().clone() for n, p in pl_module.named_parameters() if p.requires_grad})


def _one_step(tmp_path, configs, batch_size: int, accumulate: int) -> tuple[GradientAtStep, dict[str, torch.Tensor]]:
    """One optimiser step on the same two synthetic frames, configured through the CLI."""
    args = ["--config", str(configs / "synthetic.yaml"), "--config", str(configs / "debug.yaml"),
            "--data.train_options", "{count: 2, height: 64, width: 192}",
            "--data.val_options", "{count: 1, seed: 1000, height: 64, width: 192}",
            "--data.flip", "0", "--data.shuffle", "false", "--data.batch_size", str(batch_size),
            "--trainer.accumulate_grad_batches", str(accumulate),
            "--trainer.max_steps", "1", "--trainer.limit_val_batches", "0", "--trainer.num_sanity_val_steps", "0",
            "--trainer.logger", "false", "--trainer.default_root_dir", str(tmp_path),
            "--trainer.enable_progress_bar", "false", "--checkpoint.monitor", "null", "--checkpoint.save_last", "false"]
    cli = CRFDepthCLI(CRFDepthModule, CRFDataModule, args=args, run=False, seed_everything_default=0)
    assert cli.trainer.accumulate_grad_batches == accumulate
    assert isinstance(cli.datamodule, CRFDataModule) and cli.datamodule.batch_size == batch_size
    recorder = GradientAtStep()
    cli.trainer.callbacks.append(recorder)
    cli.trainer.fit(cli.model, cli.datamodule)
    assert cli.trainer.global_step == 1
    params = {n: p.detach().clone() for n, p in cli.model.named_parameters() if p.requires_grad}
    return recorder, params


def test_two_accumulated_frames_step_like_one_batch_of_two(tmp_path, configs, monkeypatch):
    monkeypatch.setattr(sys, "argv", ["python -m train"])  # the CLI reads only ``args``
    accumulated, params_acc = _one_step(tmp_path / "acc", configs, batch_size=1, accumulate=2)
    batched, params_batch = _one_step(tmp_path / "batch", configs, batch_size=2, accumulate=1)
    first, _ = _one_step(tmp_path / "first", configs, batch_size=1, accumulate=1)  # frame a alone
    assert len(accumulated.grads) == len(batched.grads) == 1  # one optimiser step each
    (g_acc,), (g_batch,) = accumulated.grads, batched.grads
    assert g_acc.keys() == g_batch.keys() and len(g_acc) >= 7
    worst = max(float((g_acc[n] - g_batch[n]).abs().max() / g_batch[n].abs().max().clamp_min(1e-12)) for n in g_acc)
    print(f"\naccumulated 2 x 1 frame vs 1 batch of 2: largest relative gradient difference {worst:.2e}")
    assert worst < 1e-4
    # The comparison tells one frame from two: frame a's gradient alone is far from the mean.
    alone = max(float((first.grads[0][n] - g_batch[n]).abs().max() / g_batch[n].abs().max()) for n in g_acc)
    print(f"frame a alone vs the batch of two: {alone:.2e}")
    assert alone > 1e-2
    for name in params_acc:  # Adam's first step is lr * g / (|g| + eps): equal gradients, equal weights
        torch.testing.assert_close(params_acc[name], params_batch[name], rtol=1e-5, atol=1e-6)
