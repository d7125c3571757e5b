"""The implicit gradient's accuracy settings (docs/design.md section 4): ``grad_rtol`` and float64 work.

The gradient formulas of the adjoint are exact only at ``A x = b``: a solve whose result
will be differentiated runs to ``min(rtol, grad_rtol)`` (float32 inputs in float64), one
that will not keeps ``rtol`` and its dtype.
"""

from __future__ import annotations

import dataclasses

import pytest
import torch

from crfdepth.errors import InputError
from crfdepth.linalg import adjoint, solve_grid_laplacian, solver_settings
from crfdepth.linalg.diagnostics import GRAD_RTOL

F64 = torch.float64


def hard_grid(seed: int = 0, height: int = 48, width: int = 64):
    """A depth-completion-like grid system: strong data on 3% of pixels, weak prior, varied edges.

    Returns (b, d, weight_h, weight_v, x0): x0 a poor warm start (the data's mean everywhere).
    """
    g = torch.Generator().manual_seed(seed)
    rows = torch.linspace(0, 1, height, dtype=F64)[:, None]
    depth = 5.0 + 20.0 * rows + torch.zeros(height, width, dtype=F64)  # a ground plane
    observed = torch.rand(height, width, generator=g) < 0.03
    d = torch.where(observed, torch.tensor(300.0, dtype=F64), torch.tensor(1e-3, dtype=F64))[None]
    b = d * depth[None]
    weight_h = 0.05 + torch.rand(1, height, width - 1, generator=g, dtype=F64)
    weight_v = 0.05 + torch.rand(1, height - 1, width, generator=g, dtype=F64)
    x0 = torch.full_like(b, float(depth[observed].mean()))
    return b, d, weight_h, weight_v, x0


def _gradients(dtype, **settings):
    b, d, wh, wv, x0 = (t.to(dtype) for t in hard_grid())
    leaves = [t.clone().requires_grad_() for t in (b, d, wh, wv)]
    x, info = solve_grid_laplacian(*leaves, x0=x0, **settings)
    g = torch.Generator().manual_seed(1)
    weights = torch.randn(x.shape, generator=g, dtype=F64).to(dtype)
    ((x - 10.0) ** 2 * weights.abs()).sum().backward()
    return x, [t.grad for t in leaves], info


def _relative_error(grads, reference):
    return max(float((a.double() - r).norm() / r.norm()) for a, r in zip(grads, reference))


def test_differentiated_forward_runs_to_grad_rtol_and_plain_forward_to_rtol():
    b, d, wh, wv, x0 = hard_grid()
    _, info_plain = solve_grid_laplacian(b, d, wh, wv, x0=x0, rtol=1e-5)
    with torch.no_grad():
        _, info_nograd = solve_grid_laplacian(b.requires_grad_(), d, wh, wv, x0=x0, rtol=1e-5)
    x, info_grad = solve_grid_laplacian(b, d, wh, wv, x0=x0, rtol=1e-5)
    assert info_plain.rtol == info_nograd.rtol == 1e-5
    assert info_grad.rtol == GRAD_RTOL and float(info_grad.rel_residual[0]) <= GRAD_RTOL
    _, info_jacobi = solve_grid_laplacian(b, d, wh, wv, x0=x0, rtol=1e-5, preconditioner="jacobi")
    assert info_jacobi.rtol == GRAD_RTOL and int(info_jacobi.iterations[0]) > int(info_plain.iterations[0])
    x.sum().backward()
    assert info_grad.adjoint.rtol == 1e-5  # the adjoint keeps rtol, relative to ||g||
    assert bool(info_grad.adjoint.converged.all())
    _, tighter = solve_grid_laplacian(b, d, wh, wv, x0=x0, rtol=1e-11)
    assert tighter.rtol == 1e-11  # a tighter rtol is kept


