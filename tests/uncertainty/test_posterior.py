"""Posterior variance diag(A^-1): exact on small graphs, sampled on large ones."""

import pytest
import torch

from crfdepth.errors import InputError
from crfdepth.linalg import grid_edge_index, solve_laplacian
from crfdepth.uncertainty.posterior import grid_posterior_variance, posterior_variance

F64 = torch.float64


def superpixel_like_system(rows=55, cols=100, observed=0.3, seed=0):
    """A 5,500-node 4-neighbour graph with data on 30% of the nodes (like SLIC on KITTI)."""
    g = torch.Generator().manual_seed(seed)
    ei = grid_edge_index(rows, cols)
    w = torch.rand(ei.shape[1], generator=g, dtype=F64) * 0.9 + 0.1
    d = torch.where(torch.rand(rows * cols, generator=g) < observed, 1.0, 0.0).to(F64) + 1e-3
    return d, ei, w


def test_exact_variance_matches_dense_inverse():
    d, ei, w = superpixel_like_system(8, 9)
    A = torch.diag(d).index_put((ei[0], ei[0]), w, accumulate=True).index_put((ei[1], ei[1]), w, accumulate=True)
    A = A.index_put((ei[0], ei[1]), -w, accumulate=True).index_put((ei[1], ei[0]), -w, accumulate=True)
    assert torch.allclose(posterior_variance(d, ei, w), torch.linalg.inv(A).diagonal(), rtol=1e-10)


def test_sampled_std_agrees_with_exact_on_a_subsample_within_10_percent():
    d, ei, w = superpixel_like_system()
    n = d.shape[0]
    est = posterior_variance(d, ei, w, exact_max_nodes=0)  # force the estimate (32 samples)
    nodes = torch.randperm(n, generator=torch.Generator().manual_seed(1))[:40]
    exact = []
    for i in nodes.tolist():  # (A^-1)_ii = e_i^T A^-1 e_i, one solve per node
        e = torch.zeros(n, dtype=F64)
        e[i] = 1.0
        exact.append(solve_laplacian(e, d, ei, w, rtol=1e-12)[0][i])
    exact_std = torch.stack(exact).sqrt()
    rel = (est[nodes].sqrt() - exact_std).abs() / exact_std
    print(f"\nstd relative error on 40 nodes: median {rel.median():.3f}, max {rel.max():.3f}")
    assert float(rel.median()) < 0.05 and float(rel.quantile(0.9)) < 0.10
    assert bool((est >= 1.0 / (d + torch.bincount(ei[0], w, n) + torch.bincount(ei[1], w, n)) - 1e-12).all())


def test_grid_estimate_matches_edge_estimate_and_is_seeded():
    d, ei, w = superpixel_like_system(20, 30)
    h, wd = 20, 30
    nh = h * (wd - 1)
    grid = grid_posterior_variance(d.view(1, h, wd), w[:nh].view(1, h, wd - 1), w[nh:].view(1, h - 1, wd))
    again = grid_posterior_variance(d.view(1, h, wd), w[:nh].view(1, h, wd - 1), w[nh:].view(1, h - 1, wd))
    assert torch.equal(grid, again)
    exact = posterior_variance(d, ei, w).view(1, h, wd)
    rel = ((grid.sqrt() - exact.sqrt()).abs() / exact.sqrt()).flatten()
    assert float(rel.median()) < 0.05


def test_bad_samples():
    d, ei, w = superpixel_like_system(4, 4)
    for samples, got in ((0, "0"), (1.5, "float 1.5"), (10**20, str(10**20))):
        with pytest.raises(InputError) as info:
            posterior_variance(d, ei, w, samples=samples)
        assert str(info.value) == f"samples: expected an integer in [1, 4096], got {got}"
