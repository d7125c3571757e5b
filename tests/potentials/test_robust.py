"""Robust reweighting (IRLS) of the pixel-grid data term: crfdepth/potentials/robust.py and CRFDepth(irls=...)."""

from __future__ import annotations

import pytest
import torch

from crfdepth.errors import InputError
from crfdepth.linalg import grid_edge_index
from crfdepth.linalg.operators import PixelGrid
from crfdepth.model import CRFDepth
from crfdepth.potentials.robust import leave_one_out, robust_factor
from tests.scenes import leaky_wall


def _dense_matrix(d, wh, wv):
    """``A = diag(d) + L`` of one (1, H, W) grid as a dense matrix."""
    h, w = d.shape[1:]
    edges = grid_edge_index(h, w)
    weight = torch.cat([wh.reshape(-1), wv.reshape(-1)])
    A = torch.diag(d.reshape(-1)).clone()
    i, j = edges
    A.index_put_((i, j), -weight, accumulate=True)
    A.index_put_((j, i), -weight, accumulate=True)
    A.index_put_((i, i), weight, accumulate=True)
    A.index_put_((j, j), weight, accumulate=True)
    return A


def test_the_grid_degree_used_by_the_leave_one_out_sums_the_edges_at_each_pixel():
    wh = torch.arange(1.0, 7.0).reshape(1, 2, 3)   # 2 x 4 grid: 3 horizontal edges per row
    wv = torch.arange(10.0, 14.0).reshape(1, 1, 4)  # 4 vertical edges
    deg = PixelGrid.degree(wh, wv)
    # pixel (0, 1): left edge 1, right edge 2, down edge 11
    assert deg.shape == (1, 2, 4)
    assert float(deg[0, 0, 1]) == 1 + 2 + 11
    assert float(deg[0, 1, 3]) == 6 + 13
    A = _dense_matrix(torch.zeros(1, 2, 4, dtype=torch.float64), wh.double(), wv.double())
    assert torch.allclose(torch.diag(A).reshape(1, 2, 4), deg.double())


def test_leave_one_out_is_the_node_value_without_its_datum():
    # Row k of A x = b with the neighbours held at x: x^_k = (b_k - a_k z_k + sum_j w_kj x_j) / (D_k - a_k).
    g = torch.Generator().manual_seed(0)
    h, w = 5, 6
    wh = torch.rand(1, h, w - 1, generator=g, dtype=torch.float64)
    wv = torch.rand(1, h - 1, w, generator=g, dtype=torch.float64)
    a = torch.where(torch.rand(1, h, w, generator=g) < 0.4, 50.0, 0.0).double()
    z = torch.rand(1, h, w, generator=g, dtype=torch.float64) * 10 + 5
    eps, x0 = 0.1, torch.full((1, h, w), 7.0, dtype=torch.float64)
    d, b = a + eps, a * z + eps * x0
    A = _dense_matrix(d, wh, wv)
    x = torch.linalg.solve(A, b.reshape(-1)).reshape(1, h, w)
    D = d + PixelGrid.degree(wh, wv)
    x_hat = leave_one_out(x, z, a, D)
    offdiag = A - torch.diag(torch.diag(A))
    pull = -(offdiag @ x.reshape(-1)).reshape(1, h, w)  # sum_j w_kj x_j
    direct = (eps * x0 + pull) / (D - a)
    data = a > 0
    assert torch.allclose(x_hat[data], direct[data], rtol=1e-10)
    assert torch.equal(x_hat[~data], x[~data])


def test_robust_factor_values_and_gradient():
    scale = torch.tensor(0.02, requires_grad=True)
    r = torch.tensor([-0.5, 0.0, 0.02, 0.06])
    f = robust_factor(r, scale)
    assert torch.allclose(f, torch.tensor([1.0, 1.0, 0.25, 0.01]), atol=1e-7)  # (1 + 3^2)^-2 = 0.01
    f.sum().backward()
    assert scale.grad is not None and float(scale.grad) > 0  # a larger sigma forgives more


