"""The implicit-gradient solve of ``(diag(d) + L(w)) x = b`` (docs/design.md section 4).

Algorithm and autograd, no input checks: :mod:`crfdepth.linalg.solve` checks the
arguments of the public functions; the library's own callers pass a trusted
:class:`~crfdepth.linalg.system.System` to :func:`solve_system`.
"""

from __future__ import annotations

import dataclasses
import functools
import math

import torch

from crfdepth.linalg.cg import KrylovResult, conjugate_gradient, conjugate_gradient_squared
from crfdepth.linalg.diagnostics import SolveInfo, SolverSettings, report_nonconvergence
from crfdepth.linalg.multigrid import GridMultigrid
from crfdepth.linalg.operators import EdgeGraph, PixelGrid
from crfdepth.linalg.system import System
from crfdepth.precision import HALF, autocast_off, full_dtype

_METHODS = {"cg": conjugate_gradient, "cgs": conjugate_gradient_squared}

# ----------------------------------------------------------------------------------------
# the solve proper
# ----------------------------------------------------------------------------------------

def _default_max_iter(n: int) -> int:
    # CG on a graph Laplacian needs O(sqrt(cond)) ~ O(diameter) iterations.
    return 10 * math.isqrt(max(n, 1)) + 100


def _krylov_solve(layout, scaled_matvec, inv_sqrt_diag_rows, diag_rows, b_rows, x0_rows,
                  settings: SolverSettings, precondition=None) -> tuple[torch.Tensor, SolveInfo]:
    """Solve on (G, n) rows; restarts from the true residual when the recurrence drifted.

    With a ``precondition`` (multigrid) convergence is checked after every iteration: one
    costs more than a host synchronisation.

    Each row is solved for ``b / 2^k`` with ``2^k`` near its largest ``|b_i|`` (exact in floating
    point, the solution scales back exactly), so that norms neither underflow nor overflow: a
    right-hand side of 1e-30 in float32 once had ``||b|| = 0`` and counted as converged whatever x
    was. A row with ``b = 0`` gets its exact answer ``x = 0``. A row whose x or residual is not
    finite never counts as converged.
    """
    scale = _power_of_two_scale(b_rows)
    zero_rhs = scale == 0
    scale = torch.where(zero_rhs, torch.ones_like(scale), scale)
    b_rows = b_rows / scale
    s = inv_sqrt_diag_rows
    c = b_rows * s
    y = None if x0_rows is None else torch.where(zero_rhs, 0.0, x0_rows / scale) / s
    max_iter = settings.max_iter if settings.max_iter is not None else _default_max_iter(b_rows.shape[1])
    krylov = _METHODS[settings.method]
    total = torch.zeros(b_rows.shape[0], dtype=torch.int64, device=b_rows.device)
    b_norm = torch.linalg.vector_norm(b_rows, dim=1)
    budget = max_iter
    extra = {} if precondition is None else {"precondition": precondition}
    check_every = settings.check_every if precondition is None else 1
    native = _native_kernels(scaled_matvec, c, settings, precondition)
    native_mg = None
    if precondition is not None:  # the multigrid V-cycle and CG fused (crfdepth/native/multigrid.h)
        from crfdepth.linalg import multigrid

        native_mg = multigrid.native_kernels(precondition, scaled_matvec, c)
    for attempt in range(settings.restarts + 1):
        step = None  # (y, KrylovResult, relative residual) of a compiled loop; None: it failed or cannot run
        if native is not None:  # the same iteration in three fused passes (crfdepth.native)
            step = _native_cg(native, scaled_matvec.grid_weights, c, y, diag_rows, settings, budget, check_every)
        elif native_mg is not None:
            step = multigrid.native_cg(native_mg, precondition, scaled_matvec.grid_weights, c, y, diag_rows,
                                       settings.rtol, budget)
        if step is not None:
            y, res, rel = step
        else:
            with torch.inference_mode():  # skips autograd bookkeeping on every operation
                y, res = krylov(scaled_matvec, c, y, diag_rows, settings.rtol, budget, check_every, **extra)
            y = y.clone()  # a normal tensor again, usable by autograd
            # True residual of the original system: r = D^1/2 (c - M y).
            true_res = torch.linalg.vector_norm((c - scaled_matvec(y)) / s, dim=1)
            rel = torch.where(b_norm > 0, true_res / b_norm.clamp_min(torch.finfo(b_norm.dtype).tiny),
                              torch.zeros_like(true_res))
        total += res.iterations
        converged = (rel <= settings.rtol) & torch.isfinite(y).all(dim=1)
        budget = max_iter - int(total.max())
        if bool(converged.all()) or budget <= 0 or not bool(res.converged.any()):
            break
    x_rows = y * s * scale
    return x_rows, SolveInfo(settings.method, total, rel, converged, settings.rtol)


