"""Aggregation multigrid on the pixel grid: a V-cycle preconditioner for CG (docs/design.md section 4).

For ``A = diag(d) + L(w)`` on a batch of ``H x W`` 4-grids (:class:`~crfdepth.linalg.operators.PixelGrid`).
Each coarser level joins 2 x 2 blocks of pixels (2 x 1 or 1 x 2 once a side is one pixel
wide). With the piecewise-constant prolongation ``P`` the Galerkin operator ``P^T A P`` is
again a 4-grid system: ``d`` summed over a block, and each coarse edge weight the sum of the
fine edges that cross between its two blocks (edges inside a block cancel in the
Laplacian). So every level is applied with shifted slices, like the finest, without index
arrays or sparse matrices.

One V-cycle approximates ``A^-1 r``: damped Jacobi (``omega`` 0.8) from zero, the residual
restricted by ``P^T`` to the next level, the correction prolonged back, and damped Jacobi
again; at the coarsest level (at most 512 pixels per image) a dense inverse, in float64.
Pre- and post-smoothing are the same symmetric step and ``P^T`` is the transpose of ``P``,
so the cycle is a symmetric positive definite operator: a valid CG preconditioner.

On the KITTI val frame's refinement system (1216 x 352, float64, one CPU thread) it cut
the CG iterations of the differentiated forward solve (rtol 1e-8, warm start) from 200 to
21 and of the adjoint (rtol 1e-5, zero start) from 216 to 25; one iteration costs about
four Jacobi-CG iterations (two grid products per cycle, plus the coarse levels).

Where the compiled kernels run (:mod:`crfdepth.native`, float32 / float64 on the CPU), the whole preconditioned CG
runs in crfdepth/native/multigrid.h (:func:`native_cg`: three fused passes an iteration instead of about a hundred
torch kernels, about 4x faster on 2 threads at 320 x 896); the levels built here are its input, and this eager cycle
remains the reference.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F

from crfdepth.linalg.cg import KrylovResult

OMEGA = 0.8  # Jacobi damping; 0.6 and 1.0 took more CG iterations on the KITTI frame (1.0: 3.5x)
COARSEST_NODES = 512  # per image: the coarsest level is solved by a dense (n, n) inverse


def _factors(height: int, width: int) -> tuple[int, int]:
    return (2 if height > 1 else 1), (2 if width > 1 else 1)


def _block_sum(t: torch.Tensor, fh: int, fw: int) -> torch.Tensor:
    """(B, H, W) -> (B, ceil(H / fh), ceil(W / fw)) sums over fh x fw blocks (zero padding): rows, then columns
    (strided adds, as :meth:`_Level.restrict`; several times faster than a sum over the block's dims)."""
    b, h, w = t.shape
    h2, w2 = -(-h // fh), -(-w // fw)
    t = F.pad(t, (0, w2 * fw - w, 0, h2 * fh - h)).contiguous()
    if fh == 2:
        t = t.view(b, h2, 2 * w2 * fw)
        t = t[:, :, :w2 * fw] + t[:, :, w2 * fw:]
    if fw == 2:
        t = t.reshape(b, h2, w2, 2)
        t = t[..., 0] + t[..., 1]
    return t.reshape(b, h2, w2)


def coarsen(d: torch.Tensor, weight_h: torch.Tensor, weight_v: torch.Tensor):
    """The Galerkin coarse system ``P^T A P`` of the 2 x 2 aggregation, again (d, weight_h, weight_v).

    Args:
        d: (B, H, W); weight_h: (B, H, W-1); weight_v: (B, H-1, W).

    Returns:
        (B, H2, W2), (B, H2, W2-1), (B, H2-1, W2) with ``H2 = ceil(H / 2)`` (1 stays 1), same for W.
    """
    _, h, w = d.shape
    fh, fw = _factors(h, w)
    h2, w2 = -(-h // fh), -(-w // fw)
    # The fine edges between block columns J and J+1 start at column fw J + fw - 1.
    cross_h = weight_h[:, :, fw - 1::fw][:, :, :w2 - 1]
    cross_v = weight_v[:, fh - 1::fh, :][:, :h2 - 1, :]
    return _block_sum(d, fh, fw), _block_sum(cross_h, fh, 1), _block_sum(cross_v, 1, fw)


class _Level:
    """One level: its operator, the Jacobi weights and the work buffers of a V-cycle."""

    def __init__(self, d: torch.Tensor, weight_h: torch.Tensor, weight_v: torch.Tensor) -> None:
        b, h, w = d.shape
        self.shape = (b, h, w)
        self.weight_h, self.weight_v = weight_h, weight_v
        deg = d.clone()
        deg[:, :, :-1] += weight_h
        deg[:, :, 1:] += weight_h
        deg[:, :-1, :] += weight_v
        deg[:, 1:, :] += weight_v
        self.diag = deg
        self.jacobi = OMEGA / deg
        self.fh, self.fw = _factors(h, w)
        self.coarse_shape = (b, -(-h // self.fh), -(-w // self.fw))
        self.padded = (self.coarse_shape[1] * self.fh, self.coarse_shape[2] * self.fw)
        self.x = torch.empty_like(d)
        self.t = torch.empty_like(d)
        self.pad = None if self.padded == (h, w) else d.new_zeros((b, *self.padded))

    def residual(self, r: torch.Tensor, x: torch.Tensor, out: torch.Tensor) -> torch.Tensor:
        """``out = r - A x``, in place (no temporaries)."""
        torch.mul(self.diag, x, out=out)
        torch.sub(r, out, out=out)
        out[:, :, :-1].addcmul_(self.weight_h, x[:, :, 1:])
        out[:, :, 1:].addcmul_(self.weight_h, x[:, :, :-1])
        out[:, :-1, :].addcmul_(self.weight_v, x[:, 1:, :])
        out[:, 1:, :].addcmul_(self.weight_v, x[:, :-1, :])
        return out

    def restrict(self, t: torch.Tensor) -> torch.Tensor:
        """``P^T t``: sums over the blocks, rows then columns (strided adds, ~10x faster than sum over dims)."""
        b, h, w = self.shape
        _, h2, w2 = self.coarse_shape
        if self.pad is not None:
            self.pad[:, :h, :w] = t
            t = self.pad
        wp = self.padded[1]
        if self.fh == 2:
            t = t.view(b, h2, 2 * wp)
            t = t[:, :, :wp] + t[:, :, wp:]
        if self.fw == 2:
            t = t.reshape(b, h2, w2, 2)
            t = t[..., 0] + t[..., 1]
        return t.reshape(b, h2, w2)

    def prolong_add(self, x: torch.Tensor, e: torch.Tensor) -> None:
        """``x += P e`` in place."""
        b, h, w = self.shape
        _, h2, w2 = self.coarse_shape
        spread = e[:, :, None, :, None]
        if self.pad is None:
            x.view(b, h2, self.fh, w2, self.fw).add_(spread)
        else:
            x += spread.expand(b, h2, self.fh, w2, self.fw).reshape(b, *self.padded)[:, :h, :w]


class GridMultigrid:
    """V-cycle preconditioner for ``A = diag(d) + L(w)`` on a batch of pixel grids.

    Args:
        d: (B, H, W) diagonal >= 0; weight_h: (B, H, W-1), weight_v: (B, H-1, W) edge
            weights >= 0 (the system of :func:`crfdepth.linalg.solve_grid_laplacian`; A SPD).

    Calling it on a (B, H, W) residual returns one V-cycle's approximation of
    ``A^-1 r`` (a work buffer, valid until the next call).
    """

    def __init__(self, d: torch.Tensor, weight_h: torch.Tensor, weight_v: torch.Tensor) -> None:
        self.levels = [_Level(d, weight_h, weight_v)]
        while self.levels[-1].shape[1] * self.levels[-1].shape[2] > COARSEST_NODES:
            d, weight_h, weight_v = coarsen(d, weight_h, weight_v)
            self.levels.append(_Level(d, weight_h, weight_v))
        self.coarse_inverse = self._dense_inverse(self.levels[-1])
        self._native: tuple[list[torch.Tensor], torch.Tensor] | None = None  # native_levels(), built once

    @staticmethod
    def _dense_inverse(level: _Level) -> torch.Tensor:
        """(B, n, n) float64 inverse of the coarsest level's matrix ``diag(D) - W``."""
        b, h, w = level.shape
        n = h * w
        matrix = torch.diag_embed(level.diag.reshape(b, n).double())
        node = torch.arange(n, device=matrix.device).view(h, w)
        batch = torch.arange(b, device=matrix.device)[:, None]
        pairs = ((node[:, :-1], node[:, 1:], level.weight_h), (node[:-1, :], node[1:, :], level.weight_v))
        for src, dst, weight in pairs:
            src, dst, weight = src.reshape(1, -1), dst.reshape(1, -1), -weight.reshape(b, -1).double()
            matrix.index_put_((batch, src, dst), weight, accumulate=True)
            matrix.index_put_((batch, dst, src), weight, accumulate=True)
        chol, info = torch.linalg.cholesky_ex(matrix)
        if bool((info == 0).all()):
            return torch.cholesky_inverse(chol)
        return torch.linalg.pinv(matrix, hermitian=True)  # numerically semi-definite: least squares

    def _cycle(self, k: int, r: torch.Tensor) -> torch.Tensor:
        if k == len(self.levels) - 1:
            b = r.shape[0]
            x = torch.bmm(self.coarse_inverse, r.reshape(b, -1, 1).double())
            return x.view(r.shape).to(r.dtype)
        level = self.levels[k]
        x, t = level.x, level.t
        torch.mul(level.jacobi, r, out=x)
        level.residual(r, x, t)
        level.prolong_add(x, self._cycle(k + 1, level.restrict(t)))
        level.residual(r, x, t)
        x.addcmul_(level.jacobi, t)
        return x

    def __call__(self, r: torch.Tensor) -> torch.Tensor:
        return self._cycle(0, r)

    def native_levels(self) -> tuple[list[torch.Tensor], torch.Tensor]:
        """The compiled V-cycle's arguments (crfdepth/native/multigrid.h): ``[diag, omega / diag, weight_h,
        weight_v]`` of every level below the finest (which runs in the scaled form of CG), contiguous, and the
        coarsest level's (B, n, n) float64 inverse."""
        if self._native is None:
            tensors = [t.contiguous() for level in self.levels[1:]
                       for t in (level.diag, level.jacobi, level.weight_h, level.weight_v)]
            self._native = (tensors, self.coarse_inverse.contiguous())
        return self._native


def native_kernels(precondition, scaled_matvec, c: torch.Tensor):
    """The compiled kernels (:mod:`crfdepth.native`) where they can run CG preconditioned by ``precondition``: the
    V-cycle of ``adjoint._scaled_multigrid`` (its ``multigrid`` attribute) on a pixel grid's scaled operator,
    float32 or float64 tensors on the CPU; else None (the eager loop, the reference)."""
    state = getattr(precondition, "multigrid", None)
    weights = getattr(scaled_matvec, "grid_weights", None)
    if state is None or weights is None or c.device.type != "cpu" or c.dtype not in (torch.float32, torch.float64):
        return None
    cycle, sqrt_diag_rows = state
    levels, inverse = cycle.native_levels()
    tensors = (*weights, sqrt_diag_rows, *levels)
    if any(t.dtype != c.dtype or t.device.type != "cpu" for t in tensors) or inverse.dtype != torch.float64:
        return None
    from crfdepth.native import kernels

    return kernels()


def native_cg(native, precondition, weights, c: torch.Tensor, y: torch.Tensor | None, diag_rows: torch.Tensor,
              rtol: float, budget: int):
    """``(y, KrylovResult, true relative residual)`` of the compiled multigrid-preconditioned CG (a convergence
    check after every iteration), as the eager loop gives them; ``y`` None: from zero."""
    cycle, sqrt_diag_rows = precondition.multigrid
    levels, inverse = cycle.native_levels()
    start_zero = y is None
    y = torch.zeros_like(c) if start_zero else y.contiguous().clone()
    out = native.grid_mg_cg(*(w.contiguous() for w in weights), c.contiguous(), diag_rows.contiguous(),
                            sqrt_diag_rows.contiguous(), y, levels, inverse, OMEGA, float(rtol), int(budget),
                            start_zero)
    if out is None:  # the kernel failed (told in a warning): the eager loop runs from the same start
        return None
    out = out.to(c.dtype)
    iterations, recurrence, rel = out[:, 0].long(), out[:, 1], out[:, 2]
    converged = (recurrence <= rtol) & torch.isfinite(recurrence) & torch.isfinite(y).all(dim=1)
    return y, KrylovResult(iterations, recurrence, converged), rel