def _isolated_leaks():
    """The box before the wall of the gate's tests, one wall return leaked into columns 40 and
    50 of the box on every scan line (isolated: no other leak beside it), and the box's rows
    between its first and last scan line."""
    image, sparse, K, truth, leaked = leaky_wall(leak_columns=((40, 41), (50, 51)))
    box = torch.zeros_like(leaked)
    box[14:39, 30:60] = True
    return image, sparse, K, truth, leaked, box


def test_irls_discounts_isolated_returns_behind_their_surroundings():
    image, sparse, K, truth, leaked, box = _isolated_leaks()
    err, at_leak = {}, {}
    for rounds in (0, 1, 2):
        with torch.no_grad():
            depth = CRFDepth(mode="pixel", irls=rounds)(image, sparse, K).depth[0, 0]
        err[rounds] = float((depth - truth)[box].abs().mean())
        at_leak[rounds] = float(depth[leaked].mean())
    # Measured: mean box error 1.04 / 0.29 / 0.19 m; the leaked pixels 24.0 / 11.0 / 9.2 m (truth 8).
    assert at_leak[0] > 20.0
    assert at_leak[1] < 13.0 and at_leak[2] < at_leak[1]
    assert err[1] < err[0] / 3 and err[2] < err[1]


def test_irls_keeps_returns_in_front_of_their_surroundings():
    # A thin pole (one column at 6 m) before the wall: its returns lie in front of their
    # surroundings, so IRLS leaves their weight alone and the pole stays. (The wall returns
    # beside it lie behind a prediction the pole pulls forward and lose a little weight:
    # the pole's depth moves by 0.025 m, measured.)
    h, w = 40, 64
    K = torch.tensor([[720.0, 0, w / 2], [0, 720.0, h / 2], [0, 0, 1]])
    image = torch.full((1, 3, h, w), 0.5)
    sparse = torch.zeros(1, 1, h, w)
    sparse[0, 0, 2::4] = 25.0
    sparse[0, 0, 2::4, 32] = 6.0
    with torch.no_grad():
        plain = CRFDepth(mode="pixel")(image, sparse, K)
        robust = CRFDepth(mode="pixel", irls=2)(image, sparse, K)
    pole = torch.zeros(h, w, dtype=torch.bool)
    pole[2::4, 32] = True
    pole = pole.reshape(-1)
    assert torch.equal(robust.terms.w[pole], plain.terms.w[pole])
    assert bool((robust.terms.w[~pole] <= plain.terms.w[~pole]).all())
    assert torch.allclose(robust.depth[0, 0, 2::4, 32], plain.depth[0, 0, 2::4, 32], atol=0.05)


def test_irls_scale_gets_a_gradient_in_both_modes():
    image, sparse, K, truth, _, _ = _isolated_leaks()
    for mode in ("pixel", "superpixel"):
        model = CRFDepth(mode=mode, irls=1, superpixels=300, scale_superpixels=False).double()
        out = model(image.double(), sparse.double(), K.double())
        (out.depth - truth.double()).abs().mean().backward()
        g = model.log_irls_scale.grad
        assert g is not None and torch.isfinite(g) and g != 0, mode


def test_irls_off_changes_nothing():
    image, sparse, K, _, _, _ = _isolated_leaks()
    assert not hasattr(CRFDepth(mode="pixel"), "log_irls_scale")
    assert "irls_scale" in CRFDepth(irls=1).weights()
    with torch.no_grad():
        a = CRFDepth(mode="pixel", gate=True)(image, sparse, K).depth
        b = CRFDepth(mode="pixel", gate=True, irls=0)(image, sparse, K).depth
    assert torch.equal(a, b)


@pytest.mark.parametrize("kwargs, name", [
    ({"irls": -1}, "irls"), ({"irls": True}, "irls"), ({"irls": 1.5}, "irls"),
    ({"irls_scale": 0.0}, "irls_scale"), ({"irls_scale": float("nan")}, "irls_scale"),
])
def test_bad_irls_options_name_the_argument(kwargs, name):
    with pytest.raises(InputError, match=name):
        CRFDepth(**kwargs)
