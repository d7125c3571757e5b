"""crfdepth.linalg on bad input: second-order gradients, non-finite solves, empty batches.

- Second-order gradients through the implicit solve are refused with one clear error
  (first-order ones, with or without ``create_graph``, still match finite differences).
- A solve whose x or residual is NaN/inf is never reported converged, whatever the method.
- A batch of no image is refused by name, before any iteration.
"""

from __future__ import annotations

import warnings

import pytest
import torch

from crfdepth.errors import ConvergenceError, ConvergenceWarning, InputError
from crfdepth.linalg import grid_edge_index, solve_grid_laplacian, solve_laplacian
from crfdepth.linalg.cg import conjugate_gradient, conjugate_gradient_squared

F64 = torch.float64
DOUBLE_BACKWARD = "create_graph: second-order gradients (double backward"


def grid(dtype=F64, b=1, h=3, w=4, seed=0):
    g = torch.Generator().manual_seed(seed)
    rhs = torch.randn(b, h, w, generator=g, dtype=F64)
    d = 0.5 + torch.rand(b, h, w, generator=g, dtype=F64)
    wh = 0.2 + torch.rand(b, h, w - 1, generator=g, dtype=F64)
    wv = 0.2 + torch.rand(b, h - 1, w, generator=g, dtype=F64)
    return [t.to(dtype).requires_grad_() for t in (rhs, d, wh, wv)]


def first_line(exc: pytest.ExceptionInfo) -> str:
    return str(exc.value).splitlines()[0]


# ----------------------------------------------------------------------------------------
# item 1: second-order gradients
# ----------------------------------------------------------------------------------------

def test_first_order_gradients_still_pass_gradcheck():
    leaves = grid()
    assert torch.autograd.gradcheck(lambda *t: solve_grid_laplacian(*t, rtol=1e-12)[0], leaves,
                                    atol=1e-6, rtol=1e-4)


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_create_graph_first_order_equals_plain_first_order(dtype):
    leaves = grid(dtype)
    x, _ = solve_grid_laplacian(*leaves, rtol=1e-12)
    plain = torch.autograd.grad((x ** 2).sum(), leaves)
    x, _ = solve_grid_laplacian(*leaves, rtol=1e-12)
    graph = torch.autograd.grad((x ** 2).sum(), leaves, create_graph=True)
    for a, b in zip(plain, graph):
        torch.testing.assert_close(a, b.detach(), rtol=1e-6, atol=1e-6)


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
@pytest.mark.parametrize("loss, wrt", [
    ("square", 0),   # Hessian-vector product in b: through the incoming gradient
    ("linear", 1),   # gradient penalty in d: the loss is linear, only d and the weights carry it
    ("linear", 2),   # ... in the edge weights
])
def test_second_order_gradient_raises_the_clear_error(dtype, loss, wrt):
    leaves = grid(dtype)
    x, _ = solve_grid_laplacian(*leaves, rtol=1e-12)
    value = (x ** 2).sum() if loss == "square" else (x * torch.linspace(1, 2, x.numel(), dtype=dtype).view(x.shape)).sum()
    (g,) = torch.autograd.grad(value, [leaves[wrt]], create_graph=True)
    with pytest.raises(RuntimeError) as exc:
        torch.autograd.grad((g ** 2).sum(), leaves[wrt])
    assert first_line(exc).startswith(DOUBLE_BACKWARD)
    # .backward() of a penalty reaches the same error rather than a silently partial gradient
    x, _ = solve_grid_laplacian(*leaves, rtol=1e-12)
    (g,) = torch.autograd.grad(x.sum() if loss == "linear" else (x ** 2).sum(), [leaves[wrt]], create_graph=True)
    with pytest.raises(RuntimeError, match="create_graph: second-order gradients"):
        (x.sum() + (g ** 2).sum()).backward()


def test_second_order_through_the_graph_solve_raises_the_clear_error():
    h, w = 3, 4
    ei = grid_edge_index(h, w)
    b, d, wh, wv = grid()
    weight = torch.cat([wh.detach().reshape(-1), wv.detach().reshape(-1)]).requires_grad_()
    x, _ = solve_laplacian(b.detach().reshape(-1), d.detach().reshape(-1), ei, weight, rtol=1e-12)
    (g,) = torch.autograd.grad(x.sum(), weight, create_graph=True)
    with pytest.raises(RuntimeError) as exc:
        torch.autograd.grad(g.sum(), weight)
    assert first_line(exc).startswith(DOUBLE_BACKWARD)


# ----------------------------------------------------------------------------------------
# item 2: a non-finite solve is never converged
# ----------------------------------------------------------------------------------------

@pytest.mark.parametrize("krylov", [conjugate_gradient, conjugate_gradient_squared])
@pytest.mark.parametrize("rows", [1, 2])  # one system (CG's host loop) and a batch
def test_every_krylov_method_reports_nan_as_not_converged(krylov, rows):
    c = torch.ones(rows, 6, dtype=F64)

    def matvec(y):  # an operator whose products turn NaN: a broken system
        return y * float("nan")

    _, result = krylov(matvec, c, None, torch.ones_like(c), 1e-6, 20, 1)
    assert not bool(result.converged.any())


