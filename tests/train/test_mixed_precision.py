"""Training under ``--trainer.precision bf16-mixed`` on the CPU.

Lightning runs ``training_step`` under ``torch.autocast("cpu", dtype=torch.bfloat16)``. The
CRF runs with autocast off (:mod:`crfdepth.precision`) and the loss is element-wise, so a
bf16-mixed step is the float32 step: the same gradients and weights, bit for bit.
"""

from __future__ import annotations

import pytest
import torch

pytestmark = pytest.mark.filterwarnings("ignore::DeprecationWarning:lightning.pytorch.cli",
                                        "ignore:.*does not have many workers:UserWarning",
                                        "ignore:.*log_every_n_steps.*:UserWarning")


def test_one_bf16_mixed_step_is_the_float32_step(tmp_path, train_step):
    args = ["--data.batch_size", "2", "--model.crf", "{structure: {mode: pixel, head: true}}"]
    mixed = train_step(tmp_path / "bf16", [*args, "--trainer.precision", "bf16-mixed"])
    full = train_step(tmp_path / "fp32", args)
    assert type(mixed.cli.trainer.precision_plugin).__name__ == "MixedPrecision"
    assert mixed.cli.trainer.precision_plugin.precision == "bf16-mixed"
    (g_mixed,), (g_full,) = mixed.grads, full.grads
    assert g_mixed.keys() == g_full.keys() and any(n.startswith("model.head.") for n in g_full)
    assert all(bool(torch.isfinite(g).all()) and g.dtype == torch.float32 for g in g_mixed.values())
    assert all(torch.equal(g_mixed[n], g_full[n]) for n in g_full)
    assert all(torch.equal(mixed.params[n], full.params[n]) for n in full.params)
