"""crfdepth.precision: the model, the layer and the solves under ``torch.autocast`` (CPU, bfloat16).

The CRF runs with autocast off and takes half-precision tensors as float32, so under
autocast its depth is the float32 depth exactly (tolerance 0), where without that guard the
SLIC clustering alone (its Lab conversion and distances are matmuls) moved depths by
metres. Inside a network under autocast, the layer's output differs from the all-float32
network's only by what the network's own bfloat16 convolutions change.
"""

from __future__ import annotations

import pytest
import torch
from torch import nn

from crfdepth.layer import CRFRefine
from crfdepth.linalg import solve_grid_laplacian
from crfdepth.model import CRFDepth
from crfdepth.precision import autocast_off, full_precision, widen
from crfdepth.superpixels.slic import slic_torch
from tests.scenes import leaky_wall

BF16 = dict(device_type="cpu", dtype=torch.bfloat16)


def test_widen_and_autocast_off():
    half = torch.ones(2, dtype=torch.bfloat16, requires_grad=True)
    assert widen(half).dtype == torch.float32 and widen(half).requires_grad
    assert widen(torch.ones(2, dtype=torch.float64)).dtype == torch.float64 and widen(3) == 3
    a = torch.randn(4, 4)
    with torch.autocast(**BF16):
        assert (a @ a).dtype == torch.bfloat16
        with autocast_off(a):
            assert (a @ a).dtype == torch.float32
        assert full_precision(lambda x: x @ x)(a.bfloat16()).dtype == torch.float32


def _model(config) -> CRFDepth:
    """``CRFDepth(config)``, seeded; its head (if any) moved away from its identity start so that
    its factors matter and every layer of it gets a gradient."""
    torch.manual_seed(0)
    model = CRFDepth(config)
    if model.head is not None:
        with torch.no_grad():
            for p in model.head.parameters():
                p.add_(0.3 * torch.randn_like(p))
    return model


@pytest.mark.parametrize("config", [
    {"structure": {"mode": "pixel", "head": True}, "gate": {"enabled": True}},  # the head's convolutions
    {"structure": {"mode": "superpixel", "superpixels": 60}},  # SLIC, graph normals, the pixel refinement
], ids=["pixel_head", "superpixel"])
def test_model_under_bf16_autocast_is_the_float32_model(config):
    image, sparse, K, truth, _ = leaky_wall()
    model = _model(config)
    with torch.no_grad():
        ref = model(image, sparse, K, return_std=True)
        with torch.autocast(**BF16):
            out = model(image, sparse, K, return_std=True)
    assert out.depth.dtype == out.std.dtype == torch.float32
    assert bool(torch.isfinite(out.depth).all()) and bool(torch.isfinite(out.std).all())
    assert torch.equal(out.depth, ref.depth) and torch.equal(out.std, ref.std)
    # the scene is solved, not just reproduced: the box and the wall within 0.5 m at their centres
    assert abs(float(out.depth[0, 0, 26, 45]) - 8.0) < 0.5 and abs(float(out.depth[0, 0, 4, 10]) - 25.0) < 0.5


def test_model_gradients_under_bf16_autocast_are_the_float32_ones():
    image, sparse, K, truth, _ = leaky_wall()
    grads = []
    for autocast in (False, True):
        model = _model({"structure": {"mode": "pixel", "head": True}})
        with torch.autocast(**BF16, enabled=autocast):
            depth = model(image, sparse, K).depth
        ((depth[0, 0] - truth) ** 2).mean().backward()
        grads.append({n: p.grad for n, p in model.named_parameters() if p.grad is not None})
    assert grads[0].keys() == grads[1].keys() and "raw_alpha" in grads[0] and "head.net.0.weight" in grads[0]
    assert all(float(g.abs().max()) > 0 for n, g in grads[0].items() if n != "log_sigma_d"), grads[0]
    assert all(torch.equal(grads[0][n], grads[1][n]) for n in grads[0])


def test_slic_would_cluster_in_bf16_without_the_guard():
    """What the guard prevents: the undecorated SLIC under autocast gives other segments."""
    image = leaky_wall()[0]
    image = image + 0.05 * torch.rand(image.shape, generator=torch.Generator().manual_seed(0))
    ref = slic_torch(image, 60)
    with torch.autocast(**BF16):
        guarded = slic_torch(image, 60)
        unguarded = slic_torch.__wrapped__(image, 60)
    assert torch.equal(guarded, ref)
    assert float((unguarded != ref).float().mean()) > 0.01


