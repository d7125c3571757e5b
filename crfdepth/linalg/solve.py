"""Differentiable solve of ``(diag(d) + L(w)) x = b``: the public, checked entry points (docs/design.md section 4).

- :func:`solve_laplacian` for any batch of graphs given as an edge list,
- :func:`solve_grid_laplacian` for batches of 4-connected pixel grids (fast path).

Both check their inputs before iterating, then call the trusted solves of
:mod:`crfdepth.linalg.adjoint` (Jacobi-preconditioned CG, default, or CGS under
``no_grad``, differentiated by one adjoint solve), so memory does not grow with the
iteration count. :func:`solver_settings` checks the settings once for callers that solve
many times (the model, the layer).
"""

from __future__ import annotations

from typing import Literal

import numpy as np
import torch

from crfdepth.config import check_solver
from crfdepth.errors import InputError
from crfdepth.linalg.adjoint import solve_system
from crfdepth.linalg.diagnostics import GRAD_RTOL, SolveInfo, SolverSettings
from crfdepth.linalg.system import System
from crfdepth.precision import full_precision

Method = Literal["cg", "cgs"]
OnFail = Literal["warn", "raise", "ignore"]
Preconditioner = Literal["auto", "jacobi", "multigrid"]


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


def _check_array(name: str, t, shape: tuple, ref: torch.Tensor, nonneg: bool) -> None:
    """:func:`_check_tensor` with ``shape``, then :func:`_check_float` against ``ref``."""
    _check_tensor(name, t, shape)
    _check_float(name, t, ref, nonneg)


def _warm_start(x0, shape: tuple, b: torch.Tensor) -> torch.Tensor | None:
    """``x0`` checked like ``b`` and detached (no gradient flows to a warm start); None stays None."""
    if x0 is None:
        return None
    _check_array("x0", x0, shape, b, nonneg=False)
    return x0.detach()


def solver_settings(method: Method = "cg", rtol: float = 1e-6, max_iter: int | None = None, check_every: int = 8,
                    on_nonconvergence: OnFail = "warn", grad_rtol: float = GRAD_RTOL,
                    preconditioner: Preconditioner = "auto") -> SolverSettings:
    """The checked settings of a solve, for :mod:`crfdepth.linalg.adjoint`'s trusted solves.

    The arguments are those of :func:`solve_grid_laplacian` (graph solves ignore
    ``preconditioner``: always Jacobi).
    """
    return _check_settings(method, rtol, max_iter, check_every, on_nonconvergence, grad_rtol, preconditioner)


def _check_settings(method, rtol, max_iter, check_every, on_nonconvergence, grad_rtol=GRAD_RTOL,
                    preconditioner="auto") -> SolverSettings:
    check_solver(method, rtol, max_iter)  # the rules of the configuration's Solver group
    if not (isinstance(grad_rtol, (int, float)) and 0 < grad_rtol < 1):
        raise InputError(f"grad_rtol: expected a number in (0, 1), got {grad_rtol!r}")
    if not isinstance(check_every, int) or check_every < 1:
        raise InputError(f"check_every: expected a positive int, got {check_every!r}")
    if on_nonconvergence not in ("warn", "raise", "ignore"):
        raise InputError(f"on_nonconvergence: expected 'warn', 'raise' or 'ignore', got {on_nonconvergence!r}")
    if preconditioner not in ("auto", "jacobi", "multigrid"):
        raise InputError(f"preconditioner: expected 'auto', 'jacobi' or 'multigrid', got {preconditioner!r}")
    if preconditioner == "multigrid" and method != "cg":
        raise InputError(f"preconditioner: 'multigrid' needs method 'cg', got method {method!r}")
    return SolverSettings(str(method), float(rtol), max_iter, check_every, on_nonconvergence,
                     grad_rtol=float(grad_rtol), preconditioner=str(preconditioner))


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
# public API
# ----------------------------------------------------------------------------------------

