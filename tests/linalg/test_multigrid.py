"""The pixel-grid multigrid preconditioner (docs/design.md section 4) against dense oracles."""

from __future__ import annotations

import numpy as np
import pytest
import torch

import crfdepth.linalg.multigrid as multigrid
from crfdepth.errors import InputError
from crfdepth.linalg import grid_edge_index, solve_grid_laplacian
from crfdepth.linalg.multigrid import GridMultigrid, coarsen

F64 = torch.float64
SIZES = [(7, 9), (1, 11), (6, 1), (8, 8), (5, 2)]


def random_grid(height: int, width: int, batch: int = 2, seed: int = 0, observed: float = 0.3):
    g = torch.Generator().manual_seed(seed)
    d = torch.rand(batch, height, width, generator=g, dtype=F64) * (torch.rand(batch, height, width, generator=g)
                                                                    < observed) + 1e-3
    weight_h = torch.rand(batch, height, width - 1, generator=g, dtype=F64)
    weight_v = torch.rand(batch, height - 1, width, generator=g, dtype=F64)
    return d, weight_h, weight_v


def dense(d: torch.Tensor, weight_h: torch.Tensor, weight_v: torch.Tensor) -> torch.Tensor:
    """(B, n, n) matrices ``diag(d) + L(w)``, assembled densely (the oracle)."""
    b, h, w = d.shape
    src, dst = grid_edge_index(h, w)
    out = []
    for k in range(b):
        weights = torch.cat([weight_h[k].reshape(-1), weight_v[k].reshape(-1)])
        a = torch.diag(d[k].reshape(-1))
        for i, j, sign in ((src, dst, -1.0), (dst, src, -1.0), (src, src, 1.0), (dst, dst, 1.0)):
            a.index_put_((i, j), sign * weights, accumulate=True)  # a node is in several edges
        out.append(a)
    return torch.stack(out)


