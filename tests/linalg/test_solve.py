"""The differentiable Laplacian solve (docs/design.md section 4) against independent oracles."""

from __future__ import annotations

import warnings

import pytest
import torch

from crfdepth.errors import ConvergenceError, ConvergenceWarning, InputError
from crfdepth.linalg import grid_edge_index, solve_grid_laplacian, solve_laplacian

F64 = torch.float64


def random_graph(n: int, seed: int, edges_per_node: float = 2.0, observed: float = 0.3):
    """A connected-ish random graph: a random spanning path plus random chords."""
    g = torch.Generator().manual_seed(seed)
    perm = torch.randperm(n, generator=g)
    path = torch.stack([perm[:-1], perm[1:]])
    extra = torch.randint(0, n, (2, int(edges_per_node * n)), generator=g)
    extra = extra[:, extra[0] != extra[1]]
    edge_index = torch.cat([path, extra], dim=1)
    w = torch.rand(edge_index.shape[1], generator=g, dtype=F64) + 0.05
    d = torch.where(torch.rand(n, generator=g) < observed, torch.rand(n, generator=g, dtype=F64) + 0.5,
                    torch.zeros(n, dtype=F64)) + 1e-2
    b = torch.randn(n, generator=g, dtype=F64)
    return b, d, edge_index, w


def dense_matrix(d: torch.Tensor, edge_index: torch.Tensor, w: torch.Tensor) -> torch.Tensor:
    """A = diag(d) + L(w), assembled densely and differentiably (the oracle)."""
    n = d.shape[0]
    src, dst = edge_index
    inc = torch.zeros(edge_index.shape[1], n, dtype=w.dtype)
    inc[torch.arange(src.numel()), src] += 1.0
    inc[torch.arange(src.numel()), dst] -= 1.0
    return torch.diag(d) + inc.T @ (w[:, None] * inc)


def batch_of(graphs):
    """Concatenate graphs into one block-diagonal system with node offsets."""
    bs, ds, eis, ws, ptr = [], [], [], [], [0]
    for b, d, ei, w in graphs:
        bs.append(b), ds.append(d), ws.append(w)
        eis.append(ei + ptr[-1])
        ptr.append(ptr[-1] + b.shape[0])
    return torch.cat(bs), torch.cat(ds), torch.cat(eis, 1), torch.cat(ws), torch.tensor(ptr)


@pytest.mark.parametrize("method", ["cg", "cgs"])
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_matches_dense_solve(method, seed):
    b, d, ei, w = random_graph(40, seed)
    x, info = solve_laplacian(b, d, ei, w, method=method, rtol=1e-12, max_iter=2000)
    x_ref = torch.linalg.solve(dense_matrix(d, ei, w), b)
    assert torch.allclose(x, x_ref, rtol=0, atol=1e-8), (x - x_ref).abs().max()
    assert bool(info.converged.all()) and float(info.rel_residual.max()) <= 1e-12
    assert info.method == method and int(info.iterations[0]) > 0


@pytest.mark.parametrize("method", ["cg", "cgs"])
def test_grid_matches_dense_solve_and_edge_path(method):
    g = torch.Generator().manual_seed(3)
    B, H, W = 2, 6, 9
    d = torch.rand(B, H, W, generator=g, dtype=F64) * (torch.rand(B, H, W, generator=g) < 0.2) + 1e-3
    wh = torch.rand(B, H, W - 1, generator=g, dtype=F64)
    wv = torch.rand(B, H - 1, W, generator=g, dtype=F64)
    b = torch.randn(B, H, W, generator=g, dtype=F64)
    x, info = solve_grid_laplacian(b, d, wh, wv, method=method, rtol=1e-12)
    ei = grid_edge_index(H, W)
    assert ei.shape == (2, H * (W - 1) + W * (H - 1))
    for k in range(B):
        w = torch.cat([wh[k].reshape(-1), wv[k].reshape(-1)])
        x_ref = torch.linalg.solve(dense_matrix(d[k].reshape(-1), ei, w), b[k].reshape(-1))
        assert torch.allclose(x[k].reshape(-1), x_ref, rtol=0, atol=1e-8)
        x_edge, _ = solve_laplacian(b[k].reshape(-1), d[k].reshape(-1), ei, w, method=method, rtol=1e-12)
        assert torch.allclose(x[k].reshape(-1), x_edge, rtol=0, atol=1e-9)
    assert info.converged.tolist() == [True, True]


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_gradcheck_edge_graph(seed):
    b, d, ei, w = random_graph(12, seed)
    args = (b.requires_grad_(), d.requires_grad_(), w.requires_grad_())
    assert torch.autograd.gradcheck(lambda b, d, w: solve_laplacian(b, d, ei, w, rtol=1e-13)[0], args)