@full_precision
def solve_laplacian(b: torch.Tensor, d: torch.Tensor, edge_index: torch.Tensor, edge_weight: torch.Tensor, *,
                    ptr: torch.Tensor | None = None, x0: torch.Tensor | None = None, method: Method = "cg",
                    rtol: float = 1e-6, max_iter: int | None = None, check_every: int = 8,
                    on_nonconvergence: OnFail = "warn", grad_rtol: float = GRAD_RTOL) -> tuple[torch.Tensor, SolveInfo]:
    """Solve ``(diag(d) + L(edge_index, edge_weight)) x = b`` for a batch of graphs.

    ``L`` is the weighted graph Laplacian, ``(L x)_i = sum_j w_ij (x_i - x_j)`` over the
    undirected edges ``(i, j)`` (each listed once; a pair listed twice adds its weights).
    A batch of graphs is one block-diagonal system: concatenate their nodes, offset their
    edge indices, and pass the node offsets as ``ptr``. Each graph gets its own CG step
    sizes and convergence test, so a graph of a batch gets the answer it would get alone.

    Differentiable in ``b``, ``d`` and ``edge_weight`` by one adjoint solve (docs/design.md
    section 4); memory does not grow with the iteration count.

    Args:
        b: (N,) right-hand side.
        d: (N,) diagonal, >= 0. Every connected component needs some ``d_i > 0``
            (otherwise A is singular).
        edge_index: (2, E) int64 node indices in ``[0, N)``; edges may not join graphs.
        edge_weight: (E,) weights >= 0.
        ptr: (G + 1,) int64 node offsets of the graphs of a batch (``ptr[0] = 0``,
            ``ptr[-1] = N``, non-decreasing, G >= 1); None for one graph.
        x0: (N,) warm start (no gradient flows to it); None starts from zero.
        method: "cg" (Jacobi-preconditioned Conjugate Gradient, default) or "cgs"
            (Conjugate Gradient Squared as in the paper; can diverge in float32).
        rtol: relative tolerance on ``||b - A x|| / ||b||`` per graph; the adjoint solve
            of the backward pass stops at ``||g - A lam|| <= rtol ||g||``.
        max_iter: iteration cap per solve; default ``10 sqrt(n) + 100`` for the largest
            graph of ``n`` nodes.
        check_every: iterations between convergence checks (each is a host sync).
        on_nonconvergence: "warn" (a :class:`ConvergenceWarning` with the numbers),
            "raise" (:class:`ConvergenceError`) or "ignore"; the adjoint solve too.
        grad_rtol: tolerance of the forward solve when its result will be differentiated
            (grad mode on and ``b``, ``d`` or ``edge_weight`` requiring grad): the tighter
            of ``rtol`` and ``grad_rtol`` is used, and float32 inputs are solved in
            float64. The implicit gradient is exact only at ``A x = b``; on a real
            KITTI frame the shipped model's gradients at a forward ``rtol`` of 1e-5 were
            up to 18% off, at 1e-8 within 0.1% (docs/design.md section 4).

    Returns:
        ``x`` (N,) with b's dtype and device, and :class:`SolveInfo` (per graph; the
        adjoint's diagnostics appear in its ``adjoint`` field once backward has run).
        Float16 / bfloat16 tensors are solved and returned in float32, with
        ``torch.autocast`` off (:mod:`crfdepth.precision`).

    Raises:
        InputError: on mismatched shapes, dtypes or devices, indices out of range or
            across graphs, negative ``d`` or ``edge_weight``, NaN/inf anywhere, or a
            singular system; raised before iterating.
        ConvergenceError: with ``on_nonconvergence="raise"``, a solve (or the adjoint solve)
            that did not converge. A graph whose ``x`` or residual is NaN/inf (a numerically
            singular system, e.g. ``d`` far below the edge weights) is never reported
            converged, and is warned about even under "ignore".

    Second-order gradients (``create_graph=True`` and a gradient of the gradient) are not
    supported and raise a RuntimeError naming ``create_graph``.
    """
    settings = _check_settings(method, rtol, max_iter, check_every, on_nonconvergence, grad_rtol)
    _check_tensor("b", b)
    if b.dim() != 1:
        raise InputError(f"b: expected a 1-D tensor (N,), got shape {tuple(b.shape)}")
    n = b.shape[0]
    _check_float("b", b, b, nonneg=False)
    _check_array("d", d, (n,), b, nonneg=True)
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
        if ptr.dim() == 1 and ptr.numel() < 2:
            raise InputError(f"ptr: expected G + 1 >= 2 node offsets (a batch of at least 1 graph), got "
                             f"{ptr.tolist()}")
        if ptr.dim() != 1 or int(ptr[0]) != 0 or int(ptr[-1]) != n \
                or bool((ptr[1:] < ptr[:-1]).any()):
            raise InputError(f"ptr: expected non-decreasing node offsets from 0 to {n} (G + 1 entries), "
                             f"got {ptr.tolist()[:10]}")
        if num_edges:
            graph = torch.bucketize(edge_index, ptr[1:], right=True)
            if bool((graph[0] != graph[1]).any()):
                e = int(torch.nonzero(graph[0] != graph[1])[0])
                raise InputError(f"edge_index: edge {e} joins nodes {edge_index[:, e].tolist()} of "
                                 f"different graphs (ptr {ptr.tolist()[:10]})")
    x0 = _warm_start(x0, (n,), b)
    _check_positive_definite(d.detach().cpu().numpy(), edge_index[0].cpu().numpy(),
                             edge_index[1].cpu().numpy(), edge_weight.detach().cpu().numpy(), n, "d")
    return solve_system(System.graph(d, b, edge_index, edge_weight, ptr), x0, settings)


