"""The Gaussian CRF core: one solve, and the posterior std, on a pixel grid or a graph.

Every CRF in crfdepth (the model's superpixel graph and pixel grid, its pixel-level
refinement, and the :class:`~crfdepth.layer.CRFRefine` layer) minimises a quadratic energy

    E(x) = sum_i sum_k u_ki (x_i - t_ki)^2 + sum_(i,j) w_ij (x_i - x_j)^2

with unary terms ``k`` (weight ``u_k >= 0`` pulling towards target ``t_k``: LiDAR, a prior
depth, a network's depth) and pairwise weights ``w_ij >= 0``. Its minimiser solves
``A x = b`` with ``A = diag(d) + L(w)``, ``d = sum_k u_k``, ``b = sum_k u_k t_k``
(:func:`crfdepth.potentials.energy.unary_system`; docs/design.md sections 3 and 4).

:func:`grid_crf` / :func:`graph_crf` solve it with the implicit-gradient CG of
:mod:`crfdepth.linalg` (gradients reach ``d``, ``b`` and ``w``); :func:`grid_crf_std` /
:func:`graph_crf_std` give the predictive standard deviation ``s sqrt(diag(A^-1))``
(docs/design.md section 5; the variance carries no gradient, ``s`` does).

Pure functions that trust their inputs: the public functions that call them
(:class:`crfdepth.model.CRFDepth`, :func:`crfdepth.layer.crf_refine`) check arguments once,
at the boundary (docs/design.md section 8).
"""

from __future__ import annotations

import torch

from crfdepth.linalg.adjoint import SolveInfo, _Settings, solve_grid_laplacian_trusted, solve_laplacian_trusted
from crfdepth.uncertainty.posterior import grid_posterior_variance, posterior_variance

__all__ = ["graph_crf", "graph_crf_std", "grid_crf", "grid_crf_std"]


def grid_crf(d: torch.Tensor, b: torch.Tensor, weight_h: torch.Tensor, weight_v: torch.Tensor, *,
             x0: torch.Tensor | None, settings: _Settings) -> tuple[torch.Tensor, SolveInfo]:
    """The CRF's minimiser on a batch of 4-connected pixel grids.

    Args:
        d, b: (B, H, W) diagonal (> 0 somewhere in every image) and right-hand side.
        weight_h: (B, H, W-1) weights >= 0 between (r, c) and (r, c+1); weight_v:
            (B, H-1, W) between (r, c) and (r+1, c).
        x0: (B, H, W) warm start (no gradient flows to it) or None.
        settings: :func:`crfdepth.linalg.solver_settings`.

    Returns:
        ``x`` (B, H, W), differentiable in ``d``, ``b`` and the weights, and the solve's
        :class:`~crfdepth.linalg.SolveInfo` (one entry per image).
    """
    return solve_grid_laplacian_trusted(b, d, weight_h, weight_v, None if x0 is None else x0.detach(), settings)


def grid_crf_std(d: torch.Tensor, weight_h: torch.Tensor, weight_v: torch.Tensor, std_scale: torch.Tensor, *,
                 samples: int, seed: int | None = 0, rtol: float = 1e-4) -> torch.Tensor:
    """(B, H, W) ``std_scale * sqrt(diag(A^-1))`` of the system of :func:`grid_crf`
    (:func:`crfdepth.uncertainty.posterior.grid_posterior_variance`; gradient only to ``std_scale``)."""
    var = grid_posterior_variance(d.detach(), weight_h.detach(), weight_v.detach(), samples=samples, seed=seed,
                                  rtol=rtol)
    return std_scale * var.sqrt()


def graph_crf(d: torch.Tensor, b: torch.Tensor, edge_index: torch.Tensor, edge_weight: torch.Tensor,
              ptr: torch.Tensor, *, x0: torch.Tensor | None, settings: _Settings) -> tuple[torch.Tensor, SolveInfo]:
    """The CRF's minimiser on a batch of graphs, one block-diagonal system.

    Args:
        d, b: (N,) diagonal and right-hand side; edge_index: (2, E) int64, each undirected
            edge once; edge_weight: (E,) >= 0; ptr: (G + 1,) int64 node offsets (graph
            ``g`` owns nodes ``ptr[g]:ptr[g+1]``).
        x0, settings: as in :func:`grid_crf`.

    Returns:
        ``x`` (N,) and the solve's :class:`~crfdepth.linalg.SolveInfo` (one entry per graph).
    """
    return solve_laplacian_trusted(b, d, edge_index, edge_weight, ptr, None if x0 is None else x0.detach(),
                                   settings)


def graph_crf_std(d: torch.Tensor, edge_index: torch.Tensor, edge_weight: torch.Tensor, ptr: torch.Tensor,
                  std_scale: torch.Tensor, *, samples: int, seed: int | None = 0, rtol: float = 1e-4) -> torch.Tensor:
    """(N,) ``std_scale * sqrt(diag(A^-1))`` of the system of :func:`graph_crf`
    (:func:`crfdepth.uncertainty.posterior.posterior_variance`: exact up to 1,000 nodes per graph)."""
    var = posterior_variance(d.detach(), edge_index, edge_weight.detach(), ptr=ptr, samples=samples, seed=seed,
                             rtol=rtol)
    return std_scale * var.sqrt()