def test_layer_on_float32_inputs_under_autocast_is_the_float32_layer():
    image, sparse, K, truth, _ = leaky_wall()
    g = torch.Generator().manual_seed(0)
    depth, confidence, features = truth[None, None] + torch.rand(1, 1, 48, 96, generator=g), \
        torch.rand(1, 1, 48, 96, generator=g), torch.randn(1, 8, 48, 96, generator=g)
    runs = []
    for autocast in (False, True):
        torch.manual_seed(0)
        layer = CRFRefine(8)
        with torch.autocast(**BF16, enabled=autocast):
            out = layer(depth, confidence, features, sparse)
        out.depth.sum().backward()
        runs.append((out.depth.detach(), [p.grad for p in layer.parameters() if p.grad is not None]))
    (d32, g32), (d16, g16) = runs
    assert torch.equal(d16, d32) and len(g32) == 3 and all(torch.equal(a, b) for a, b in zip(g16, g32))


class _Net(nn.Module):
    """A stand-in depth network: depth, confidence and 8 guidance features from RGB + LiDAR."""

    def __init__(self) -> None:
        super().__init__()
        torch.manual_seed(0)
        self.body = nn.Conv2d(4, 10, 3, padding=1)

    def forward(self, image, sparse):
        out = self.body(torch.cat([image, sparse / 25.0], 1))
        return 25.0 * torch.sigmoid(out[:, :1]), nn.functional.softplus(out[:, 1:2]), out[:, 2:]


def test_layer_under_bf16_autocast_solves_in_float32_and_gets_gradients():
    image, sparse, K, truth, _ = leaky_wall()
    results = []
    for autocast in (False, True):
        net, layer = _Net(), CRFRefine(8)
        with torch.autocast(**BF16, enabled=autocast):
            depth, confidence, features = net(image, sparse)
            out = layer(depth, confidence, features, sparse)
        if autocast:  # the network's outputs are bfloat16; the layer's are not
            assert depth.dtype == features.dtype == torch.bfloat16
        loss = ((out.depth[0, 0] - truth) ** 2).mean()
        loss.backward()
        results.append((out, net, layer))
    (ref, net32, layer32), (out, net16, layer16) = results
    assert out.depth.dtype == torch.float32 and bool(torch.isfinite(out.depth).all())
    assert bool(out.info.converged.all())
    # bfloat16 in the network only: the refined depth stays within 0.1 m (0.4% of 25 m) of float32's
    diff = float((out.depth - ref.depth).detach().abs().max())
    print(f"\nCRFRefine in a bf16 network: largest depth difference to float32 {diff:.3g} m")
    assert diff < 0.1
    for name, p in [*net16.named_parameters(), *layer16.named_parameters()]:
        if name == "log_std_scale":  # gets a gradient through the std only
            continue
        assert p.grad is not None and p.grad.dtype == torch.float32, name
        assert bool(torch.isfinite(p.grad).all()) and float(p.grad.abs().max()) > 0, name
    g16, g32 = layer16.log_edge_scale.grad, layer32.log_edge_scale.grad
    assert float((g16 - g32).abs()) < 0.05 * float(g32.abs())


def test_half_precision_system_is_solved_in_float32():
    g = torch.Generator().manual_seed(0)
    b = (torch.rand(1, 16, 24, generator=g) * 20).bfloat16()
    d = torch.rand(1, 16, 24, generator=g).bfloat16() + 0.1
    wh, wv = torch.rand(1, 16, 23, generator=g).bfloat16(), torch.rand(1, 15, 24, generator=g).bfloat16()
    x, info = solve_grid_laplacian(b, d, wh, wv, rtol=1e-6)
    ref, _ = solve_grid_laplacian(b.float(), d.float(), wh.float(), wv.float(), rtol=1e-6)
    assert x.dtype == torch.float32 and bool(info.converged.all()) and float(info.rel_residual.max()) <= 1e-6
    assert torch.equal(x, ref)  # the same solve as float32 inputs holding the bf16 values
