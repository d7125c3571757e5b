"""The model's additions beyond the paper (docs/design.md section 3b): the inverse- and
log-depth unknowns, the occlusion gate in the data term, the IP-Basic prior and the learned head."""

from __future__ import annotations

import pytest
import torch

from crfdepth.errors import InputError
from crfdepth.model import CRFDepth
from crfdepth.potentials.head import PotentialHead
from tests.scenes import leaky_wall

F, CY, H, W = 720.0, -20.0, 60, 96  # every row below the horizon: a road from 14 m to 59 m


def _road(dtype=torch.float64):
    """A flat road 1.65 m below the camera, sampled on every 6th row (scan lines), uniform colour."""
    K = torch.tensor([[F, 0, W / 2], [0, F, CY], [0, 0, 1.0]], dtype=dtype)
    v = torch.arange(H, dtype=dtype)[:, None].expand(H, W)
    depth = F * 1.65 / (v - CY)
    rows = torch.arange(3, H, 6)
    sparse = torch.zeros(H, W, dtype=dtype)
    sparse[rows] = depth[rows]
    image = torch.full((1, 3, H, W), 0.5, dtype=dtype)
    return image, sparse[None, None], K, depth, slice(int(rows[0]), int(rows[-1]) + 1)


def _plane_error(variable: str, **kwargs) -> float:
    image, sparse, K, depth, between = _road()
    model = CRFDepth(mode="pixel", variable=variable, rtol=1e-10, **kwargs).double()
    with torch.no_grad():
        out = model(image, sparse, K)
    return float(((out.depth[0, 0] - depth).abs() / depth)[between].max())


def test_inverse_depth_reproduces_a_slanted_plane_between_scan_lines():
    # The membrane on 1/z is exact on a plane; what remains is the small prior toward the
    # piecewise-constant nearest fill (eps). Measured: 0.086% against 1.3% on z.
    inverse = _plane_error("inverse", potentials=("colour",), eps=1e-3)
    depth = _plane_error("depth", potentials=("colour",), eps=1e-3)
    assert inverse < 1e-3
    assert depth > 1e-2
    # Hand-set defaults (all potentials, eps 0.1): within 1%, three times closer than on z
    # (measured 0.72% against 2.2%).
    inverse, depth = _plane_error("inverse"), _plane_error("depth")
    assert inverse < 0.01 and inverse < depth / 3


def test_log_depth_bends_a_plane_less_than_depth_and_more_than_inverse_depth():
    # Measured, colour only (eps 1e-3): 0.086% (1/z), 0.66% (log z), 1.3% (z).
    errors = [_plane_error(v, potentials=("colour",), eps=1e-3) for v in ("inverse", "log", "depth")]
    assert errors[0] < errors[1] / 4 and errors[1] < errors[2] / 1.5


def test_inverse_depth_std_is_in_metres():
    image, sparse, K, depth, between = _road(torch.float32)
    out = {v: CRFDepth(mode="pixel", variable=v, std_samples=8, uncertainty="posterior")(image, sparse, K,
                                                                                          return_std=True)
           for v in ("depth", "inverse", "log")}
    for o in out.values():
        assert torch.isfinite(o.std).all() and (o.std > 0).all()
    # Far rows are less certain in metres on 1/z (std_z = z^2 std_1/z) and on log z
    # (std_z = z std_log z), not on z.
    s = out["inverse"].std.detach()[0, 0, between].mean(1)
    assert float(s[0] / s[-1]) > 2.0
    s = out["log"].std.detach()[0, 0, between].mean(1)
    assert float(s[0] / s[-1]) > 1.5