def test_every_krylov_method_reports_an_infinite_iterate_as_not_converged():
    c = torch.ones(2, 6, dtype=F64)
    y0 = torch.full_like(c, float("inf"))
    for krylov in (conjugate_gradient, conjugate_gradient_squared):
        _, result = krylov(lambda y: y, c, y0, torch.ones_like(c), 1e-6, 5, 1)
        assert not bool(result.converged.any()), krylov.__name__


@pytest.mark.parametrize("method", ["cg", "cgs"])
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_tiny_right_hand_side_is_solved_not_declared_converged(method, dtype):
    """b of 1e-30 in float32 once had ||b|| = 0: "converged" with x anything. Now the solve is
    scale-free: the answer is 1e-30 times that for b."""
    b, d, wh, wv = (t.detach().to(dtype) for t in grid())
    x_ref, info_ref = solve_grid_laplacian(b, d, wh, wv, method=method, rtol=1e-5)
    x0 = torch.full_like(b, 3.0)  # a warm start far off in the scaled units
    x, info = solve_grid_laplacian(b * 1e-30, d, wh, wv, x0=x0 * 1e-30, method=method, rtol=1e-5)
    assert bool(info.converged.all()) and bool(info_ref.converged.all())
    torch.testing.assert_close(x / 1e-30, x_ref, rtol=1e-3, atol=1e-3)


def test_zero_right_hand_side_with_a_warm_start_gives_exactly_zero():
    b, d, wh, wv = (t.detach() for t in grid())
    x, info = solve_grid_laplacian(torch.zeros_like(b), d, wh, wv, x0=torch.ones_like(b), rtol=1e-8)
    assert bool(info.converged.all()) and float(x.abs().max()) == 0.0


@pytest.mark.parametrize("method", ["cg", "cgs"])
@pytest.mark.parametrize("grad", [False, True])
def test_numerically_singular_system_is_never_converged_with_a_nan(method, grad):
    """d of 1e-30 against edge weights of about 1 and a far warm start: whatever comes out,
    a converged solve has a finite x within rtol, and a failed one says the system is singular."""
    b, d, wh, wv = (t.detach() for t in grid(h=8, w=10))
    d = torch.full_like(d, 1e-30)
    leaves = [t.clone().requires_grad_(grad) for t in (b * 1e-30, d, wh, wv)]
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        with torch.set_grad_enabled(grad):
            x, info = solve_grid_laplacian(*leaves, x0=torch.full_like(b, 1e6), method=method, rtol=1e-5,
                                           on_nonconvergence="warn")
    ok = info.converged
    assert bool(torch.isfinite(x[ok]).all()) and bool((info.rel_residual[ok] <= 1e-5).all())
    assert bool(ok.all()) or any(issubclass(w.category, ConvergenceWarning) for w in caught)


def test_nan_solve_warns_even_under_ignore_and_raises_under_raise():
    # A first-order non-SPD system slipped past the checks (the trusted solve): CG breaks down.
    from crfdepth.linalg import System, solve_system, solver_settings

    b, d, wh, wv = (t.detach() for t in grid())
    system = System.grid(-torch.full_like(d, 1e300), b, wh, wv)
    with pytest.warns(ConvergenceWarning, match="numerically singular"):
        x, info = solve_system(system, None, solver_settings(on_nonconvergence="ignore"))
    assert not bool(info.converged.any())
    with pytest.raises(ConvergenceError) as exc:
        solve_system(system, None, solver_settings(on_nonconvergence="raise"))
    assert first_line(exc).startswith("solve (cg) did not reach rtol=1e-06 for 1 of 1 graph(s)")


# ----------------------------------------------------------------------------------------
# item 3: empty batches
# ----------------------------------------------------------------------------------------

@pytest.mark.parametrize("shape", [(0, 3, 4), (1, 0, 4), (2, 3, 0)])
def test_grid_solve_refuses_an_empty_batch(shape):
    bsz, h, w = shape
    z = lambda *s: torch.ones(*s, dtype=F64)  # noqa: E731
    with pytest.raises(InputError) as exc:
        solve_grid_laplacian(z(bsz, h, w), z(bsz, h, w), z(bsz, h, max(w - 1, 0)), z(bsz, max(h - 1, 0), w))
    assert first_line(exc) == (f"b: expected a batch of at least 1 image of at least 1x1 pixels, (B, H, W) "
                               f"with B, H, W >= 1, got shape {shape}")


def test_graph_solve_refuses_a_batch_of_no_graph_and_solves_an_empty_graph():
    empty = torch.zeros(0, dtype=F64)
    with pytest.raises(InputError) as exc:
        solve_laplacian(empty, empty, torch.zeros(2, 0, dtype=torch.int64), empty, ptr=torch.tensor([0]))
    assert first_line(exc) == "ptr: expected G + 1 >= 2 node offsets (a batch of at least 1 graph), got [0]"
    x, info = solve_laplacian(empty, empty, torch.zeros(2, 0, dtype=torch.int64), empty)
    assert x.shape == (0,) and bool(info.converged.all())
