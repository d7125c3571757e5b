"""Differentiable solve of ``(diag(d) + L(w)) x = b`` (DESIGN.md section 4).

Public entry points:

- :func:`solve_laplacian` for any batch of graphs given as an edge list,
- :func:`solve_grid_laplacian` for batches of 4-connected pixel grids (fast path).

Both check their inputs before iterating, solve with Jacobi-preconditioned CG (default)
or CGS under ``no_grad``, and differentiate by one adjoint solve (see
:class:`_LaplacianSolve`), so memory does not grow with the iteration count.
"""

from __future__ import annotations

import math
import warnings
from dataclasses import dataclass, field
from typing import Literal

import numpy as np
import torch

from crfdepth.errors import ConvergenceError, ConvergenceWarning, InputError
from crfdepth.linalg.krylov import conjugate_gradient, conjugate_gradient_squared
from crfdepth.linalg.operators import EdgeGraph, PixelGrid

Method = Literal["cg", "cgs"]
OnFail = Literal["warn", "raise", "ignore"]

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
# input checks
# ----------------------------------------------------------------------------------------

def _check_tensor(name: str, t, shape: tuple | None = None) -> torch.Tensor:
    if not isinstance(t, torch.Tensor):
        raise InputError(f"{name}: expected a torch.Tensor, got {type(t).__name__}")
    if shape is not None and tuple(t.shape) != tuple(shape):
        raise InputError(f"{name}: expected shape {tuple(shape)}, got {tuple(t.shape)}")
    return t


def _check_float(name: str, t: torch.Tensor, ref: torch.Tensor, nonneg: bool) -> None:
    if not t.is_floating_point():
        raise InputError(f"{name}: expected a floating-point tensor, got dtype {t.dtype}")
    if t.dtype != ref.dtype or t.device != ref.device:
        raise InputError(f"{name}: expected dtype {ref.dtype} on {ref.device} like b, "
                         f"got {t.dtype} on {t.device}")
    t = t.detach()  # checks must not record autograd history
    finite = torch.isfinite(t)
    if not bool(finite.all()):
        bad = int((~finite).sum())
        raise InputError(f"{name}: expected finite values, got {bad} NaN/inf entries")
    if nonneg and t.numel() and bool((t < 0).any()):
        raise InputError(f"{name}: expected values >= 0, got minimum {float(t.min()):.4g} "
                         f"({int((t < 0).sum())} negative entries)")


def _check_settings(method, rtol, max_iter, check_every, on_nonconvergence) -> _Settings:
    if method not in _METHODS:
        raise InputError(f"method: expected one of {sorted(_METHODS)}, got {method!r}")
    if not (isinstance(rtol, (int, float)) and 0 < rtol < 1):
        raise InputError(f"rtol: expected a number in (0, 1), got {rtol!r}")
    if max_iter is not None and (not isinstance(max_iter, int) or max_iter < 0):
        raise InputError(f"max_iter: expected a non-negative int or None, got {max_iter!r}")
    if not isinstance(check_every, int) or check_every < 1:
        raise InputError(f"check_every: expected a positive int, got {check_every!r}")
    if on_nonconvergence not in ("warn", "raise", "ignore"):
        raise InputError(f"on_nonconvergence: expected 'warn', 'raise' or 'ignore', got {on_nonconvergence!r}")
    return _Settings(str(method), float(rtol), max_iter, check_every, on_nonconvergence)


def _check_positive_definite(d: np.ndarray, src: np.ndarray, dst: np.ndarray, w: np.ndarray,
                             num_nodes: int, arg_d: str) -> None:
    """A is SPD iff every connected component (through edges with w > 0) has some d > 0."""
    if num_nodes == 0 or (d > 0).all():
        return
    import scipy.sparse as sp
    from scipy.sparse.csgraph import connected_components

    keep = w > 0
    adj = sp.coo_matrix((np.ones(int(keep.sum())), (src[keep], dst[keep])), shape=(num_nodes, num_nodes))
    n_comp, labels = connected_components(adj, directed=False)
    has_data = np.zeros(n_comp, dtype=bool)
    np.logical_or.at(has_data, labels, d > 0)
    if not has_data.all():
        bad = np.flatnonzero(~has_data)
        sizes = np.bincount(labels, minlength=n_comp)[bad]
        first = int(np.flatnonzero(labels == bad[0])[0])
        raise InputError(
            f"{arg_d}: the system is not positive definite: {len(bad)} connected component(s) "
            f"have zero diagonal everywhere (sizes {sizes[:5].tolist()}{'...' if len(bad) > 5 else ''}; "
            f"first contains node {first}). Add a small positive prior to {arg_d} (e.g. eps).")


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