@pytest.mark.parametrize("variable, mean", [("depth", 25.0), ("inverse", 16.0), ("log", 20.0)])
def test_each_unknown_averages_a_near_and_a_far_return_in_its_own_space(variable, mean):
    # Columns of returns at 10 m and 40 m, nothing between, uniform colour: halfway, the
    # membrane gives the arithmetic (z), harmonic (1/z) or geometric (log z) mean of the
    # two (measured 24.99, 15.99, 19.99 m; the rest is the prior, eps 1e-4).
    h, w = 8, 41
    K = torch.tensor([[720.0, 0, w / 2], [0, 720.0, h / 2], [0, 0, 1]], dtype=torch.float64)
    image = torch.full((1, 3, h, w), 0.5, dtype=torch.float64)
    sparse = torch.zeros(1, 1, h, w, dtype=torch.float64)
    sparse[..., 0], sparse[..., -1] = 10.0, 40.0
    model = CRFDepth(mode="pixel", variable=variable, potentials=("colour",), eps=1e-4, rtol=1e-12).double()
    with torch.no_grad():
        depth = model(image, sparse, K).depth[0, 0, :, w // 2]
    assert torch.allclose(depth, torch.full_like(depth, mean), rtol=2e-3)


def test_gate_keeps_leaked_background_out_of_the_foreground():
    image, sparse, K, truth, leaked = leaky_wall()
    box = torch.zeros_like(truth, dtype=torch.bool)
    box[14:39, 30:60] = True  # the box between its first and last scan line
    err = {}
    for gate in (False, True):
        with torch.no_grad():
            depth = CRFDepth(mode="pixel", gate=gate)(image, sparse, K).depth[0, 0]
        err[gate] = (depth - truth)[box].abs()
    # Without the gate the leaked 25 m returns pull the box's edge columns far back; with
    # it the box's mean error is a quarter of that. What remains is in the two leaked
    # columns, now without data, whose prior (the nearest kept return) is partly the wall
    # next to them (measured 2.4 m and 1.5 m there, 0.23 m mean over the box).
    assert float(err[False].max()) > 10.0 and float(err[False].mean()) > 1.0
    assert float(err[True].mean()) < 0.3
    inner = err[True].reshape(25, 30)[:, 2:-2]
    assert float(inner.max()) < 1.0  # measured 0.67 m


def test_gate_threshold_and_softness_get_gradients():
    image, sparse, K, truth, _ = leaky_wall()
    for mode in ("pixel", "superpixel"):
        model = CRFDepth(mode=mode, gate=True, superpixels=300, scale_superpixels=False).double()
        out = model(image.double(), sparse.double(), K.double())
        (out.depth - truth.double()).abs().mean().backward()
        for name in ("log_gate_threshold", "log_gate_softness"):
            g = getattr(model, name).grad
            assert g is not None and torch.isfinite(g) and g != 0, (mode, name)


def test_ip_basic_prior_changes_only_the_prior():
    image, sparse, K, truth, _ = leaky_wall()
    with torch.no_grad():
        a = CRFDepth(mode="pixel", gate=True)(image, sparse, K).depth
        b = CRFDepth(mode="pixel", gate=True, prior="ip_basic")(image, sparse, K).depth
    assert torch.isfinite(b).all() and (b > 0).all()
    assert not torch.equal(a, b)
    assert float((a - b).abs().max()) < 5.0


def test_fresh_head_is_the_identity_and_learns():
    image, sparse, K, truth, _ = leaky_wall()
    plain = CRFDepth(mode="pixel", gate=True)
    headed = CRFDepth(mode="pixel", gate=True, head=True)
    headed.load_state_dict(plain.state_dict(), strict=False)
    with torch.no_grad():
        assert torch.equal(headed(image, sparse, K).depth, plain(image, sparse, K).depth)
    out = headed(image, sparse, K)
    (out.depth - truth).abs().mean().backward()
    last = headed.head.net[-1]
    assert last.weight.grad is not None and float(last.weight.grad.abs().sum()) > 0
    assert 1_000 < sum(p.numel() for p in headed.head.parameters()) < 5_000


def test_head_factors_are_bounded_and_positive():
    head = PotentialHead(limit=2.0)
    torch.nn.init.normal_(head.net[-1].weight, std=100.0)
    image, sparse, K, truth, _ = leaky_wall()
    data, edge = head(image, sparse, truth[None, None])
    assert data.shape == (1, 1, 48, 96) and edge.shape == (1, 2, 48, 96)
    for f in (data.detach(), edge.detach()):
        assert float(f.min()) >= torch.exp(torch.tensor(-2.0)) * (1 - 1e-6)
        assert float(f.max()) <= torch.exp(torch.tensor(2.0)) * (1 + 1e-6)


@pytest.mark.parametrize("kwargs, name", [
    ({"variable": "sqrt"}, "variable"), ({"prior": "zero"}, "prior"), ({"gate_window": 4}, "gate_window"),
    ({"gate_threshold": -1.0}, "gate_threshold"), ({"gate": True, "aggregate": "median"}, "aggregate"),
])
def test_bad_options_name_the_argument(kwargs, name):
    with pytest.raises(InputError, match=name):
        CRFDepth(**kwargs)


def test_gate_parameters_exist_only_with_the_gate():
    assert not hasattr(CRFDepth(), "log_gate_threshold")
    names = dict(CRFDepth(gate=True).named_parameters())
    assert {"log_gate_threshold", "log_gate_softness"} <= names.keys()
    assert set(CRFDepth(gate=True).weights()) >= {"gate_threshold", "gate_softness"}
