"""The one system type (crfdepth/linalg/system.py) and its solve and variances, against dense algebra."""

from __future__ import annotations

import torch

from crfdepth.linalg import System, solve_system, solver_settings
from crfdepth.linalg.operators import grid_edge_index
from crfdepth.uncertainty.posterior import posterior_std, system_conditional_variance


def _dense(d, edge_index, w):
    A = torch.diag(d).clone()
    for (i, j), wij in zip(edge_index.T.tolist(), w.tolist()):
        A[i, i] += wij
        A[j, j] += wij
        A[i, j] -= wij
        A[j, i] -= wij
    return A


def _grid_system(seed=0, b=2, h=5, w=6):
    g = torch.Generator().manual_seed(seed)
    d = torch.rand(b, h, w, generator=g, dtype=torch.float64) + 0.1
    rhs = torch.randn(b, h, w, generator=g, dtype=torch.float64)
    wh = torch.rand(b, h, w - 1, generator=g, dtype=torch.float64)
    wv = torch.rand(b, h - 1, w, generator=g, dtype=torch.float64)
    return System.grid(d, rhs, wh, wv)


def test_a_grid_and_the_same_graph_solve_to_the_dense_answer():
    grid = _grid_system()
    bsz, h, w = grid.rhs.shape
    ei = grid_edge_index(h, w)
    settings = solver_settings(rtol=1e-12)
    x_grid, info = solve_system(grid, None, settings)
    assert bool(info.converged.all())
    for k in range(bsz):
        weights = torch.cat([grid.weights[0][k].reshape(-1), grid.weights[1][k].reshape(-1)])
        A = _dense(grid.diagonal[k].reshape(-1), ei, weights)
        exact = torch.linalg.solve(A, grid.rhs[k].reshape(-1))
        assert torch.allclose(x_grid[k].reshape(-1), exact, rtol=1e-9, atol=1e-10)
        graph = System.graph(grid.diagonal[k].reshape(-1), grid.rhs[k].reshape(-1), ei, weights)
        x_graph, _ = solve_system(graph, None, settings)
        assert torch.allclose(x_graph, exact, rtol=1e-9, atol=1e-10)
        assert torch.allclose(system_conditional_variance(graph), 1 / A.diagonal(), rtol=1e-12)
        exact_std = 2.0 * torch.linalg.inv(A).diagonal().sqrt()  # graphs of <= 1,000 nodes are exact
        assert torch.allclose(posterior_std(graph, torch.tensor(2.0, dtype=torch.float64), samples=4), exact_std,
                              rtol=1e-8)


def test_the_solve_is_differentiable_in_every_part_of_the_system_and_not_in_the_warm_start():
    grid = _grid_system(seed=1, b=1, h=4, w=4)
    parts = [grid.diagonal, grid.rhs, *grid.weights]
    leaves = [p.clone().requires_grad_() for p in parts]
    x0 = torch.zeros_like(grid.rhs, requires_grad=True)
    x, _ = solve_system(System.grid(*leaves), x0, solver_settings(rtol=1e-10))
    x.sum().backward()
    assert all(leaf.grad is not None and bool(leaf.grad.abs().sum() > 0) for leaf in leaves)
    assert x0.grad is None


def test_detached_drops_gradients_and_keeps_values():
    grid = _grid_system()
    live = System.grid(grid.diagonal.clone().requires_grad_(), grid.rhs, *grid.weights)
    fixed = live.detached()
    assert not fixed.diagonal.requires_grad and torch.equal(fixed.diagonal, grid.diagonal)
    assert fixed.is_grid and System.graph(grid.diagonal.reshape(-1), grid.rhs.reshape(-1),
                                          torch.zeros(2, 0, dtype=torch.long), torch.zeros(0)).ptr.tolist() == [0, 60]
