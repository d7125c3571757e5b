"""Posterior variance of the CRF: ``diag(A^-1)`` exactly or by sampling (docs/design.md section 5).

``exp(-E(x))`` is a Gaussian with precision ``A`` (up to the scale fitted by the model), so
the marginal variance of node ``i`` is ``(A^-1)_ii``.

- Small graphs: exact, from a dense Cholesky factorisation per graph.
- Large graphs: the Rao-Blackwellised Monte Carlo estimator (Papandreou & Yuille 2010;
  Siden et al. 2018). Draw ``x ~ N(0, A^-1)`` by perturbation-optimisation: with
  ``A = diag(d) + B^T diag(w) B`` (``B`` the edge incidence matrix),
  ``xi = sqrt(d) * u + B^T (sqrt(w) * v)`` with standard normal ``u, v`` has covariance
  ``A``, so ``x = A^-1 xi`` has covariance ``A^-1``. Then, since
  ``x_i | x_-i ~ N(x_i - xi_i / A_ii, 1 / A_ii)``,

      (A^-1)_ii = 1 / A_ii + E[(x_i - xi_i / A_ii)^2],

  which is estimated from the samples. The ``1 / A_ii`` part is exact, so the estimate is
  much less noisy than the plain sample variance, and it never falls below the exact
  lower bound ``1 / A_ii``. All samples are solved together as one batched CG solve.

Variances are returned without gradient: the model learns a scale ``s`` on top of them.
"""

from __future__ import annotations

import torch

from crfdepth.config import check_std_samples
from crfdepth.linalg.adjoint import solve_system
from crfdepth.linalg.solve import solver_settings
from crfdepth.linalg.system import System

#: Memory the sampling estimate may use at once; the samples are solved in chunks that fit.
MEMORY_BUDGET_BYTES = 2 * 1024**3
# Vectors of the batched sample solve held per sample and node (CG state, xi, noise, diagonal).
_VECTORS_PER_SAMPLE = 16


def _generator(seed: int | None, device) -> torch.Generator:
    g = torch.Generator(device=device)
    g.manual_seed(0 if seed is None else int(seed))
    return g


def _check_samples(samples: int) -> None:
    check_std_samples(samples, "samples")


@torch.no_grad()
def conditional_variance(d: torch.Tensor, edge_index: torch.Tensor, edge_weight: torch.Tensor) -> torch.Tensor:
    """(N,) ``1 / A_ii`` of ``A = diag(d) + L(edge_index, edge_weight)``: the variance of a
    node given its neighbours, the exact lower bound of ``(A^-1)_ii``."""
    src, dst = edge_index
    n = d.shape[0]
    deg = torch.bincount(src, weights=edge_weight, minlength=n) + torch.bincount(dst, weights=edge_weight, minlength=n)
    return 1.0 / (d + deg.to(d.dtype))


@torch.no_grad()
def grid_conditional_variance(d: torch.Tensor, weight_h: torch.Tensor, weight_v: torch.Tensor) -> torch.Tensor:
    """(B, H, W) ``1 / A_ii`` of the 4-connected grid system of :func:`grid_posterior_variance`."""
    diag = d.clone()
    diag[..., :, :-1] += weight_h
    diag[..., :, 1:] += weight_h
    diag[..., :-1, :] += weight_v
    diag[..., 1:, :] += weight_v
    return 1.0 / diag


@torch.no_grad()
def posterior_variance(
    d: torch.Tensor,
    edge_index: torch.Tensor,
    edge_weight: torch.Tensor,
    *,
    ptr: torch.Tensor | None = None,
    samples: int = 48,
    exact_max_nodes: int = 1000,
    seed: int | None = 0,
    rtol: float = 1e-4,
) -> torch.Tensor:
    """``diag(A^-1)`` for ``A = diag(d) + L(edge_index, edge_weight)``, per node.

    Args:
        d: (N,) diagonal >= 0 (as for :func:`crfdepth.linalg.solve_laplacian`).
        edge_index: (2, E) int64; edge_weight: (E,) >= 0.
        ptr: (G + 1,) node offsets of a batch of graphs, or None for one graph.
        samples: number of Monte Carlo samples when the estimate is used.
        exact_max_nodes: graphs up to this many nodes are inverted exactly (dense
            Cholesky, O(n^3)); beyond it every graph of the batch is estimated.
        seed: seed of the samples (same seed, same estimate).
        rtol: relative tolerance of the sample solves.

    Returns:
        (N,) variances, in the squared unit of ``1 / d`` (metres^2 when the energy is in
        metres^2 and unit-free weights).
    """
    _check_samples(samples)
    n = d.shape[0]
    if ptr is None:
        ptr = torch.tensor([0, n], device=d.device)
    sizes = (ptr[1:] - ptr[:-1]).tolist()
    if max(sizes) <= exact_max_nodes:
        return _exact(d, edge_index, edge_weight, ptr)
    k = samples
    gen = _generator(seed, d.device)
    src, dst = edge_index
    diag = 1.0 / conditional_variance(d, edge_index, edge_weight)
    u = torch.randn(k, n, generator=gen, device=d.device, dtype=d.dtype)
    v = torch.randn(k, edge_index.shape[1], generator=gen, device=d.device, dtype=d.dtype)
    flow = v * edge_weight.sqrt()
    xi = d.sqrt() * u
    xi = xi.index_add(1, src, flow).index_add(1, dst, -flow)
    # One block-diagonal system with k copies of the batch.
    offsets = torch.arange(k, device=d.device) * n
    ei_rep = (edge_index[:, None, :] + offsets[None, :, None]).reshape(2, -1)
    ptr_rep = torch.cat([ptr[:-1][None, :] + offsets[:, None] for _ in range(1)], 0).reshape(-1)
    ptr_rep = torch.cat([ptr_rep, torch.tensor([k * n], device=d.device)])
    x, _ = solve_system(System.graph(d.repeat(k), xi.reshape(-1), ei_rep, edge_weight.repeat(k), ptr_rep), None,
                        solver_settings(rtol=rtol))
    x = x.view(k, n)
    m = x - xi / diag
    return 1.0 / diag + (m * m).mean(0)