def aggregation(height: int, width: int) -> torch.Tensor:
    """(n, n_coarse) piecewise-constant prolongation of 2 x 2 blocks (a side of 1 stays 1)."""
    fh, fw = (2 if height > 1 else 1), (2 if width > 1 else 1)
    h2, w2 = -(-height // fh), -(-width // fw)
    rows, cols = torch.meshgrid(torch.arange(height), torch.arange(width), indexing="ij")
    block = (rows // fh) * w2 + cols // fw
    return torch.nn.functional.one_hot(block.reshape(-1), h2 * w2).to(F64)


@pytest.mark.parametrize("size", SIZES)
def test_coarse_system_is_galerkin(size):
    d, wh, wv = random_grid(*size)
    p = aggregation(*size)
    coarse = dense(*coarsen(d, wh, wv))
    assert torch.allclose(p.T @ dense(d, wh, wv) @ p, coarse, rtol=0, atol=1e-13)


@pytest.mark.parametrize("size", SIZES)
def test_v_cycle_is_symmetric_positive_definite(size, monkeypatch):
    monkeypatch.setattr(multigrid, "COARSEST_NODES", 2)  # several levels on a small grid
    d, wh, wv = random_grid(*size)
    cycle = GridMultigrid(d, wh, wv)
    assert len(cycle.levels) >= 2
    b, h, w = d.shape
    n = h * w
    basis = torch.eye(n, dtype=F64).view(n, h, w)
    columns = torch.stack([cycle(basis[i:i + 1].expand(b, h, w).contiguous()).clone() for i in range(n)], 1)
    matrix = columns.reshape(b, n, n).transpose(1, 2)
    assert torch.allclose(matrix, matrix.transpose(1, 2), rtol=0, atol=1e-12)
    assert float(torch.linalg.eigvalsh(matrix).min()) > 0
    # B ~ A^-1: the spectrum of B A lies in (0, 1] (damped Jacobi and an exact coarsest solve)
    spectrum = torch.linalg.eigvals(matrix @ dense(d, wh, wv)).real
    assert float(spectrum.min()) > 0.05 and float(spectrum.max()) <= 1 + 1e-9


@pytest.mark.parametrize("size", [(13, 17), (1, 40), (9, 1)])
def test_multigrid_solve_matches_dense_solve(size, monkeypatch):
    monkeypatch.setattr(multigrid, "COARSEST_NODES", 4)
    d, wh, wv = random_grid(*size, observed=0.1)
    b = torch.randn(d.shape, generator=torch.Generator().manual_seed(3), dtype=F64)
    x, info = solve_grid_laplacian(b, d, wh, wv, rtol=1e-12, preconditioner="multigrid")
    # numpy's LAPACK as the oracle: torch 2.13's batched float64 solve failed here with a pivot error after
    # another test had switched torch to one thread and back (tests/test_layer.py), in this order only
    x_ref = torch.from_numpy(np.linalg.solve(dense(d, wh, wv).numpy(), b.reshape(b.shape[0], -1, 1).numpy()))
    x_ref = x_ref.view(b.shape)
    assert bool(info.converged.all())
    assert torch.allclose(x, x_ref, rtol=0, atol=1e-8 * float(x_ref.abs().max()))
    x32, info32 = solve_grid_laplacian(b.float(), d.float(), wh.float(), wv.float(), rtol=1e-5,
                                       preconditioner="multigrid")
    assert x32.dtype == torch.float32 and bool(info32.converged.all())
    assert float((x32.double() - x_ref).abs().max() / x_ref.abs().max()) < 1e-4


def lidar_like_system(seed: int, h: int = 96, w: int = 160):
    """A grid system like the model's: 4% of pixels observed with a strong data weight, a depth ramp."""
    g = torch.Generator().manual_seed(seed)
    observed = torch.rand(1, h, w, generator=g) < 0.04
    d = torch.where(observed, 300.0, 1e-3).to(F64)
    b = d * (5.0 + 20.0 * torch.linspace(0, 1, h, dtype=F64)[None, :, None])
    wh = 0.05 + torch.rand(1, h, w - 1, generator=g, dtype=F64)
    wv = 0.05 + torch.rand(1, h - 1, w, generator=g, dtype=F64)
    return b, d, wh, wv


def test_multigrid_needs_far_fewer_iterations_than_jacobi():
    b, d, wh, wv = lidar_like_system(5)
    _, jacobi = solve_grid_laplacian(b, d, wh, wv, rtol=1e-8, preconditioner="jacobi")
    x, mg = solve_grid_laplacian(b, d, wh, wv, rtol=1e-8, preconditioner="multigrid")
    assert bool(jacobi.converged.all()) and bool(mg.converged.all())
    assert 3 * int(mg.iterations[0]) < int(jacobi.iterations[0]), (mg.summary(), jacobi.summary())


def test_gradcheck_through_multigrid_forward_and_adjoint(monkeypatch):
    monkeypatch.setattr(multigrid, "COARSEST_NODES", 2)
    d, wh, wv = random_grid(4, 5)
    b = torch.randn(d.shape, generator=torch.Generator().manual_seed(4), dtype=F64)
    args = tuple(t.clone().requires_grad_() for t in (b, d, wh, wv))
    infos = []

    def fn(*a):
        x, info = solve_grid_laplacian(*a, rtol=1e-13)  # "auto": multigrid when differentiated
        infos.append(info)
        return x

    assert torch.autograd.gradcheck(fn, args)
    assert all(int(i.iterations.max()) < 20 for i in infos)  # a V-cycle preconditioner, not Jacobi (n = 20)


def test_bad_preconditioner():
    d, wh, wv = random_grid(3, 4)
    b = torch.ones_like(d)
    with pytest.raises(InputError, match="preconditioner: expected 'auto', 'jacobi' or 'multigrid'"):
        solve_grid_laplacian(b, d, wh, wv, preconditioner="ilu")
    with pytest.raises(InputError, match="preconditioner: 'multigrid' needs method 'cg'"):
        solve_grid_laplacian(b, d, wh, wv, method="cgs", preconditioner="multigrid")


def test_auto_inference_uses_multigrid_on_large_grids_only(monkeypatch):
    """An undifferentiated "auto" solve: Jacobi below MULTIGRID_MIN_PIXELS per image, multigrid from there."""
    import crfdepth.linalg.adjoint as autograd

    h, w = 96, 160
    b, d, wh, wv = lidar_like_system(6, h, w)
    x_ref, jacobi = solve_grid_laplacian(b, d, wh, wv, rtol=1e-8, preconditioner="jacobi")
    x_small, small = solve_grid_laplacian(b, d, wh, wv, rtol=1e-8)  # below the size: Jacobi
    assert torch.equal(small.iterations, jacobi.iterations) and torch.equal(x_small, x_ref)
    monkeypatch.setattr(autograd, "MULTIGRID_MIN_PIXELS", h * w)  # this grid counts as large
    x, large = solve_grid_laplacian(b, d, wh, wv, rtol=1e-8)
    _, multigrid = solve_grid_laplacian(b, d, wh, wv, rtol=1e-8, preconditioner="multigrid")
    assert torch.equal(large.iterations, multigrid.iterations) and bool(large.converged.all())
    assert 3 * int(large.iterations[0]) < int(jacobi.iterations[0])
    assert float((x - x_ref).abs().max() / x_ref.abs().max()) < 1e-4  # both at rtol 1e-8 of the residual
