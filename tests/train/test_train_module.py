"""CRFDepthModule: losses, the checkpoint contract, which parameters train, batches on devices."""

from __future__ import annotations

import dataclasses
import math
import subprocess
import sys

import pytest
import torch
from lightning.fabric.utilities.apply_func import move_data_to_device

from crfdepth.data import build_dataset, collate_samples
from crfdepth.errors import InputError
from crfdepth.model import CRFDepth
from train.module import PARAMETERS, CRFDepthModule, depth_loss, gaussian_nll


def _plain(value) -> bool:
    if isinstance(value, dict):
        return all(isinstance(k, str) and _plain(v) for k, v in value.items())
    if isinstance(value, (list, tuple)):
        return all(_plain(v) for v in value)
    return value is None or isinstance(value, (bool, int, float, str))


def test_depth_loss_known_values():
    depth = torch.tensor([[[[1.0, 2.0], [3.0, 4.0]]], [[[5.0, 5.0], [5.0, 5.0]]]])
    target = torch.tensor([[[[2.0, 0.0], [1.0, 0.0]]], [[[0.0, 0.0], [0.0, 0.0]]]])
    assert depth_loss(depth, target, "l2").tolist() == [pytest.approx((1 + 4) / 2), 0.0]
    assert depth_loss(depth, target, "l1").tolist() == [pytest.approx((1 + 2) / 2), 0.0]
    # huber: the squared error up to delta, then 2 delta |e| - delta^2 (continuous, same slope)
    assert depth_loss(depth, target, "huber", 1.5).tolist() == [pytest.approx((1 + (2 * 1.5 * 2 - 1.5 ** 2)) / 2), 0.0]
    assert depth_loss(depth, target, "huber", 5.0).tolist() == depth_loss(depth, target, "l2").tolist()
    with pytest.raises(InputError, match="^loss: expected 'l2', 'l1' or 'huber', got 'l3'$"):
        depth_loss(depth, target, "l3")
    # An image without targets contributes no gradient (and no NaN).
    depth.requires_grad_(True)
    depth_loss(depth, target).sum().backward()
    assert torch.isfinite(depth.grad).all() and depth.grad[1].abs().sum() == 0


def test_gaussian_nll_known_value():
    depth = torch.tensor([[[[10.0, 7.0]]]])
    std = torch.tensor([[[[2.0, 1.0]]]])
    target = torch.tensor([[[[11.0, 0.0]]]])
    expected = math.log(2.0) + 1.0 / (2 * 4.0)  # only the first pixel has a target
    assert gaussian_nll(depth, std, target).item() == pytest.approx(expected)


def test_hyperparameters_hold_the_complete_crf_config():
    module = CRFDepthModule()
    assert module.hparams["crf"] == CRFDepth().config
    module = CRFDepthModule(crf={"mode": "pixel", "alpha": 0.3})
    crf = module.hparams["crf"]
    assert crf == CRFDepth(mode="pixel", alpha=0.3).config and crf["structure"]["mode"] == "pixel"
    assert _plain(dict(module.hparams))
    rebuilt = CRFDepth(**crf)
    rebuilt.load_state_dict({k[len("model."):]: v for k, v in module.state_dict().items() if k.startswith("model.")})
    assert rebuilt.state_dict().keys() == module.model.state_dict().keys()
    assert all(torch.equal(v, module.model.state_dict()[k]) for k, v in rebuilt.state_dict().items())


def test_unused_parameters_are_frozen():
    module = CRFDepthModule(crf={"mode": "pixel", "potentials": ["colour"]}, freeze=["sigma_d"])
    frozen = {name for name, raw in PARAMETERS.items()
              if hasattr(module.model, raw) and not getattr(module.model, raw).requires_grad}
    assert frozen == {"std_scale", "gamma", "sigma_n", "delta", "sigma_p", "sigma_d", "refine_prior"}
    optimizer = module.configure_optimizers()
    assert sum(len(g["params"]) for g in optimizer.param_groups) == 3  # alpha, beta, confidence
    assert module.model.log_std_scale.requires_grad is False
    assert CRFDepthModule(nll_weight=0.1, crf={"uncertainty": "posterior"}).model.log_std_scale.requires_grad is True
    # The predictive std (the default) trains its own weights with the NLL term, never the posterior's scale.
    assert CRFDepthModule(nll_weight=0.1).model.log_std_scale.requires_grad is False
    assert CRFDepthModule(nll_weight=0.1).model.std_head.weights.requires_grad is True
    assert module.model.std_head.weights.requires_grad is False
    # The refinement prior is learned only where there is a refinement.
    assert CRFDepthModule().model.log_refine_prior.requires_grad is True
    assert CRFDepthModule(crf={"refine": False}).model.log_refine_prior.requires_grad is False
    # ... and on the pixel grid with a coarse solve, whose painted depth it weighs (design section 17).
    assert CRFDepthModule(crf={"mode": "pixel", "coarse": 6}).model.log_refine_prior.requires_grad is True