def _native_kernels(scaled_matvec, c: torch.Tensor, settings: SolverSettings, precondition):
    """The compiled kernels (:mod:`crfdepth.native`) where they can run this solve: Jacobi CG on a pixel
    grid's operator (its ``grid_weights``), float32 or float64 on the CPU; else None (the eager loop,
    the reference)."""
    weights = getattr(scaled_matvec, "grid_weights", None)
    if weights is None or precondition is not None or settings.method != "cg":
        return None
    return _cpu_kernels(c, *weights)


def _cpu_kernels(*tensors: torch.Tensor):
    """The compiled kernels where ``tensors`` are CPU tensors of one dtype, float32 or float64; else None."""
    if tensors[0].dtype not in (torch.float32, torch.float64):
        return None
    if any(t.device.type != "cpu" or t.dtype != tensors[0].dtype for t in tensors):
        return None
    from crfdepth.native import kernels

    return kernels()


def _native_solve(structure, system: System, x0: torch.Tensor | None, settings: SolverSettings):
    """``(x, SolveInfo)`` of an undifferentiated Jacobi-CG pixel-grid solve by the compiled kernels
    (:mod:`crfdepth.native`: the scaling, the iterations and the true residual in a few fused passes),
    or None where they cannot run it (then the eager path does, the reference)."""
    if not isinstance(structure, PixelGrid) or _use_multigrid(structure, settings, False):
        return None
    tensors = (system.diagonal, system.rhs, *system.weights) + (() if x0 is None else (x0,))
    native = _cpu_kernels(system.rhs, *tensors) if settings.method == "cg" else None
    if native is None:
        return None
    max_iter = settings.max_iter if settings.max_iter is not None else _default_max_iter(structure.height * structure.width)
    solved = native.grid_solve(*(t.contiguous() for t in tensors[:4]), None if x0 is None else x0.contiguous(),
                               float(settings.rtol), int(max_iter), int(settings.check_every), int(settings.restarts))
    if solved is None:  # the kernel failed (told in a warning): the eager path solves
        return None
    x, stats = solved
    rel = stats[:, 1].to(system.rhs.dtype)
    converged = (rel <= settings.rtol) & (stats[:, 2] > 0)
    return x, SolveInfo(settings.method, stats[:, 0].long(), rel, converged, settings.rtol)


def _native_cg(native, weights, c, y, diag_rows, settings: SolverSettings, budget: int, check_every: int):
    """``(y, KrylovResult, true relative residual)`` of the compiled CG, as the eager loop gives them."""
    start_zero = y is None
    y = torch.zeros_like(c) if start_zero else y.contiguous().clone()
    out = native.grid_cg(*(w.contiguous() for w in weights), c.contiguous(), diag_rows.contiguous(), y,
                         float(settings.rtol), int(budget), int(check_every), start_zero)
    if out is None:  # the kernel failed (told in a warning): the eager loop runs from the same start
        return None
    out = out.to(c.dtype)
    iterations, recurrence, rel = out[:, 0].long(), out[:, 1], out[:, 2]
    converged = (recurrence <= settings.rtol) & torch.isfinite(recurrence) & torch.isfinite(y).all(dim=1)
    return y, KrylovResult(iterations, recurrence, converged), rel


def _power_of_two_scale(rows: torch.Tensor) -> torch.Tensor:
    """(G, 1) the power of two just above each row's largest ``|value|``, 0 for a zero row: dividing by
    it is exact and brings the row's largest entry into [0.5, 1)."""
    if rows.shape[1] == 0:
        return rows.new_zeros(rows.shape[0], 1)
    peak = rows.abs().amax(dim=1, keepdim=True)
    usable = torch.isfinite(peak) & (peak > 0)
    exponent = torch.frexp(torch.where(usable, peak, torch.ones_like(peak))).exponent
    return torch.where(peak == 0, torch.zeros_like(peak), torch.exp2(exponent.to(rows.dtype)))