def test_default_settings_give_tight_gradients_and_loose_forward_does_not():
    _, reference, _ = _gradients(F64, rtol=1e-13)
    _, default, info = _gradients(F64, rtol=1e-5)
    _, loose, _ = _gradients(F64, rtol=1e-5, grad_rtol=1e-5)  # the forward as before grad_rtol
    assert bool(info.converged.all()) and bool(info.adjoint.converged.all())
    assert _relative_error(default, reference) < 1e-3
    assert _relative_error(loose, reference) > 1e-2


def test_float32_differentiated_solve_iterates_in_float64_and_its_adjoint_in_float32():
    _, reference, _ = _gradients(F64, rtol=1e-13)
    x, grads, info = _gradients(torch.float32, rtol=1e-5)
    assert x.dtype == torch.float32 and all(g.dtype == torch.float32 for g in grads)
    assert info.rtol == GRAD_RTOL and bool(info.converged.all()) and info.rel_residual.dtype == F64
    # the adjoint's rtol 1e-5 is within float32's reach: solved in float32, converged to it
    assert info.adjoint.rel_residual.dtype == torch.float32 and bool(info.adjoint.converged.all())
    assert float(info.adjoint.rel_residual.max()) <= 1e-5
    assert _relative_error(grads, reference) < 1e-3
    with torch.no_grad():  # not differentiated: float32 throughout, rtol as given
        b, d, wh, wv, x0 = (t.float() for t in hard_grid())
        _, plain = solve_grid_laplacian(b, d, wh, wv, x0=x0, rtol=1e-5)
    assert plain.rtol == 1e-5 and plain.rel_residual.dtype == torch.float32


@pytest.mark.parametrize("bad", [0, 1, -1e-8, "1e-8", None])
def test_bad_grad_rtol(bad):
    with pytest.raises(InputError, match="grad_rtol: expected a number in"):
        solver_settings(grad_rtol=bad)
    b, d, wh, wv, _ = hard_grid()
    with pytest.raises(InputError, match="grad_rtol"):
        solve_grid_laplacian(b, d, wh, wv, grad_rtol=bad)


@pytest.mark.parametrize("preconditioner", ["multigrid", "jacobi"])
def test_the_float32_adjoint_gives_the_float64_adjoints_gradient(monkeypatch, preconditioner):
    _, single, info = _gradients(torch.float32, rtol=1e-5, preconditioner=preconditioner)
    assert info.adjoint.rel_residual.dtype == torch.float32
    monkeypatch.setattr(adjoint, "_single_precision_adjoint", lambda ctx, grad_x: (None, None))
    _, double, info64 = _gradients(torch.float32, rtol=1e-5, preconditioner=preconditioner)
    assert info64.adjoint.rel_residual.dtype == F64
    # both adjoints stop at rtol 1e-5: the gradients agree to about that
    assert _relative_error(single, [g.double() for g in double]) < 1e-4


def test_a_float32_adjoint_that_does_not_converge_is_solved_again_in_float64(monkeypatch):
    krylov = adjoint._krylov_solve

    def float32_stalls(layout, matvec, s, diag, b_rows, x0, settings, precondition=None):
        x, info = krylov(layout, matvec, s, diag, b_rows, x0, settings, precondition)
        if b_rows.dtype == torch.float32:  # as if float32 could not resolve the system to rtol
            info = dataclasses.replace(info, converged=torch.zeros_like(info.converged))
        return x, info

    monkeypatch.setattr(adjoint, "_krylov_solve", float32_stalls)
    _, grads, info = _gradients(torch.float32, rtol=1e-5)
    _, reference, _ = _gradients(F64, rtol=1e-13)
    assert info.adjoint.rel_residual.dtype == F64 and bool(info.adjoint.converged.all())
    assert _relative_error(grads, reference) < 1e-3


def test_an_adjoint_tighter_than_float32_can_reach_stays_in_float64():
    _, _, info = _gradients(torch.float32, rtol=1e-7)
    assert info.adjoint.rel_residual.dtype == F64 and float(info.adjoint.rel_residual.max()) <= 1e-7