@torch.no_grad()
def grid_posterior_variance(
    d: torch.Tensor,
    weight_h: torch.Tensor,
    weight_v: torch.Tensor,
    *,
    samples: int = 48,
    seed: int | None = 0,
    rtol: float = 1e-4,
    max_memory_bytes: int = MEMORY_BUDGET_BYTES,
) -> torch.Tensor:
    """``diag(A^-1)`` on a batch of 4-connected pixel grids, by the sampling estimator.

    Memory is bounded: the samples are solved together in chunks of at most
    ``max_memory_bytes / (16 * B * H * W * bytes per value)`` samples (all at once for a
    KITTI frame; a 4000x3000 float32 image takes 2-3 samples per chunk under the 2 GiB
    default), so a large image costs time, not an out-of-memory kill. One chunk draws
    exactly the noise of the unchunked estimate; several chunks draw it in another order
    (same distribution, another realisation).

    Args:
        d: (B, H, W) diagonal; weight_h: (B, H, W-1); weight_v: (B, H-1, W) (as for
            :func:`crfdepth.linalg.solve_grid_laplacian`).
        samples, seed, rtol: as in :func:`posterior_variance`.
        max_memory_bytes: memory budget of the sample solves.

    Returns:
        (B, H, W) variances.
    """
    _check_samples(samples)
    bsz, h, w = d.shape
    per_sample = _VECTORS_PER_SAMPLE * bsz * h * w * d.element_size()
    chunk = max(1, min(samples, max_memory_bytes // per_sample))
    gen = _generator(seed, d.device)
    diag = 1.0 / grid_conditional_variance(d, weight_h, weight_v)
    total = torch.zeros_like(d)
    for start in range(0, samples, chunk):
        k = min(chunk, samples - start)
        u = torch.randn(k, bsz, h, w, generator=gen, device=d.device, dtype=d.dtype)
        vh = torch.randn(k, bsz, h, w - 1, generator=gen, device=d.device, dtype=d.dtype) * weight_h.sqrt()
        vv = torch.randn(k, bsz, h - 1, w, generator=gen, device=d.device, dtype=d.dtype) * weight_v.sqrt()
        xi = d.sqrt() * u
        del u
        xi[..., :, :-1] += vh
        xi[..., :, 1:] -= vh
        xi[..., :-1, :] += vv
        xi[..., 1:, :] -= vv
        del vh, vv
        samples_system = System.grid(d.repeat(k, 1, 1), xi.reshape(k * bsz, h, w), weight_h.repeat(k, 1, 1),
                                     weight_v.repeat(k, 1, 1))
        x, _ = solve_system(samples_system, None, solver_settings(rtol=rtol))
        m = x.view(k, bsz, h, w) - xi / diag
        total += (m * m).sum(0)
    return 1.0 / diag + total / samples


def system_conditional_variance(system: System) -> torch.Tensor:
    """``1 / A_ii`` of ``system`` (graph or grid), in its node or pixel layout."""
    if system.is_grid:
        return grid_conditional_variance(system.diagonal, *system.weights)
    return conditional_variance(system.diagonal, system.edge_index, system.weights[0])


def posterior_std(system: System, scale: torch.Tensor, *, samples: int, seed: int | None = 0,
                  rtol: float = 1e-4) -> torch.Tensor:
    """``scale * sqrt(diag(A^-1))`` of ``system`` (graph: exact up to 1,000 nodes per graph; grid:
    sampled); the variance carries no gradient, ``scale`` does (docs/design.md section 5)."""
    fixed = system.detached()
    if fixed.is_grid:
        var = grid_posterior_variance(fixed.diagonal, *fixed.weights, samples=samples, seed=seed, rtol=rtol)
    else:
        var = posterior_variance(fixed.diagonal, fixed.edge_index, fixed.weights[0], ptr=fixed.ptr, samples=samples,
                                 seed=seed, rtol=rtol)
    return scale * var.sqrt()


def _exact(d, edge_index, edge_weight, ptr) -> torch.Tensor:
    out = torch.empty_like(d)
    src, dst = edge_index
    for g in range(ptr.numel() - 1):
        lo, hi = int(ptr[g]), int(ptr[g + 1])
        if hi == lo:
            continue
        sel = (src >= lo) & (src < hi)
        s, t, w = src[sel] - lo, dst[sel] - lo, edge_weight[sel].double()
        m = hi - lo
        A = torch.diag(d[lo:hi].double())
        A.index_put_((s, s), w, accumulate=True)
        A.index_put_((t, t), w, accumulate=True)
        A.index_put_((s, t), -w, accumulate=True)
        A.index_put_((t, s), -w, accumulate=True)
        inv = torch.cholesky_inverse(torch.linalg.cholesky(A))
        out[lo:hi] = inv.diagonal().to(d.dtype)
        del m
    return out