# ----------------------------------------------------------------------------------------
# public API
# ----------------------------------------------------------------------------------------

def solve_laplacian(
    b: torch.Tensor,
    d: torch.Tensor,
    edge_index: torch.Tensor,
    edge_weight: torch.Tensor,
    *,
    ptr: torch.Tensor | None = None,
    x0: torch.Tensor | None = None,
    method: Method = "cg",
    rtol: float = 1e-6,
    max_iter: int | None = None,
    check_every: int = 8,
    on_nonconvergence: OnFail = "warn",
) -> tuple[torch.Tensor, SolveInfo]:
    """Solve ``(diag(d) + L(edge_index, edge_weight)) x = b`` for a batch of graphs.

    ``L`` is the weighted graph Laplacian, ``(L x)_i = sum_j w_ij (x_i - x_j)`` over the
    undirected edges ``(i, j)`` (each listed once; a pair listed twice adds its weights).
    A batch of graphs is one block-diagonal system: concatenate their nodes, offset their
    edge indices, and pass the node offsets as ``ptr``. Each graph gets its own CG step
    sizes and convergence test, so a graph of a batch gets the answer it would get alone.

    Differentiable in ``b``, ``d`` and ``edge_weight`` by one adjoint solve (DESIGN.md
    section 4); memory does not grow with the iteration count.

    Args:
        b: (N,) right-hand side.
        d: (N,) diagonal, >= 0. Every connected component needs some ``d_i > 0``
            (otherwise A is singular).
        edge_index: (2, E) int64 node indices in ``[0, N)``; edges may not join graphs.
        edge_weight: (E,) weights >= 0.
        ptr: (G + 1,) int64 node offsets of the graphs of a batch (``ptr[0] = 0``,
            ``ptr[-1] = N``, non-decreasing); None for one graph.
        x0: (N,) warm start (no gradient flows to it); None starts from zero.
        method: "cg" (Jacobi-preconditioned Conjugate Gradient, default) or "cgs"
            (Conjugate Gradient Squared as in the paper; can diverge in float32).
        rtol: relative tolerance on ``||b - A x|| / ||b||`` per graph.
        max_iter: iteration cap per solve; default ``10 sqrt(n) + 100`` for the largest
            graph of ``n`` nodes.
        check_every: iterations between convergence checks (each is a host sync).
        on_nonconvergence: "warn" (a :class:`ConvergenceWarning` with the numbers),
            "raise" (:class:`ConvergenceError`) or "ignore".

    Returns:
        ``x`` (N,) with b's dtype and device, and :class:`SolveInfo` (per graph).

    Raises:
        InputError: on mismatched shapes, dtypes or devices, indices out of range or
            across graphs, negative ``d`` or ``edge_weight``, NaN/inf anywhere, or a
            singular system; raised before iterating.
    """
    settings = _check_settings(method, rtol, max_iter, check_every, on_nonconvergence)
    _check_tensor("b", b)
    if b.dim() != 1:
        raise InputError(f"b: expected a 1-D tensor (N,), got shape {tuple(b.shape)}")
    n = b.shape[0]
    _check_float("b", b, b, nonneg=False)
    _check_tensor("d", d, (n,))
    _check_float("d", d, b, nonneg=True)
    _check_tensor("edge_index", edge_index)
    if edge_index.dim() != 2 or edge_index.shape[0] != 2:
        raise InputError(f"edge_index: expected shape (2, E), got {tuple(edge_index.shape)}")
    if edge_index.dtype not in (torch.int64, torch.int32):
        raise InputError(f"edge_index: expected an int64 tensor, got dtype {edge_index.dtype}")
    if edge_index.device != b.device:
        raise InputError(f"edge_index: expected device {b.device} like b, got {edge_index.device}")
    edge_index = edge_index.long()
    num_edges = edge_index.shape[1]
    _check_tensor("edge_weight", edge_weight)
    if tuple(edge_weight.shape) != (num_edges,):
        raise InputError(f"edge_weight: expected shape ({num_edges},) (one per edge of edge_index), "
                         f"got {tuple(edge_weight.shape)}")
    _check_float("edge_weight", edge_weight, b, nonneg=True)
    if num_edges and (int(edge_index.min()) < 0 or int(edge_index.max()) >= n):
        raise InputError(f"edge_index: expected node indices in [0, {n}), got range "
                         f"[{int(edge_index.min())}, {int(edge_index.max())}]")
    if ptr is None:
        ptr = torch.tensor([0, n], device=b.device)
    else:
        _check_tensor("ptr", ptr)
        ptr = ptr.to(device=b.device, dtype=torch.int64)
        if ptr.dim() != 1 or ptr.numel() < 2 or int(ptr[0]) != 0 or int(ptr[-1]) != n \
                or bool((ptr[1:] < ptr[:-1]).any()):
            raise InputError(f"ptr: expected non-decreasing node offsets from 0 to {n} (G + 1 entries), "
                             f"got {ptr.tolist()[:10]}")
        if num_edges:
            graph = torch.bucketize(edge_index, ptr[1:], right=True)
            if bool((graph[0] != graph[1]).any()):
                e = int(torch.nonzero(graph[0] != graph[1])[0])
                raise InputError(f"edge_index: edge {e} joins nodes {edge_index[:, e].tolist()} of "
                                 f"different graphs (ptr {ptr.tolist()[:10]})")
    if x0 is not None:
        _check_tensor("x0", x0, (n,))
        _check_float("x0", x0, b, nonneg=False)
        x0 = x0.detach()
    _check_positive_definite(d.detach().cpu().numpy(), edge_index[0].cpu().numpy(),
                             edge_index[1].cpu().numpy(), edge_weight.detach().cpu().numpy(), n, "d")
    structure = EdgeGraph(edge_index, ptr)
    box: list[SolveInfo] = []
    x = _LaplacianSolve.apply(structure, settings, box, x0, b, d, edge_weight)
    return x, box[0]