def test_gradcheck_batch_of_three_graphs_of_different_sizes():
    b, d, ei, w, ptr = batch_of([random_graph(n, s) for n, s in ((5, 10), (9, 11), (7, 12))])
    args = (b.requires_grad_(), d.requires_grad_(), w.requires_grad_())
    assert torch.autograd.gradcheck(lambda b, d, w: solve_laplacian(b, d, ei, w, ptr=ptr, rtol=1e-13)[0], args)


@pytest.mark.parametrize("method", ["cg", "cgs"])
def test_gradcheck_grid(method):
    g = torch.Generator().manual_seed(4)
    B, H, W = 2, 4, 5
    args = (torch.randn(B, H, W, generator=g, dtype=F64),
            torch.rand(B, H, W, generator=g, dtype=F64) + 0.05,
            torch.rand(B, H, W - 1, generator=g, dtype=F64),
            torch.rand(B, H - 1, W, generator=g, dtype=F64))
    args = tuple(a.requires_grad_() for a in args)
    fn = lambda b, d, wh, wv: solve_grid_laplacian(b, d, wh, wv, method=method, rtol=1e-13)[0]  # noqa: E731
    assert torch.autograd.gradcheck(fn, args)


def test_implicit_gradients_equal_unrolled_dense_gradients():
    b, d, ei, w = random_graph(30, 5)
    g = torch.Generator().manual_seed(6)
    weights = torch.randn(30, generator=g, dtype=F64)

    def loss_of(x):
        return (weights * x).sum() + (x ** 2).sum()

    leaves = [t.clone().requires_grad_() for t in (b, d, w)]
    x, _ = solve_laplacian(*leaves[:2], ei, leaves[2], rtol=1e-13)
    implicit = torch.autograd.grad(loss_of(x), leaves)
    leaves_ref = [t.clone().requires_grad_() for t in (b, d, w)]
    x_ref = torch.linalg.solve(dense_matrix(leaves_ref[1], ei, leaves_ref[2]), leaves_ref[0])
    reference = torch.autograd.grad(loss_of(x_ref), leaves_ref)
    for name, a, r in zip(("b", "d", "edge_weight"), implicit, reference):
        assert torch.allclose(a, r, rtol=1e-7, atol=1e-9), f"{name}: {(a - r).abs().max()}"


def test_batch_blocks_equal_solving_alone():
    graphs = [random_graph(n, s) for n, s in ((25, 20), (60, 21), (40, 22))]
    b, d, ei, w, ptr = batch_of(graphs)
    x, info = solve_laplacian(b, d, ei, w, ptr=ptr, rtol=1e-10)
    assert info.iterations.shape == (3,) and bool(info.converged.all())
    for k, (bk, dk, eik, wk) in enumerate(graphs):
        xk, infok = solve_laplacian(bk, dk, eik, wk, rtol=1e-10)
        assert torch.allclose(x[ptr[k]:ptr[k + 1]], xk, rtol=0, atol=1e-12)
        assert int(info.iterations[k]) == int(infok.iterations[0])


def test_grid_batch_equals_single_images():
    g = torch.Generator().manual_seed(7)
    b = torch.randn(3, 8, 10, generator=g, dtype=F64)
    d = torch.rand(3, 8, 10, generator=g, dtype=F64) + 0.01
    wh = torch.rand(3, 8, 9, generator=g, dtype=F64)
    wv = torch.rand(3, 7, 10, generator=g, dtype=F64)
    x, _ = solve_grid_laplacian(b, d, wh, wv, rtol=1e-10)
    for k in range(3):
        xk, _ = solve_grid_laplacian(b[k:k + 1], d[k:k + 1], wh[k:k + 1], wv[k:k + 1], rtol=1e-10)
        assert torch.allclose(x[k], xk[0], rtol=0, atol=1e-12)