class _LaplacianSolve(torch.autograd.Function):
    """``x = A^-1 b`` with ``A = diag(d) + L(w)``, differentiated implicitly.

    The solve of :func:`solve_system` whose result will be differentiated. Forward: Krylov
    solve under ``no_grad``, to ``min(rtol, grad_rtol)`` and, for float32 (or half) inputs, in float64: the
    gradient below is exact only at ``A x = b``, and an early-stopped ``x`` biases it
    (docs/design.md section 4). ``x`` is returned in the inputs' dtype. On pixel grids
    such a solve is preconditioned by multigrid (:mod:`crfdepth.linalg.multigrid`; the
    ``preconditioner`` setting), other solves by Jacobi.

    Backward (A is symmetric): with ``g = dLoss/dx`` solve ``A lam = g`` once (to ``rtol``
    relative to ``||g||``, with the forward's kind of preconditioner; in float32 for float32 inputs
    where ``rtol`` >= 1e-6, else or if that does not converge in the forward's working precision:
    :func:`_single_precision_adjoint`); then, from
    ``dx = A^-1 (db - dA x)``,

    - ``dLoss/db = lam``
    - ``dLoss/dd_i = -lam_i x_i``                      (``dA = diag(dd)``)
    - ``dLoss/dw_ij = -(lam_i - lam_j)(x_i - x_j)``   (``dA = dw_ij (e_i - e_j)(e_i - e_j)^T``)

    No iteration is recorded, so memory is that of a few vectors whatever the iteration
    count. ``x0`` is only a warm start and gets no gradient.

    First-order only: the backward is not itself differentiable. Under ``create_graph=True`` its
    gradients come back joined to the graph through :class:`_NoDoubleBackward`, so that a second
    differentiation through them raises :data:`DOUBLE_BACKWARD_MESSAGE` instead of silently
    leaving out the terms through the solve (``once_differentiable`` loses those that flow
    through ``d`` and the weights).
    """

    @staticmethod
    def forward(ctx, structure, settings, info_box, x0, b, d, *weights):
        work = torch.float64 if b.dtype in _LOW_PRECISION else b.dtype
        forward_settings = settings
        if settings.grad_rtol < settings.rtol:
            forward_settings = dataclasses.replace(settings, rtol=settings.grad_rtol)
        with torch.no_grad():
            d_work, weights_work = d.to(work), [w.to(work) for w in weights]
            matvec, s_rows, diag_rows, precondition = _scaled_operator(structure, forward_settings, True,
                                                                       d_work, weights_work)
            x0_rows = None if x0 is None else structure.to_rows(x0.to(work))
            x_rows, info = _krylov_solve(structure, matvec, s_rows, diag_rows, structure.to_rows(b.to(work)), x0_rows,
                                         forward_settings, precondition)
            report_nonconvergence(info, forward_settings, "solve")
            x = structure.from_rows(x_rows)
        info_box.append(info)
        ctx.settings, ctx.info = settings, info
        ctx.solver_state = (structure, matvec, s_rows, diag_rows, precondition)
        ctx.system = (d_work, weights_work) if work != b.dtype else None  # for an adjoint in b's precision
        out = x.to(b.dtype)
        # x in the working precision and the output (the same tensor when b is float64): under
        # create_graph the backward ties its gradients to the output, and so to every input, through
        # _NoDoubleBackward
        ctx.save_for_backward(x) if out is x else ctx.save_for_backward(x, out)
        ctx.num_weights = len(weights)
        ctx.dtype = b.dtype
        return out

    @staticmethod
    def backward(ctx, grad_x):
        saved = ctx.saved_tensors
        x, out = saved[0], saved[-1]
        with torch.no_grad():
            grads = _LaplacianSolve._adjoint(ctx, x, grad_x)
        if torch.is_grad_enabled():  # create_graph=True: these gradients may be differentiated again
            grads = _NoDoubleBackward.tie(grads, (grad_x, out))
        return grads

    @staticmethod
    def _adjoint(ctx, x, grad_x):
        needs = ctx.needs_input_grad  # (structure, settings, info_box, x0, b, d, *weights)
        if not any(needs[4:]):
            return (None,) * (6 + ctx.num_weights)
        layout, scaled_matvec, s_rows, diag_rows, precondition = ctx.solver_state
        lam_rows, info = _single_precision_adjoint(ctx, grad_x)
        if lam_rows is None:  # in the forward's working precision
            g_rows = layout.to_rows(grad_x.to(x.dtype).contiguous())
            lam_rows, info = _krylov_solve(layout, scaled_matvec, s_rows, diag_rows, g_rows, None, ctx.settings,
                                           precondition)
        ctx.info.adjoint = info
        report_nonconvergence(info, ctx.settings, "adjoint solve")
        lam = layout.from_rows(lam_rows)
        grad_b = lam.to(ctx.dtype) if needs[4] else None
        grad_d = (-lam * x).to(ctx.dtype) if needs[5] else None
        grad_w = [None] * ctx.num_weights
        if any(needs[6:]):
            gw = layout.weight_grad(lam, x)
            grad_w = [g.to(ctx.dtype) for g in (gw if isinstance(gw, tuple) else (gw,))]
        return (None, None, None, None, grad_b, grad_d, *grad_w)


