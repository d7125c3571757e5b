"""Robust reweighting (IRLS) of the pixel-grid data term (docs/design.md section 3b).

The occlusion gate judges a return only against the returns in a small window; a
see-through return whose nearer neighbours lie further away, or a run of them along a
ring, keeps its full weight. After a solve, the CRF itself predicts every return from its
surroundings, and a return much *deeper* than that prediction is suspect in the same way.

**Leave-one-out prediction.** Row ``k`` of ``A x = b`` on the pixel grid reads
``D_k x_k = a_k z_k + S_k`` with ``a_k`` the data weight of the return, ``D_k`` the whole
diagonal (data, prior and the weights of the edges at ``k``) and ``S_k`` the prior and the
neighbours' pull. With the neighbours held at the solution, the value that ``k`` would
take without its own datum is ``x^_k = S_k / (D_k - a_k)``, so

    z_k - x^_k = (z_k - x_k) D_k / (D_k - a_k)

costs one pass over the solution. (The neighbours still feel ``k``: this underestimates
the residual of a return whose neighbours are pulled towards it, most in 1-D runs.)

**Weight.** The residual is taken in inverse depth whatever the CRF's unknown, as the
gate's lead is (parallax is a difference of inverse depths): ``r_k = 1/x^_k - 1/z_k``
(positive: the return lies behind what its surroundings predict). The data weight is
multiplied by the Geman-McClure factor ``rho_k = (1 + (r_k+ / sigma)^2)^-2`` of the
positive part: only returns *behind* the prediction lose weight, since a LiDAR return in
front of its surroundings is what a thin or small foreground object looks like, and the
camera sees it too. ``rho`` is 1 at ``r <= 0``, 1/4 at ``r = sigma``.

The weights of a round are computed from the (detached) previous solution and are
differentiable in ``sigma``; the final solve is differentiated as usual, so gradients
reach ``sigma`` and every weight through the last system (:func:`reweight`).
"""

from __future__ import annotations

import dataclasses

import torch

from crfdepth.config import DEFAULT_IRLS_SCALE
from crfdepth.linalg import SolveInfo, solve_system
from crfdepth.linalg.operators import PixelGrid
from crfdepth.potentials.energy import Variable, grid_system, to_depth

__all__ = ["DEFAULT_IRLS_SCALE", "leave_one_out", "reweight", "robust_factor"]



def leave_one_out(x: torch.Tensor, z: torch.Tensor, data_weight: torch.Tensor, diagonal: torch.Tensor
                  ) -> torch.Tensor:
    """``x^`` where ``data_weight > 0``: the solution each datum's node would take without it.

    Args:
        x: (B, H, W) the solution; z: (B, H, W) the data (any value where the weight is 0).
        data_weight: (B, H, W) ``a`` >= 0, the data term's diagonal.
        diagonal: (B, H, W) ``D``, the whole diagonal of ``A`` (``D - a > 0``: the prior
            keeps it positive).

    Returns:
        (B, H, W): ``x - (z - x) a / (D - a)`` (equal to ``x`` where ``a = 0``).
    """
    return x - (z - x) * data_weight / (diagonal - data_weight)


def robust_factor(inverse_lead: torch.Tensor, scale: torch.Tensor) -> torch.Tensor:
    """Geman-McClure factor ``(1 + (r+ / scale)^2)^-2`` of the positive part of ``r``.

    Args:
        inverse_lead: ``r = 1/x^ - 1/z`` in 1/m (no gradient is taken through it).
        scale: ``sigma`` > 0 in 1/m, a one-element tensor (gradients reach it).

    Returns:
        Factors in (0, 1], 1 where ``r <= 0``, same shape as ``inverse_lead``.
    """
    q = inverse_lead.detach().clamp_min(0.0) / scale
    return (1.0 + q * q).reciprocal().square()


def reweight(t: dict, x: torch.Tensor, sparse: torch.Tensor, rounds: int, scale: torch.Tensor,
             variable: Variable, settings, infos: list[SolveInfo]) -> tuple[torch.Tensor, dict]:
    """``rounds`` IRLS rounds of a pixel-grid system after its solve ``x``.

    Each round scales the data weight of every return by :func:`robust_factor` of its
    inverse-depth lead over its :func:`leave_one_out` prediction from the previous
    solution, and solves again (warm-started); the last solve carries the gradients.

    Args:
        t: the potentials of :func:`crfdepth.potentials.energy.grid_potentials` that gave ``x``.
        x: (B, H, W) their solution, in the unknown ``variable``.
        sparse: (B, 1, H, W) LiDAR depth in metres, 0 = none.
        rounds: >= 1; scale: ``sigma`` (1/m); settings: the solver settings.
        infos: each solve's :class:`~crfdepth.linalg.SolveInfo` is appended here.

    Returns:
        ``(depth (B, 1, H, W), potentials of the last round)``.
    """
    base, s = t.w, sparse[:, 0]
    inv_z = torch.where(s > 0, s.reciprocal(), torch.zeros_like(s))
    for _ in range(rounds):
        system = grid_system(t)
        x_hat = leave_one_out(x.detach(), t.z, (t.alpha * t.w).detach(),
                              (system.diagonal + PixelGrid.degree(*system.weights)).detach())
        lead = torch.where(s > 0, to_depth(x_hat, variable).clamp_min(1e-3).reciprocal() - inv_z, torch.zeros_like(s))
        t = dataclasses.replace(t, w=base * robust_factor(lead, scale))
        x, info = solve_system(grid_system(t), x, settings)
        infos.append(info)
    return to_depth(x, variable)[:, None], t
