"""Batched Krylov iterations on symmetrically scaled systems (docs/design.md section 4).

These are plain functions of tensors: no autograd, no knowledge of graphs. They solve
``M y = c`` for a batch of ``G`` independent systems stored as rows of a ``(G, n)``
tensor, where ``matvec(y)`` applies ``M`` row by row. Each system has its own step sizes
(so a block of a batch follows exactly the iterates it would follow alone) and its own
convergence test.

The caller passes the system already scaled by its Jacobi preconditioner,
``M = D^-1/2 A D^-1/2``, ``c = D^-1/2 b`` and ``y = D^1/2 x``: plain CG on ``M`` is then
Jacobi-preconditioned CG on ``A`` with one element-wise product less per iteration. The
convergence test is on the residual of the *original* system,
``||b - A x|| = ||D^1/2 (c - M y)||``, which is why ``residual_weight = D`` is passed.
CG also accepts a further preconditioner of ``M`` (the pixel grid's multigrid V-cycle,
:mod:`crfdepth.linalg.multigrid`).

Host synchronisation (the only way to stop a loop) happens once every ``check_every``
iterations; between checks everything stays on the device.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import torch

MatVec = Callable[[torch.Tensor], torch.Tensor]

# Below this size a CPU solve of one system is bound by per-call overhead and runs its
# vector updates through BLAS (_cg_one_system_on_host); above it, torch's multi-threaded
# element-wise kernels win, and SciPy's BLAS thread pool would compete with torch's
# (measured 7x slower on the 428,032-node pixel grid).
_HOST_LOOP_MAX_NODES = 65536


@dataclass
class KrylovResult:
    """Per-system outcome of a batched Krylov solve; tensors of shape (G,)."""

    iterations: torch.Tensor  # int64: iterations taken (frozen at the check that met rtol)
    rel_residual: torch.Tensor  # ||b - A x|| / ||b|| by the recurrence at the last check
    converged: torch.Tensor  # bool: within rtol, with a finite residual and iterate


def _rowdot(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """(G, n), (G, n) -> (G, 1) row-wise dot products."""
    if a.shape[0] == 1:  # one system: a plain dot is half the dispatch cost of vecdot
        return torch.dot(a.view(-1), b.view(-1)).view(1, 1)
    return torch.linalg.vecdot(a, b).unsqueeze(-1)


class _Monitor:
    """Tracks which systems are still iterating; syncs with the host only in `check`."""

    def __init__(self, c: torch.Tensor, residual_weight: torch.Tensor, rtol: float):
        self.residual_weight = residual_weight
        b_norm = _rowdot(c * residual_weight, c).sqrt()  # ||b|| = ||D^1/2 c||
        self.threshold = rtol * b_norm
        self.b_norm = b_norm
        g = c.shape[0]
        self.active = torch.ones(g, 1, dtype=torch.bool, device=c.device)
        self.iterations = torch.zeros(g, dtype=torch.int64, device=c.device)
        self.rel_residual = torch.ones(g, dtype=c.dtype, device=c.device)

    def check(self, r: torch.Tensor, iteration: int) -> bool:
        """Update the active mask from residual ``r`` after ``iteration`` steps; True when all done."""
        res = _rowdot(r * self.residual_weight, r).clamp_min(0).sqrt()
        rel = torch.where(self.b_norm > 0, res / self.b_norm.clamp_min(torch.finfo(r.dtype).tiny),
                          torch.zeros_like(res))
        # Systems that stopped earlier keep the numbers they stopped with.
        act = self.active.squeeze(-1)
        self.rel_residual = torch.where(act, rel.squeeze(-1), self.rel_residual)
        self.iterations = torch.where(act, torch.full_like(self.iterations, iteration), self.iterations)
        self.active = self.active & (res > self.threshold) & torch.isfinite(res)
        return not bool(self.active.any())

    def result(self, y: torch.Tensor) -> KrylovResult:
        """The outcome for the iterate ``y`` (G, n): a system whose residual or iterate holds NaN/inf
        (a breakdown of a numerically singular system) never counts as converged."""
        converged = self.rel_residual * self.b_norm.squeeze(-1) <= self.threshold.squeeze(-1)
        converged = converged & torch.isfinite(self.rel_residual) & torch.isfinite(y).all(dim=1)
        return KrylovResult(self.iterations, self.rel_residual, converged)


def _start(matvec: MatVec, c: torch.Tensor, y0: torch.Tensor | None, residual_weight: torch.Tensor, rtol: float,
           max_iter: int) -> tuple[torch.Tensor, torch.Tensor, _Monitor, bool]:
    """Initial iterate, its residual ``c - M y``, the convergence monitor, and whether the solve
    ends before the first iteration (converged at ``y0``, or ``max_iter == 0``)."""
    if y0 is None:
        y, r = torch.zeros_like(c), c.clone()
    else:
        y = y0.clone()
        r = c - matvec(y)
    monitor = _Monitor(c, residual_weight, rtol)
    return y, r, monitor, monitor.check(r, 0) or max_iter == 0


def conjugate_gradient(matvec: MatVec, c: torch.Tensor, y0: torch.Tensor | None, residual_weight: torch.Tensor,
                       rtol: float, max_iter: int, check_every: int = 8, precondition: MatVec | None = None
                       ) -> tuple[torch.Tensor, KrylovResult]:
    """Conjugate Gradient on a batch of SPD systems ``M y = c`` (rows of ``c``).

    Args:
        matvec: applies the (G independent) SPD matrices to a (G, n) tensor.
        c: (G, n) right-hand sides.
        y0: (G, n) initial guess, or None for zero.
        residual_weight: (G, n) positive weights ``D``; convergence is
            ``sqrt(sum D r^2) <= rtol * sqrt(sum D c^2)`` per system.
        rtol: relative tolerance.
        max_iter: iteration cap.
        check_every: iterations between convergence checks (host syncs).
        precondition: None (plain CG on ``M``), or an SPD approximation of ``M^-1``
            applied to (G, n) rows, row by row (preconditioned CG; its result may be
            a buffer that the next call overwrites).

    Returns:
        y (G, n) and a :class:`KrylovResult`.
    """
    y, r, monitor, done = _start(matvec, c, y0, residual_weight, rtol, max_iter)
    if done:
        return y, monitor.result(y)
    if precondition is None and c.shape[0] == 1 and c.device.type == "cpu" and c.shape[1] <= _HOST_LOOP_MAX_NODES:
        return _cg_one_system_on_host(matvec, y, r, r.clone(), monitor, max_iter, check_every)
    return _cg_loop(matvec, precondition, y, r, monitor, max_iter, check_every)


def _cg_loop(matvec, precondition, y, r, monitor, max_iter, check_every):
    """The CG loop on torch tensors: with ``z = precondition(r)`` in place of ``r`` in the search
    directions, or plain CG (``z = r``) when ``precondition`` is None."""
    tiny = torch.finfo(r.dtype).tiny
    z = r if precondition is None else precondition(r)
    p = z.clone()
    rz = _rowdot(r, z)
    for it in range(1, max_iter + 1):
        q = matvec(p)
        # Frozen (converged) systems get a zero step and keep their iterate.
        alpha = rz / _rowdot(p, q).clamp_min(tiny) * monitor.active
        y.addcmul_(p, alpha)
        r.addcmul_(q, alpha, value=-1.0)
        if (it % check_every == 0 or it == max_iter) and monitor.check(r, it):
            break
        z = r if precondition is None else precondition(r)
        rz_new = _rowdot(r, z)
        beta = rz_new / rz.clamp_min(tiny)
        rz = rz_new
        p.mul_(beta).add_(z)
    return y, monitor.result(y)


def _cg_one_system_on_host(matvec, y, r, p, monitor, max_iter, check_every):
    """The CG loop for one system on CPU: vector updates by BLAS on the tensors' memory.

    On small graphs (thousands of nodes) the loop is bound by per-call overhead, not
    arithmetic: a BLAS axpy or dot through :mod:`scipy.linalg.blas` on 5,500 doubles costs
    about 1-2 us against 3-5 us for the same torch call, updates in place without
    temporaries, and CPU scalars need no device synchronisation. The arrays share memory
    with ``y`` and ``r`` (``Tensor.numpy()`` does not copy), so the result lands in ``y``;
    the matrix-vector product stays torch's (``matvec.flat`` when the operator offers a
    flat-vector entry point).
    """
    from scipy.linalg import blas

    shape = y.shape
    yv, rv, pv = y.view(-1).numpy(), r.view(-1).numpy(), p.view(-1).numpy()
    axpy, dot, scal = blas.get_blas_funcs(("axpy", "dot", "scal"), (yv,))
    flat = getattr(matvec, "flat", None)
    if flat is None:
        def flat(v):
            return matvec(v.view(shape)).view(-1)
    p_t = torch.from_numpy(pv)
    weight = monitor.residual_weight.view(-1).numpy()
    threshold = float(monitor.threshold)
    rr = float(dot(rv, rv))
    it = 0
    for it in range(1, max_iter + 1):
        q = flat(p_t).numpy()
        pq = float(dot(pv, q))
        if not pq > 0.0:  # exact convergence (p = 0) or breakdown: nothing left to do
            break
        alpha = rr / pq
        axpy(pv, yv, a=alpha)  # y += alpha p   (in place)
        axpy(q, rv, a=-alpha)  # r -= alpha q
        rr_new = float(dot(rv, rv))
        scal(rr_new / rr, pv)  # p = r + beta p
        axpy(rv, pv)
        rr = rr_new
        if it % check_every == 0 and float(dot(rv * weight, rv)) <= threshold * threshold:
            break
    monitor.check(r, it)
    return y, monitor.result(y)


def conjugate_gradient_squared(matvec: MatVec, c: torch.Tensor, y0: torch.Tensor | None, residual_weight: torch.Tensor,
                               rtol: float, max_iter: int, check_every: int = 8) -> tuple[torch.Tensor, KrylovResult]:
    """Conjugate Gradient Squared (Sonneveld), the paper's solver; same contract as CG.

    CGS does not need symmetry and takes two matvecs per iteration; its residual is not
    monotone and it can break down or diverge, in float32 in particular. CG is the right
    method for the SPD systems of crfdepth; CGS is offered to reproduce the paper.
    """
    tiny = torch.finfo(c.dtype).tiny
    y, r, monitor, done = _start(matvec, c, y0, residual_weight, rtol, max_iter)
    if done:
        return y, monitor.result(y)
    r_hat = r.clone()
    rho = _rowdot(r_hat, r)
    u = r.clone()
    p = r.clone()
    q = torch.zeros_like(r)
    for it in range(1, max_iter + 1):
        if it > 1:
            rho_new = _rowdot(r_hat, r)
            beta = rho_new / torch.where(rho.abs() > tiny, rho, torch.full_like(rho, tiny))
            rho = rho_new
            u = r + beta * q
            p = u + beta * (q + beta * p)
        v = matvec(p)
        sigma = _rowdot(r_hat, v)
        alpha = rho / torch.where(sigma.abs() > tiny, sigma, torch.full_like(sigma, tiny)) * monitor.active
        q = u - alpha * v
        uq = u + q
        y.addcmul_(uq, alpha)
        r.addcmul_(matvec(uq), alpha, value=-1.0)
        if (it % check_every == 0 or it == max_iter) and monitor.check(r, it):
            break
    return y, monitor.result(y)
