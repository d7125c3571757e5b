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

import pytest
import torch

pytestmark = pytest.mark.filterwarnings("ignore::DeprecationWarning:lightning.pytorch.cli",
                                        "ignore:.*does not have many workers:UserWarning",
                                        "ignore:.*log_every_n_steps.*:UserWarning")


def _relative(grads: dict[str, torch.Tensor], ref: dict[str, torch.Tensor]) -> float:
    """The largest ``max |g - g_ref| / max |g_ref|`` over the parameters."""
    return max(float((grads[n] - ref[n]).abs().max() / ref[n].abs().max().clamp_min(1e-12)) for n in ref)


def test_two_accumulated_frames_step_like_one_batch_of_two(tmp_path, train_step):
    accumulated = train_step(tmp_path / "acc", ["--data.batch_size", "1", "--trainer.accumulate_grad_batches", "2"])
    batched = train_step(tmp_path / "batch", ["--data.batch_size", "2"])
    first = train_step(tmp_path / "first", ["--data.batch_size", "1"])  # frame a alone
    assert accumulated.cli.trainer.accumulate_grad_batches == 2 and accumulated.cli.datamodule.batch_size == 1
    assert len(accumulated.grads) == len(batched.grads) == 1  # one optimiser step each
    (g_acc,), (g_batch,) = accumulated.grads, batched.grads
    assert g_acc.keys() == g_batch.keys() and len(g_acc) >= 7
    worst = _relative(g_acc, g_batch)
    print(f"\naccumulated 2 x 1 frame vs 1 batch of 2: largest relative gradient difference {worst:.2e}")
    assert worst < 1e-4
    # The comparison tells one frame from two: frame a's gradient alone is far from the mean.
    alone = _relative(first.grads[0], g_batch)
    print(f"frame a alone vs the batch of two: {alone:.2e}")
    assert alone > 1e-2
    for name in accumulated.params:  # Adam's first step is lr * g / (|g| + eps): equal gradients, equal weights
        torch.testing.assert_close(accumulated.params[name], batched.params[name], rtol=1e-5, atol=1e-6)
