"""The implicit-gradient solve of ``(diag(d) + L(w)) x = b`` (docs/design.md section 4).

Algorithm and autograd, no input checks: :mod:`crfdepth.linalg.solve` checks the
arguments of the public functions; the library's own callers pass trusted tensors to
:func:`solve_laplacian_trusted` / :func:`solve_grid_laplacian_trusted`.
"""

from __future__ import annotations

import math
import warnings
from dataclasses import dataclass, field

import torch

from crfdepth.errors import ConvergenceError, ConvergenceWarning
from crfdepth.linalg.krylov import conjugate_gradient, conjugate_gradient_squared
from crfdepth.linalg.operators import EdgeGraph, PixelGrid

_METHODS = {"cg": conjugate_gradient, "cgs": conjugate_gradient_squared}

@dataclass
class SolveInfo:
    """Diagnostics of one batched solve; tensors have one entry per graph (G,).

    Attributes:
        method: "cg" or "cgs".
        iterations: int64 iterations taken per graph (over all restarts).
        rel_residual: ``||b - A x|| / ||b||`` per graph, recomputed from the returned x
            (0 for a graph with ``b = 0``).
        converged: ``rel_residual <= rtol`` per graph.
        rtol: the tolerance asked for.
        adjoint: diagnostics of the adjoint solve, filled in when backward runs.
    """

    method: str
    iterations: torch.Tensor
    rel_residual: torch.Tensor
    converged: torch.Tensor
    rtol: float
    adjoint: "SolveInfo | None" = field(default=None, repr=False)

    def summary(self) -> str:
        return (f"{self.method}: iterations {self.iterations.tolist()}, relative residual "
                f"{[f'{r:.2e}' for r in self.rel_residual.tolist()]} (rtol {self.rtol:g}), "
                f"converged {self.converged.tolist()}")


@dataclass
class _Settings:
    method: str
    rtol: float
    max_iter: int | None
    check_every: int
    on_nonconvergence: str
    restarts: int = 3


# ----------------------------------------------------------------------------------------
# the solve proper
# ----------------------------------------------------------------------------------------

def _default_max_iter(n: int) -> int:
    # CG on a graph Laplacian needs O(sqrt(cond)) ~ O(diameter) iterations.
    return 10 * math.isqrt(max(n, 1)) + 100


def _krylov_solve(layout, scaled_matvec, inv_sqrt_diag_rows, diag_rows, b_rows, x0_rows,
                  settings: _Settings) -> tuple[torch.Tensor, SolveInfo]:
    """Solve on (G, n) rows; restarts from the true residual when the recurrence drifted."""
    s = inv_sqrt_diag_rows
    c = b_rows * s
    y = None if x0_rows is None else x0_rows / s
    max_iter = settings.max_iter if settings.max_iter is not None else _default_max_iter(b_rows.shape[1])
    krylov = _METHODS[settings.method]
    total = torch.zeros(b_rows.shape[0], dtype=torch.int64, device=b_rows.device)
    b_norm = torch.linalg.vector_norm(b_rows, dim=1)
    budget = max_iter
    for attempt in range(settings.restarts + 1):
        with torch.inference_mode():  # skips autograd bookkeeping on every operation
            y, res = krylov(scaled_matvec, c, y, diag_rows, settings.rtol, budget, settings.check_every)
        y = y.clone()  # a normal tensor again, usable by autograd
        total += res.iterations
        # True residual of the original system: r = D^1/2 (c - M y).
        true_res = torch.linalg.vector_norm((c - scaled_matvec(y)) / s, dim=1)
        rel = torch.where(b_norm > 0, true_res / b_norm.clamp_min(torch.finfo(b_norm.dtype).tiny),
                          torch.zeros_like(true_res))
        converged = rel <= settings.rtol
        budget = max_iter - int(total.max())
        if bool(converged.all()) or budget <= 0 or not bool(res.converged.any()):
            break
    x_rows = y * s
    return x_rows, SolveInfo(settings.method, total, rel, converged, settings.rtol)


def _report(info: SolveInfo, settings: _Settings, what: str) -> None:
    if settings.on_nonconvergence == "ignore" or bool(info.converged.all()):
        return
    bad = torch.nonzero(~info.converged).flatten().tolist()
    details = ", ".join(f"graph {g}: {int(info.iterations[g])} iterations, relative residual "
                        f"{float(info.rel_residual[g]):.3e}" for g in bad[:8])
    msg = (f"{what} ({settings.method}) did not reach rtol={settings.rtol:g} for {len(bad)} of "
           f"{info.converged.numel()} graph(s): {details}. Raise max_iter, loosen rtol, or pass a "
           f"warm start x0.")
    if settings.on_nonconvergence == "raise":
        raise ConvergenceError(msg)
    warnings.warn(msg, ConvergenceWarning, stacklevel=4)