def test_warm_start_from_solution_takes_no_iterations():
    b, d, ei, w = random_graph(50, 8)
    x, _ = solve_laplacian(b, d, ei, w, rtol=1e-10)
    x2, info = solve_laplacian(b, d, ei, w, rtol=1e-8, x0=x)
    assert int(info.iterations[0]) == 0
    assert torch.equal(x, x2)


def test_float32_solve_and_zero_rhs():
    b, d, ei, w = random_graph(50, 9)
    x32, info = solve_laplacian(b.float(), d.float(), ei, w.float(), rtol=1e-5)
    x64 = torch.linalg.solve(dense_matrix(d, ei, w), b)
    assert x32.dtype == torch.float32
    assert float((x32.double() - x64).abs().max() / x64.abs().max()) < 1e-4
    x0, info0 = solve_laplacian(torch.zeros_like(b), d, ei, w)
    assert torch.count_nonzero(x0) == 0 and float(info0.rel_residual[0]) == 0.0


def test_nonconvergence_warns_with_numbers_or_raises():
    b, d, ei, w = random_graph(200, 10, observed=0.02)
    with pytest.warns(ConvergenceWarning, match=r"graph 0: 3 iterations, relative residual \d") as caught:
        _, info = solve_laplacian(b, d, ei, w, max_iter=3, check_every=1)
    assert not bool(info.converged[0]) and int(info.iterations[0]) == 3
    assert caught[0].filename == __file__  # the warning names the caller's line, not the library's
    w.requires_grad_(True)  # the differentiated solve (through autograd) names it too
    with pytest.warns(ConvergenceWarning) as caught:
        solve_laplacian(b, d, ei, w, max_iter=3, check_every=1)
    assert caught[0].filename == __file__
    w = w.detach()
    with pytest.raises(ConvergenceError, match="did not reach rtol"):
        solve_laplacian(b, d, ei, w, max_iter=3, on_nonconvergence="raise")
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        solve_laplacian(b, d, ei, w, max_iter=3, on_nonconvergence="ignore")


def test_backward_memory_does_not_grow_with_iterations():
    """Autograd keeps the solution only: saved tensors are independent of the iteration count."""
    b, d, ei, w = random_graph(300, 11, observed=0.02)
    saved = []

    def pack(t):
        saved.append(t.numel())
        return t

    for rtol in (1e-2, 1e-12):
        saved.clear()
        leaves = [t.clone().requires_grad_() for t in (b, d, w)]
        with torch.autograd.graph.saved_tensors_hooks(pack, lambda t: t):
            x, info = solve_laplacian(leaves[0], leaves[1], ei, leaves[2], rtol=rtol, max_iter=5000,
                                      grad_rtol=rtol)  # the forward runs to rtol, grad or not
        x.sum().backward()
        assert sum(saved) == 300  # just x, whatever the iteration count
    assert int(info.iterations[0]) > 30


def _case():
    return random_graph(10, 0)


@pytest.mark.parametrize("mutate, match", [
    (lambda b, d, ei, w: (b, d, ei, w[:-1]), r"edge_weight: expected shape \(\d+,\)"),
    (lambda b, d, ei, w: (b, d[:-1], ei, w), r"d: expected shape \(10,\)"),
    (lambda b, d, ei, w: (b[None], d, ei, w), r"b: expected a 1-D tensor"),
    (lambda b, d, ei, w: (b, d, ei[:1], w), r"edge_index: expected shape \(2, E\)"),
    (lambda b, d, ei, w: (b, d, ei + 5, w), r"edge_index: expected node indices in \[0, 10\)"),
    (lambda b, d, ei, w: (b, d, ei.float(), w), r"edge_index: expected an int64 tensor"),
    (lambda b, d, ei, w: (b, d, ei, -w), r"edge_weight: expected values >= 0"),
    (lambda b, d, ei, w: (b, -d, ei, w), r"d: expected values >= 0"),
    (lambda b, d, ei, w: (b.clone().index_fill_(0, torch.tensor([3]), float("nan")), d, ei, w),
     r"b: expected finite values, got 1 NaN/inf"),
    (lambda b, d, ei, w: (b, d, ei, w.clone().index_fill_(0, torch.tensor([0]), float("inf"))),
     r"edge_weight: expected finite values"),
    (lambda b, d, ei, w: (b, d.float(), ei, w), r"d: expected dtype torch.float64"),
    (lambda b, d, ei, w: (b, torch.zeros_like(d), ei, w), r"d: the system is not positive definite"),
])
def test_bad_input_raises_before_iterating(mutate, match):
    with pytest.raises(InputError, match=match):
        solve_laplacian(*mutate(*_case()))