def solve_grid_laplacian(
    b: torch.Tensor,
    d: torch.Tensor,
    weight_h: torch.Tensor,
    weight_v: torch.Tensor,
    *,
    x0: torch.Tensor | None = None,
    method: Method = "cg",
    rtol: float = 1e-6,
    max_iter: int | None = None,
    check_every: int = 8,
    on_nonconvergence: OnFail = "warn",
) -> tuple[torch.Tensor, SolveInfo]:
    """Solve ``(diag(d) + L) x = b`` on a batch of 4-connected pixel grids.

    The same system as :func:`solve_laplacian` with the edges of
    :func:`~crfdepth.linalg.operators.grid_edge_index`, without index arrays: the
    Laplacian is applied with shifted slices. Each image of the batch is its own graph.

    Args:
        b: (B, H, W) right-hand side.
        d: (B, H, W) diagonal, >= 0 (see :func:`solve_laplacian` for positivity).
        weight_h: (B, H, W-1) weights >= 0 between pixel (r, c) and (r, c+1).
        weight_v: (B, H-1, W) weights >= 0 between pixel (r, c) and (r+1, c).
        x0, method, rtol, max_iter, check_every, on_nonconvergence: as in
            :func:`solve_laplacian`.

    Returns:
        ``x`` (B, H, W) and :class:`SolveInfo` with one entry per image.
    """
    settings = _check_settings(method, rtol, max_iter, check_every, on_nonconvergence)
    _check_tensor("b", b)
    if b.dim() != 3 or b.shape[1] < 1 or b.shape[2] < 1:
        raise InputError(f"b: expected a (B, H, W) tensor, got shape {tuple(b.shape)}")
    bsz, h, w = b.shape
    _check_float("b", b, b, nonneg=False)
    _check_tensor("d", d, (bsz, h, w))
    _check_float("d", d, b, nonneg=True)
    _check_tensor("weight_h", weight_h, (bsz, h, w - 1))
    _check_float("weight_h", weight_h, b, nonneg=True)
    _check_tensor("weight_v", weight_v, (bsz, h - 1, w))
    _check_float("weight_v", weight_v, b, nonneg=True)
    if x0 is not None:
        _check_tensor("x0", x0, (bsz, h, w))
        _check_float("x0", x0, b, nonneg=False)
        x0 = x0.detach()
    if not bool((d > 0).all()):
        from crfdepth.linalg.operators import grid_edge_index

        ei = grid_edge_index(h, w).numpy()
        n = h * w
        src = np.concatenate([ei[0] + k * n for k in range(bsz)])
        dst = np.concatenate([ei[1] + k * n for k in range(bsz)])
        wts = torch.cat([weight_h.detach().reshape(bsz, -1), weight_v.detach().reshape(bsz, -1)], 1)
        _check_positive_definite(d.detach().reshape(-1).cpu().numpy(), src, dst,
                                 wts.reshape(-1).cpu().numpy(), bsz * n, "d")
    structure = PixelGrid(bsz, h, w)
    box: list[SolveInfo] = []
    x = _LaplacianSolve.apply(structure, settings, box, x0, b, d, weight_h, weight_v)
    return x, box[0]