class _LaplacianSolve(torch.autograd.Function):
    """``x = A^-1 b`` with ``A = diag(d) + L(w)``, differentiated implicitly.

    Forward: Krylov solve under ``no_grad``.

    Backward (A is symmetric): with ``g = dLoss/dx`` solve ``A lam = g`` once; then, from
    ``dx = A^-1 (db - dA x)``,

    - ``dLoss/db = lam``
    - ``dLoss/dd_i = -lam_i x_i``                      (``dA = diag(dd)``)
    - ``dLoss/dw_ij = -(lam_i - lam_j)(x_i - x_j)``   (``dA = dw_ij (e_i - e_j)(e_i - e_j)^T``)

    No iteration is recorded, so memory is that of a few vectors whatever the iteration
    count. ``x0`` is only a warm start and gets no gradient. First-order only.
    """

    @staticmethod
    def forward(ctx, structure, settings, info_box, x0, b, d, *weights):
        with torch.no_grad():
            x, info, solver_state = _forward_solve(structure, settings, x0, b, d, weights)
        info_box.append(info)
        ctx.structure, ctx.settings, ctx.info = structure, settings, info
        ctx.solver_state = solver_state
        ctx.save_for_backward(x)
        ctx.num_weights = len(weights)
        return x

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx, grad_x):
        (x,) = ctx.saved_tensors
        needs = ctx.needs_input_grad
        if not any(needs[4:]):
            return (None,) * (6 + ctx.num_weights)
        layout, scaled_matvec, s_rows, diag_rows = ctx.solver_state
        g_rows = layout.to_rows(grad_x.contiguous())
        lam_rows, info = _krylov_solve(layout, scaled_matvec, s_rows, diag_rows, g_rows, None, ctx.settings)
        ctx.info.adjoint = info
        _report(info, ctx.settings, "adjoint solve")
        lam = layout.from_rows(lam_rows)
        grad_b = lam if needs[4] else None
        grad_d = -lam * x if needs[5] else None
        grad_w = [None] * ctx.num_weights
        if any(needs[6:]):
            gw = layout.weight_grad(lam, x)
            grad_w = list(gw) if isinstance(gw, tuple) else [gw]
        return (None, None, None, None, grad_b, grad_d, *grad_w)


def _forward_solve(structure, settings, x0, b, d, weights):
    if isinstance(structure, PixelGrid):
        weight_h, weight_v = weights
        diag = d + PixelGrid.degree(weight_h, weight_v)
        s = diag.rsqrt()
        matvec = structure.scaled_matvec(weight_h, weight_v, s)
    else:
        (edge_weight,) = weights
        diag = d + structure.degree(edge_weight)
        s = diag.rsqrt()
        matvec = structure.scaled_matvec(edge_weight, s)
    s_rows = structure.to_rows(s, fill=1.0)
    diag_rows = structure.to_rows(diag, fill=1.0)
    b_rows = structure.to_rows(b)
    x0_rows = None if x0 is None else structure.to_rows(x0)
    x_rows, info = _krylov_solve(structure, matvec, s_rows, diag_rows, b_rows, x0_rows, settings)
    _report(info, settings, "solve")
    return structure.from_rows(x_rows), info, (structure, matvec, s_rows, diag_rows)



def solve_laplacian_trusted(b, d, edge_index, edge_weight, ptr, x0, settings: _Settings):
    """:func:`crfdepth.linalg.solve_laplacian` without input checks (``ptr`` required, ``x0`` detached or None)."""
    box: list[SolveInfo] = []
    x = _LaplacianSolve.apply(EdgeGraph(edge_index, ptr), settings, box, x0, b, d, edge_weight)
    return x, box[0]


def solve_grid_laplacian_trusted(b, d, weight_h, weight_v, x0, settings: _Settings):
    """:func:`crfdepth.linalg.solve_grid_laplacian` without input checks."""
    box: list[SolveInfo] = []
    bsz, h, w = b.shape
    x = _LaplacianSolve.apply(PixelGrid(bsz, h, w), settings, box, x0, b, d, weight_h, weight_v)
    return x, box[0]