def _single_precision_adjoint(ctx, grad_x: torch.Tensor):
    """``(lam_rows, SolveInfo)`` of the adjoint in float32 for a float32 solve whose forward ran in float64, else
    ``(None, None)`` (the caller solves in the forward's precision): its ``rtol`` (1e-5) is 150 float32 ulps and the
    gradient is float32; its operator and V-cycle are built again in float32 (4 ms at 320x896) and its iterations
    move half the bytes (51 -> 20 ms for 40). One that does not converge so is solved again in float64."""
    if ctx.system is None or ctx.dtype != torch.float32 or ctx.settings.rtol < 1e-6:
        return None, None
    layout = ctx.solver_state[0]
    d, weights = ctx.system
    operator = _scaled_operator(layout, ctx.settings, True, d.float(), [w.float() for w in weights])
    g_rows = layout.to_rows(grad_x.float().contiguous())
    lam_rows, info = _krylov_solve(layout, *operator[:3], g_rows, None, ctx.settings, operator[3])
    return (lam_rows.double(), info) if bool(info.converged.all()) else (None, None)


DOUBLE_BACKWARD_MESSAGE = (
    "create_graph: second-order gradients (double backward, e.g. a gradient penalty or a Hessian-vector "
    "product) through crfdepth's CRF solve are not supported: its backward is one implicit adjoint solve "
    "(docs/design.md section 4) and is not itself differentiable. First-order gradients are supported, "
    "with or without create_graph=True, as long as they are not differentiated again; differentiate the "
    "inputs of the CRF (not through it) or compute second-order terms by finite differences.")
"""The error of a second differentiation through :class:`_LaplacianSolve` (a RuntimeError, as
torch's own "differentiate twice" errors)."""


class _NoDoubleBackward(torch.autograd.Function):
    """Identity on the gradients of :class:`_LaplacianSolve` whose own backward raises
    :data:`DOUBLE_BACKWARD_MESSAGE`.

    :meth:`tie` makes those gradients depend, in the graph, on the incoming gradient and on
    the solve's output (and through its node on ``b``, ``d`` and the weights): everything they
    depend on in truth, so that any second-order derivative that would flow through the
    solve's backward reaches this node and fails clearly, and none is silently left out.
    """

    @staticmethod
    def forward(ctx, num_grads, *tensors):
        return tuple(t.clone() for t in tensors[:num_grads])

    @staticmethod
    def backward(ctx, *grad_outputs):
        raise RuntimeError(DOUBLE_BACKWARD_MESSAGE)

    @staticmethod
    def tie(grads: tuple, dependencies: tuple) -> tuple:
        present = [i for i, g in enumerate(grads) if g is not None]
        if not present or not any(t.requires_grad for t in dependencies):
            return grads
        tied = _NoDoubleBackward.apply(len(present), *(grads[i] for i in present), *dependencies)
        out = list(grads)
        for i, t in zip(present, tied):
            out[i] = t
        return tuple(out)


_LOW_PRECISION = (torch.float16, torch.bfloat16, torch.float32)


def _differentiable(*tensors: torch.Tensor) -> bool:
    """Will the solve's result be differentiated (grad mode on and an input requiring grad)?"""
    return torch.is_grad_enabled() and any(t.requires_grad for t in tensors)


MULTIGRID_MIN_PIXELS = 4_000_000
"""Pixels per image from which an undifferentiated "auto" solve is preconditioned by multigrid too
(docs/design.md section 10)."""


def _use_multigrid(structure, settings: SolverSettings, differentiable: bool) -> bool:
    """Multigrid for CG on pixel grids: when asked, or ("auto") for solves that will be differentiated
    and for those on images of :data:`MULTIGRID_MIN_PIXELS` or more.

    Measured on 2 CPU threads (``benchmarks/speed.py --solvers``, the model's own solves):
    a multigrid iteration costs about 4 Jacobi ones plus a setup of about 10, so at
    1216 x 352 Jacobi is faster for every solve (the refinement: 40 iterations, 17 ms,
    against 8 and 40 ms), at 2-3 megapixels the two are level, and at 4000 x 3000
    multigrid is 12-23% faster (the refinement: 56 Jacobi iterations, 3.5 s, against 9,
    2.7 s), its iteration count staying put while Jacobi's grows with the image.
    """
    if not isinstance(structure, PixelGrid) or settings.method != "cg":
        return False
    if settings.preconditioner != "auto":
        return settings.preconditioner == "multigrid"
    return differentiable or structure.height * structure.width >= MULTIGRID_MIN_PIXELS