@full_precision
def solve_grid_laplacian(b: torch.Tensor, d: torch.Tensor, weight_h: torch.Tensor, weight_v: torch.Tensor, *,
                         x0: torch.Tensor | None = None, method: Method = "cg", rtol: float = 1e-6,
                         max_iter: int | None = None, check_every: int = 8, on_nonconvergence: OnFail = "warn",
                         grad_rtol: float = GRAD_RTOL, preconditioner: Preconditioner = "auto"
                         ) -> tuple[torch.Tensor, SolveInfo]:
    """Solve ``(diag(d) + L) x = b`` on a batch of 4-connected pixel grids.

    The same system as :func:`solve_laplacian` with the edges of
    :func:`~crfdepth.linalg.operators.grid_edge_index`, without index arrays: the
    Laplacian is applied with shifted slices. Each image of the batch is its own graph.

    Args:
        b: (B, H, W) right-hand side, B, H, W >= 1.
        d: (B, H, W) diagonal, >= 0 (see :func:`solve_laplacian` for positivity).
        weight_h: (B, H, W-1) weights >= 0 between pixel (r, c) and (r, c+1).
        weight_v: (B, H-1, W) weights >= 0 between pixel (r, c) and (r+1, c).
        x0, method, rtol, max_iter, check_every, on_nonconvergence, grad_rtol: as in
            :func:`solve_laplacian`.
        preconditioner: of CG: "jacobi" (the scaling of docs/design.md section 4),
            "multigrid" (a V-cycle of 2 x 2 aggregation, :mod:`crfdepth.linalg.multigrid`:
            about 10x fewer iterations, each about 4x as costly) or "auto" (default:
            multigrid for solves that will be differentiated, whose forward runs to
            ``grad_rtol``, and their adjoints, and for images of 4 megapixels or more;
            Jacobi for the rest, such as inference at KITTI's size).
            "multigrid" needs ``method="cg"``.

    Returns:
        ``x`` (B, H, W) and :class:`SolveInfo` with one entry per image.
    """
    settings = _check_settings(method, rtol, max_iter, check_every, on_nonconvergence, grad_rtol,
                               preconditioner)
    _check_tensor("b", b)
    if b.dim() != 3:
        raise InputError(f"b: expected a (B, H, W) tensor, got shape {tuple(b.shape)}")
    if b.numel() == 0:
        raise InputError(f"b: expected a batch of at least 1 image of at least 1x1 pixels, (B, H, W) with "
                         f"B, H, W >= 1, got shape {tuple(b.shape)}")
    bsz, h, w = b.shape
    _check_float("b", b, b, nonneg=False)
    _check_array("d", d, (bsz, h, w), b, nonneg=True)
    _check_array("weight_h", weight_h, (bsz, h, w - 1), b, nonneg=True)
    _check_array("weight_v", weight_v, (bsz, h - 1, w), b, nonneg=True)
    x0 = _warm_start(x0, (bsz, h, w), b)
    if not bool((d > 0).all()):
        from crfdepth.linalg.operators import grid_edge_index

        ei = grid_edge_index(h, w).numpy()
        n = h * w
        src = np.concatenate([ei[0] + k * n for k in range(bsz)])
        dst = np.concatenate([ei[1] + k * n for k in range(bsz)])
        wts = torch.cat([weight_h.detach().reshape(bsz, -1), weight_v.detach().reshape(bsz, -1)], 1)
        _check_positive_definite(d.detach().reshape(-1).cpu().numpy(), src, dst,
                                 wts.reshape(-1).cpu().numpy(), bsz * n, "d")
    return solve_system(System.grid(d, b, weight_h, weight_v), x0, settings)