def test_zero_diagonal_component_is_found_among_good_ones():
    b, d, ei, w, ptr = batch_of([random_graph(10, 1), random_graph(6, 2)])
    d[10:] = 0.0  # the second graph has no data at all
    with pytest.raises(InputError, match=r"1 connected component\(s\) have zero diagonal"):
        solve_laplacian(b, d, ei, w, ptr=ptr)


def test_bad_ptr_and_cross_graph_edges():
    b, d, ei, w, ptr = batch_of([random_graph(10, 1), random_graph(6, 2)])
    with pytest.raises(InputError, match=r"ptr: expected non-decreasing node offsets from 0 to 16"):
        solve_laplacian(b, d, ei, w, ptr=torch.tensor([0, 10, 15]))
    ei_bad = torch.cat([ei, torch.tensor([[2], [12]])], 1)
    with pytest.raises(InputError, match=r"edge_index: edge \d+ joins nodes \[2, 12\] of different graphs"):
        solve_laplacian(b, d, ei_bad, torch.cat([w, w[:1]]), ptr=ptr)


def test_bad_settings():
    b, d, ei, w = _case()
    with pytest.raises(InputError, match="method: expected one of"):
        solve_laplacian(b, d, ei, w, method="gmres")
    with pytest.raises(InputError, match="rtol: expected a number in"):
        solve_laplacian(b, d, ei, w, rtol=0)
    with pytest.raises(InputError, match="x0: expected shape"):
        solve_laplacian(b, d, ei, w, x0=b[:3])


def test_grid_bad_input():
    b = torch.zeros(1, 4, 5, dtype=F64)
    d = torch.ones(1, 4, 5, dtype=F64)
    wh = torch.ones(1, 4, 4, dtype=F64)
    wv = torch.ones(1, 3, 5, dtype=F64)
    with pytest.raises(InputError, match=r"weight_h: expected shape \(1, 4, 4\), got \(1, 4, 5\)"):
        solve_grid_laplacian(b, d, torch.ones(1, 4, 5, dtype=F64), wv)
    with pytest.raises(InputError, match=r"weight_v: expected values >= 0"):
        solve_grid_laplacian(b, d, wh, -wv)
    with pytest.raises(InputError, match=r"d: the system is not positive definite"):
        solve_grid_laplacian(b, torch.zeros_like(d), wh, wv)
    wh_cut = wh.clone()
    wh_cut[..., 2] = 0.0
    wv_cut = torch.zeros_like(wv)
    d_half = torch.zeros_like(d)
    d_half[..., :2] = 1.0  # left part has data, right part (cut off) has none
    # Each of the 4 rows is cut after column 2: four data-free pieces of 2 pixels.
    with pytest.raises(InputError, match=r"4 connected component\(s\) .* \(sizes \[2, 2, 2, 2\]"):
        solve_grid_laplacian(b, d_half, wh_cut, wv_cut)


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
def test_cuda_matches_cpu():
    b, d, ei, w = random_graph(100, 12)
    x_cpu, _ = solve_laplacian(b, d, ei, w, rtol=1e-10)
    x_gpu, info = solve_laplacian(b.cuda(), d.cuda(), ei.cuda(), w.cuda(), rtol=1e-10)
    assert x_gpu.device.type == "cuda" and torch.allclose(x_gpu.cpu(), x_cpu, atol=1e-9)