def _scaled_operator(structure, settings, differentiable, d, weights):
    """``(matvec, s_rows, diag_rows, precondition)``: the Jacobi-scaled ``M = D^-1/2 A D^-1/2`` and its
    preconditioner, which the forward solve and the adjoint solve share."""
    precondition = None
    if isinstance(structure, PixelGrid):
        weight_h, weight_v = weights
        diag = d + PixelGrid.degree(weight_h, weight_v)
        s = diag.rsqrt()
        matvec = structure.scaled_matvec(weight_h, weight_v, s)
        if _use_multigrid(structure, settings, differentiable):
            precondition = _scaled_multigrid(GridMultigrid(d, weight_h, weight_v), structure.to_rows(diag.sqrt()))
    else:
        (edge_weight,) = weights
        diag = d + structure.degree(edge_weight)
        s = diag.rsqrt()
        matvec = structure.scaled_matvec(edge_weight, s)
    return matvec, structure.to_rows(s, fill=1.0), structure.to_rows(diag, fill=1.0), precondition


def _scaled_multigrid(cycle: GridMultigrid, sqrt_diag_rows: torch.Tensor):
    """The V-cycle ``B ~ A^-1`` as a preconditioner of the scaled ``M = D^-1/2 A D^-1/2``: ``D^1/2 B D^1/2``."""
    shape = cycle.levels[0].shape

    def precondition(r_rows: torch.Tensor) -> torch.Tensor:
        return sqrt_diag_rows * cycle((sqrt_diag_rows * r_rows).view(shape)).reshape(r_rows.shape)

    precondition.multigrid = (cycle, sqrt_diag_rows)  # for the compiled loop (multigrid.native_kernels)
    return precondition


def solve_system(system: System, x0: torch.Tensor | None, settings: SolverSettings) -> tuple[torch.Tensor, SolveInfo]:
    """``x`` of ``system`` (differentiable in its diagonal, right-hand side and weights) and the
    solve's :class:`SolveInfo`, without input checks; ``x0`` is a warm start, no gradient flows to it.

    A solve that will not be differentiated (inference runs under ``no_grad``) goes straight to the
    Krylov loop, in the system's dtype; one that will goes through :class:`_LaplacianSolve`. Either
    runs with ``torch.autocast`` off, and float16 / bfloat16 tensors of the system are solved and
    returned in float32 (:mod:`crfdepth.precision`): a half-precision solve would be useless."""
    if any(t.dtype in HALF for t in (system.rhs, system.diagonal, *system.weights)):  # from autocast's ops
        work = functools.reduce(torch.promote_types,
                                (full_dtype(t.dtype) for t in (system.rhs, system.diagonal, *system.weights)))
        system = dataclasses.replace(system, diagonal=system.diagonal.to(work), rhs=system.rhs.to(work),
                                     weights=tuple(w.to(work) for w in system.weights))
    if x0 is not None and x0.dtype in HALF:
        x0 = x0.to(system.rhs.dtype)
    structure = PixelGrid(*system.rhs.shape) if system.is_grid else EdgeGraph(system.edge_index, system.ptr)
    tensors = (system.rhs, system.diagonal, *system.weights)
    with autocast_off(system.rhs):
        if _differentiable(*tensors):
            box: list[SolveInfo] = []
            x = _LaplacianSolve.apply(structure, settings, box, None if x0 is None else x0.detach(), *tensors)
            return x, box[0]
        with torch.no_grad():
            solved = _native_solve(structure, system, x0, settings)
            if solved is not None:
                report_nonconvergence(solved[1], settings, "solve")
                return solved
            matvec, s_rows, diag_rows, precondition = _scaled_operator(structure, settings, False, system.diagonal,
                                                                       list(system.weights))
            x_rows, info = _krylov_solve(structure, matvec, s_rows, diag_rows, structure.to_rows(system.rhs),
                                         None if x0 is None else structure.to_rows(x0), settings, precondition)
    report_nonconvergence(info, settings, "solve")
    return structure.from_rows(x_rows), info
