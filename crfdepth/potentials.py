"""The CRF's potentials and energy (paper eq. 2-6, DESIGN.md section 3).

Pure functions of tensors. Every pairwise potential is an edge affinity in [0, 1] that
enters the system matrix *as it is*, as the weight of a graph Laplacian:

    E(x) = alpha * sum_i w_i (x_i - z_i)^2
         + beta  * sum_(i,j) e_ij  (x_i - x_j)^2        colour          (colour_affinity)
         + gamma * sum_(i,j) nr_ij (x_i - x_j)^2        surface normal  (normal_affinity)
         + delta * sum_(i,j) dp_ij (x_i - x_j)^2        3D distance     (distance_affinity)
         + eps   * sum_i (x_i - x0_i)^2                 prior toward the initial fill

and its minimiser solves ``A x = b`` with ``A = diag(alpha w + eps) + L(beta e + gamma nr +
delta dp)`` and ``b = alpha w z + eps x0`` (:func:`system_terms`).
"""

from __future__ import annotations

from dataclasses import dataclass

import torch


def colour_affinity(colour_i: torch.Tensor, colour_j: torch.Tensor, sigma_d: torch.Tensor) -> torch.Tensor:
    """``e_ij = exp(-||c_i - c_j||^2 / sigma_d^2)``.

    Args:
        colour_i, colour_j: (..., 3) colours of the two ends of each edge (RGB in [0, 1]).
        sigma_d: scalar tensor > 0, in colour units.

    Returns:
        (...) affinities in (0, 1].
    """
    return torch.exp(-((colour_i - colour_j) ** 2).sum(-1) / sigma_d ** 2)


def normal_affinity(normal_i: torch.Tensor, normal_j: torch.Tensor, sigma_n: torch.Tensor) -> torch.Tensor:
    """``nr_ij = exp((cos_ij - 1) / sigma_n^2)``: the cosine similarity mapped to (0, 1].

    A raw cosine can be negative and would break positive definiteness (DESIGN.md
    section 3); this mapping is 1 for parallel normals and ``exp(-2 / sigma_n^2)`` for
    opposite ones.

    Args:
        normal_i, normal_j: (..., 3) unit normals; a zero vector (unknown normal) gives
            cos = 0, i.e. the affinity of perpendicular normals.
        sigma_n: scalar tensor > 0.
    """
    cos = (normal_i * normal_j).sum(-1).clamp(-1.0, 1.0)
    return torch.exp((cos - 1.0) / sigma_n ** 2)


def distance_affinity(point_i: torch.Tensor, point_j: torch.Tensor, sigma_p: torch.Tensor) -> torch.Tensor:
    """``dp_ij = exp(-||p_i - p_j||^2 / sigma_p^2)`` for (..., 3) camera-frame points in metres."""
    return torch.exp(-((point_i - point_j) ** 2).sum(-1) / sigma_p ** 2)


def data_confidence(count: torch.Tensor, scale: torch.Tensor) -> torch.Tensor:
    """``w_i = scale * n_i / (n_i + 1)``: 0 without LiDAR, growing with the count ``n_i``.

    One LiDAR point gives half the confidence of a well-covered node; the value saturates
    at ``scale`` (a mean over many points is more reliable than one point, but points in
    one node are not independent measurements of its depth).
    """
    count = count.to(scale.dtype)
    return scale * count / (count + 1.0)


@dataclass
class EnergyTerms:
    """One CRF system on a graph (a batch is one block-diagonal graph).

    Node tensors are (N,) and edge tensors (E,), with ``edge_index`` (2, E); on a pixel grid
    use :func:`crfdepth.linalg.grid_edge_index` ordering. Weights are already multiplied
    by nothing: ``alpha``..``delta`` and ``eps`` are applied by :func:`system_terms`.
    """

    z: torch.Tensor  # (N,) aggregated LiDAR depth, metres (anything where w = 0)
    w: torch.Tensor  # (N,) data confidence >= 0
    x_prior: torch.Tensor  # (N,) the initial fill x0, metres
    edge_index: torch.Tensor  # (2, E)
    colour: torch.Tensor | None  # (E,) e_ij
    normal: torch.Tensor | None  # (E,) nr_ij
    distance: torch.Tensor | None  # (E,) dp_ij
    alpha: torch.Tensor
    beta: torch.Tensor
    gamma: torch.Tensor
    delta: torch.Tensor
    eps: torch.Tensor  # effective prior weight (already scaled)

    def edge_weight(self) -> torch.Tensor:
        """(E,) ``beta e + gamma nr + delta dp`` over the potentials that are on."""
        total = torch.zeros_like(self.edge_index[0], dtype=self.w.dtype)
        for scale, term in ((self.beta, self.colour), (self.gamma, self.normal), (self.delta, self.distance)):
            if term is not None:
                total = total + scale * term
        return total


def system_terms(t: EnergyTerms) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """``(b, d, edge_weight)`` of ``A x = b`` with ``A = diag(d) + L(edge_weight)``."""
    d = t.alpha * t.w + t.eps
    b = t.alpha * t.w * t.z + t.eps * t.x_prior
    return b, d, t.edge_weight()


def energy(x: torch.Tensor, t: EnergyTerms) -> dict[str, torch.Tensor]:
    """The energy E(x) (paper eq. 2) of a depth vector, per potential and in total.

    Args:
        x: (N,) node depths in metres (any vector, not only the minimiser).
        t: the system's terms.

    Returns:
        ``{"data", "colour", "normal", "distance", "prior", "total"}``: scalar tensors
        (a potential that is off contributes 0), differentiable in ``x`` and in the terms.
    """
    src, dst = t.edge_index
    sq = (x[src] - x[dst]) ** 2
    zero = x.new_zeros(())
    out = {
        "data": t.alpha * (t.w * (x - t.z) ** 2).sum(),
        "colour": t.beta * (t.colour * sq).sum() if t.colour is not None else zero,
        "normal": t.gamma * (t.normal * sq).sum() if t.normal is not None else zero,
        "distance": t.delta * (t.distance * sq).sum() if t.distance is not None else zero,
        "prior": t.eps * ((x - t.x_prior) ** 2).sum(),
    }
    out["total"] = sum(out.values())
    return out