@pytest.mark.parametrize("kwargs, match", [
    ({"loss": "l3"}, "loss"), ({"nll_weight": -1.0}, "nll_weight"), ({"lr": 0.0}, "lr"),
    ({"loss": "huber", "huber_delta": 0.0}, "^huber_delta: expected a number of metres > 0, got 0.0$"),
    ({"huber_delta": "1 m"}, "^huber_delta: "),
    ({"exclude_inputs": "yes"}, "^exclude_inputs: expected true or false, got 'yes'$"),
    ({"freeze": ["alpha", "zeta"]}, "zeta"), ({"crf": {"mode": "voxel"}}, "mode"),
])
def test_bad_arguments(kwargs, match):
    with pytest.raises(InputError, match=match):
        CRFDepthModule(**kwargs)


def test_exclude_inputs_scores_only_the_pixels_without_an_input_return():
    sample = build_dataset("synthetic", count=1, seed=3, height=64, width=192)[0]
    batch = collate_samples([sample])
    inputs = batch.sparse > 0
    assert int((inputs & (batch.target > 0)).sum()) > 50  # the synthetic target covers the input pixels
    module = CRFDepthModule(crf={"mode": "pixel"}, loss="l1", exclude_inputs=True)
    loss, _, out = module._objective(batch)
    zeroed = torch.where(inputs, torch.zeros_like(batch.target), batch.target)
    assert torch.allclose(loss, depth_loss(out.depth, zeroed, "l1"), rtol=1e-6)
    assert not torch.allclose(loss, depth_loss(out.depth, batch.target, "l1"), rtol=1e-3)
    # the target at input pixels does not matter; elsewhere it does
    moved = batch.target.clone()
    moved[inputs] += 5.0
    assert torch.allclose(module._objective(dataclasses.replace(batch, target=moved))[0], loss, rtol=1e-6)
    assert CRFDepthModule(crf={"mode": "pixel"}, loss="l1")._objective(dataclasses.replace(batch, target=moved))[0] \
        > loss + 0.1


def test_nll_term_trains_only_the_std_scale():
    sample = build_dataset("synthetic", count=1, seed=3, height=64, width=192)[0]
    batch = collate_samples([sample])
    module = CRFDepthModule(crf={"mode": "superpixel", "superpixels": 2000, "uncertainty": "posterior"}, nll_weight=1.0)
    _, parts, out = module._objective(batch)
    assert out.std is not None and set(parts) == {"depth_loss", "nll"}
    parts["nll"].sum().backward()
    grads = {name: getattr(module.model, raw).grad for name, raw in PARAMETERS.items() if hasattr(module.model, raw)}
    assert grads["std_scale"] is not None and grads["std_scale"].abs().item() > 0
    assert all(g is None or g.abs().item() == 0 for n, g in grads.items() if n != "std_scale")


def test_nll_term_trains_only_the_predictive_std():
    sample = build_dataset("synthetic", count=1, seed=3, height=64, width=192)[0]
    module = CRFDepthModule(crf={"mode": "pixel"}, nll_weight=1.0)
    _, parts, _ = module._objective(collate_samples([sample]))
    parts["nll"].sum().backward()
    assert bool((module.model.std_head.weights.grad.abs() > 0).all())
    grads = [getattr(module.model, raw).grad for raw in PARAMETERS.values() if hasattr(module.model, raw)]
    assert all(g is None or g.abs().item() == 0 for g in grads)


def test_lightning_moves_batches_with_batch_to():
    batch = collate_samples([build_dataset("synthetic", count=1, height=32, width=64)[0]])
    moved = move_data_to_device(batch, torch.device("meta"))  # what the default transfer hook does
    assert type(moved) is type(batch) and moved.names == batch.names
    assert {t.device.type for t in (moved.image, moved.sparse, moved.target, moved.K, moved.has_target)} == {"meta"}


def test_importing_crfdepth_does_not_import_lightning():
    code = ("import sys, crfdepth, crfdepth.model, crfdepth.data, crfdepth.metrics, crfdepth.cli; "
            "crfdepth.cli.build_parser(); "
            "bad = sorted(m for m in sys.modules if m.split('.')[0] in ('lightning', 'pytorch_lightning', "
            "'torchmetrics', 'train')); print(bad); sys.exit(1 if bad else 0)")
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stdout + proc.stderr
