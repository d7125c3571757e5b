"""The CRF's potentials and energy (paper eq. 2-6, docs/design.md section 3).

Pure functions of tensors. Every pairwise potential is an edge affinity in [0, 1] that
enters the system matrix *as it is*, as the weight of a graph Laplacian:

    E(x) = alpha * sum_i w_i (x_i - z_i)^2
         + beta  * sum_(i,j) e_ij  (x_i - x_j)^2        colour          (colour_affinity)
         + gamma * sum_(i,j) nr_ij (x_i - x_j)^2        surface normal  (normal_affinity)
         + delta * sum_(i,j) dp_ij (x_i - x_j)^2        3D distance     (distance_affinity)
         + eps   * sum_i (x_i - x0_i)^2                 prior toward the initial fill

and its minimiser solves ``A x = b`` with ``A = diag(alpha w + eps) + L(beta e + gamma nr +
delta dp)`` and ``b = alpha w z + eps x0``: the :class:`~crfdepth.linalg.system.System` of
:func:`graph_system` (superpixel graphs) or :func:`grid_system` (pixel grids).
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Literal

import torch

from crfdepth.config import Variable
from crfdepth.geometry.normals import camera_points, dense_normals
from crfdepth.linalg.operators import grid_edge_index
from crfdepth.linalg.system import System
from crfdepth.potentials.compiled import fused_affinities, fused_system


def to_unknown(depth: torch.Tensor, variable: Variable) -> torch.Tensor:
    """The CRF's unknown for a depth map in metres: ``z``, ``1/z`` or ``log z`` (0 stays 0: no data there;
    every use of the unknown at an empty pixel has weight 0)."""
    if variable == "depth":
        return depth
    if variable == "log":
        return torch.where(depth > 0, torch.log(depth.clamp_min(1e-6)), torch.zeros_like(depth))
    return torch.where(depth > 0, 1.0 / depth.clamp_min(1e-6), torch.zeros_like(depth))


def to_depth(x: torch.Tensor, variable: Variable) -> torch.Tensor:
    """Depth in metres from the CRF's unknown (inverse of :func:`to_unknown` where ``x > 0``).

    The solution of an inverse-depth system is positive (``A`` is an M-matrix and ``b > 0``
    wherever the prior is), the clamp only guards against round-off; ``exp`` of a log-depth
    solution is positive by construction.
    """
    if variable == "depth":
        return x
    if variable == "log":
        return torch.exp(x)
    return 1.0 / x.clamp_min(1e-6)


def std_in_metres(std: torch.Tensor, depth: torch.Tensor, variable: Variable) -> torch.Tensor:
    """A std of the unknown as a std of depth, to first order (``std_z = z^2 std_(1/z)``,
    ``std_z = z std_(log z)``; no gradient to ``depth``)."""
    if variable == "depth":
        return std
    return std * depth.detach() ** (1 if variable == "log" else 2)


def colour_affinity(colour_i: torch.Tensor, colour_j: torch.Tensor, sigma_d: torch.Tensor) -> torch.Tensor:
    """``e_ij = exp(-||c_i - c_j||^2 / sigma_d^2)``.

    Args:
        colour_i, colour_j: (..., 3) colours of the two ends of each edge (RGB in [0, 1]).
        sigma_d: scalar tensor > 0, in colour units.

    Returns:
        (...) affinities in (0, 1].
    """
    return gaussian_affinity(((colour_i - colour_j) ** 2).sum(-1), sigma_d)


def normal_affinity(normal_i: torch.Tensor, normal_j: torch.Tensor, sigma_n: torch.Tensor) -> torch.Tensor:
    """``nr_ij = exp((cos_ij - 1) / sigma_n^2)``: the cosine similarity mapped to (0, 1].

    A raw cosine can be negative and would break positive definiteness (docs/design.md
    section 3); this mapping is 1 for parallel normals and ``exp(-2 / sigma_n^2)`` for
    opposite ones.

    Args:
        normal_i, normal_j: (..., 3) unit normals; a zero vector (unknown normal) gives
            cos = 0, i.e. the affinity of perpendicular normals.
        sigma_n: scalar tensor > 0.
    """
    return cosine_affinity((normal_i * normal_j).sum(-1), sigma_n)


def distance_affinity(point_i: torch.Tensor, point_j: torch.Tensor, sigma_p: torch.Tensor) -> torch.Tensor:
    """``dp_ij = exp(-||p_i - p_j||^2 / sigma_p^2)`` for (..., 3) camera-frame points in metres."""
    return gaussian_affinity(((point_i - point_j) ** 2).sum(-1), sigma_p)


def gaussian_affinity(squared_distance: torch.Tensor, sigma: torch.Tensor) -> torch.Tensor:
    """``exp(-d^2 / sigma^2)`` of squared distances (the colour and 3D-distance affinities)."""
    return torch.exp(-squared_distance / sigma ** 2)


def cosine_affinity(cos: torch.Tensor, sigma_n: torch.Tensor) -> torch.Tensor:
    """``exp((cos - 1) / sigma_n^2)`` of cosines, clamped to [-1, 1] (the normal affinity)."""
    return torch.exp((cos.clamp(-1.0, 1.0) - 1.0) / sigma_n ** 2)


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
    by nothing: ``alpha``..``delta`` and ``eps`` are applied by :func:`graph_system`.
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


def unary_system(*terms: tuple[torch.Tensor, torch.Tensor]) -> tuple[torch.Tensor, torch.Tensor]:
    """``(d, b)`` of ``sum_k u_k (x - t_k)^2`` from ``(u_k, t_k)`` pairs: ``d = sum u_k``, ``b = sum u_k t_k``.

    The diagonal and right-hand side that unary terms (weight ``u_k >= 0`` towards target
    ``t_k``) contribute to ``A x = b``; weights and targets broadcast (a scalar weight is fine).
    """
    (u, t), rest = terms[0], terms[1:]
    d, b = u, u * t
    for u, t in rest:
        d = d + u
        b = b + u * t
    return d, b


def graph_system(t: EnergyTerms, ptr: torch.Tensor | None = None) -> System:
    """The system of ``t`` on its graph batch (node offsets ``ptr``; None: one graph)."""
    d, b = unary_system((t.alpha * t.w, t.z), (t.eps, t.x_prior))
    return System.graph(d, b, t.edge_index, t.edge_weight(), ptr)


def grid_pairs(values: torch.Tensor, reduce: Literal["squared_distance", "dot"]
               ) -> tuple[torch.Tensor, torch.Tensor]:
    """Between 4-neighbours of a (B, C, H, W) grid, ``sum_c (a_c - b_c)^2`` or ``sum_c a_c b_c``:
    ``(horizontal (B, H, W-1), vertical (B, H-1, W))``.

    Channel by channel on contiguous planes; :func:`gaussian_affinity` or
    :func:`cosine_affinity` of the result is the grid form of the affinities above. The planes are
    taken apart once (``unbind``) and then shifted: in backward that is one stack and a shift per
    plane, where selecting the channel of each shifted copy cost a zero-filled copy of all channels per
    channel (2.4x the time of forward and backward at 320x896).
    """
    planes = values.unbind(1)

    def pair(dim: int) -> torch.Tensor:
        total = None
        for p in planes:
            n = p.shape[dim]
            a, b = p.narrow(dim, 0, n - 1), p.narrow(dim, 1, n - 1)
            term = (a - b) ** 2 if reduce == "squared_distance" else a * b
            total = term if total is None else total + term
        return total

    return pair(2), pair(1)


def grid_energy_terms(z, w, prior, colour, normal, distance, alpha, beta, gamma, delta, eps) -> EnergyTerms:
    """Pixel-grid terms in edge-list form (:func:`crfdepth.linalg.grid_edge_index` order per image).

    ``z, w, prior``: (B, H, W); ``colour, normal, distance``: ``(horizontal, vertical)``
    pairs of :func:`grid_pairs` or None; ``gamma`` / ``delta`` None for potentials that are off.
    """
    bsz, h, w_ = z.shape
    n = h * w_
    ei = grid_edge_index(h, w_, device=z.device)
    edge_index = ei if bsz == 1 else torch.cat([ei + k * n for k in range(bsz)], 1)

    def flat(pair):
        return None if pair is None else torch.cat([pair[0].reshape(bsz, -1), pair[1].reshape(bsz, -1)], 1).reshape(-1)

    zero = torch.zeros_like(alpha)
    return EnergyTerms(z.reshape(-1), w.reshape(-1), prior.reshape(-1), edge_index, flat(colour), flat(normal),
                       flat(distance), alpha, beta, gamma if gamma is not None else zero,
                       delta if delta is not None else zero, eps)


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


@dataclass(frozen=True)
class PotentialWeights:
    """The weights of the potentials (``gamma`` / ``delta`` None for a potential that is off)."""

    alpha: torch.Tensor
    beta: torch.Tensor
    gamma: torch.Tensor | None
    delta: torch.Tensor | None
    confidence: torch.Tensor
    sigma_d: torch.Tensor
    sigma_n: torch.Tensor
    sigma_p: torch.Tensor


Pair = tuple[torch.Tensor, torch.Tensor]  # (horizontal (B, H, W-1), vertical (B, H-1, W)) of grid_pairs


@dataclass(frozen=True)
class GridTerms:
    """The potentials of one pixel-grid round: maps (B, H, W) and pairwise terms as :data:`Pair`."""

    alpha: torch.Tensor
    beta: torch.Tensor
    gamma: torch.Tensor | None
    delta: torch.Tensor | None
    eps: torch.Tensor
    z: torch.Tensor  # LiDAR in the unknown
    w: torch.Tensor  # data weight (confidence x gate x head factor)
    prior: torch.Tensor  # x0 in the unknown
    colour: Pair
    normal: Pair | None = None
    distance: Pair | None = None
    edge_factor: Pair | None = None  # the head's factor on the edge to the right / downwards

    def energy_terms(self) -> EnergyTerms:
        """The same terms in edge-list form (:func:`grid_energy_terms`)."""
        return grid_energy_terms(self.z, self.w, self.prior, self.colour, self.normal, self.distance, self.alpha,
                                 self.beta, self.gamma, self.delta, self.eps)


def grid_potentials(image: torch.Tensor, sparse: torch.Tensor, K: torch.Tensor, prior: torch.Tensor,
                    eps: torch.Tensor, geometry: torch.Tensor | None, weights: PotentialWeights, *,
                    variable: Variable = "depth", gate: torch.Tensor | None = None,
                    factors: tuple[torch.Tensor, torch.Tensor] | None = None,
                    previous: GridTerms | None = None) -> GridTerms:
    """The potentials of one pixel-grid round (pixel mode and the refinement; docs/design.md sections 3 and 6).

    Args:
        image: (B, 3, H, W) RGB in [0, 1]; sparse: (B, 1, H, W) LiDAR depth, metres, 0 = none;
        K: (B, 3, 3); prior: (B, 1, H, W) the prior depth ``x0``; eps: its weight.
        geometry: (B, 1, H, W) depth from which normals and 3D points are taken (None in a
            first pass: then only the colour term is on).
        weights: the potentials' weights (``gamma`` / ``delta`` None when that potential is off).
        variable: the unknown, ``"depth"`` or ``"inverse"`` (:func:`to_unknown`); ``z`` and
            ``prior`` of the result are in it, ``geometry`` stays depth.
        gate: (B, 1, H, W) per-pixel factor on the data weight (the occlusion gate of
            :mod:`crfdepth.potentials.occlusion`) or None.
        factors: ``(data (B, 1, H, W), edge (B, 2, H, W))`` of :class:`crfdepth.potentials.head.PotentialHead`
            or None: the data weight is multiplied by ``data``, the pairwise weights of the
            edge to the right / downwards of a pixel by ``edge[:, 0]`` / ``edge[:, 1]``.
        previous: an earlier round's terms with the same arguments but ``geometry``: its data, prior and
            colour terms are the same tensors, so they are taken, and only the normal and 3D-distance
            terms are computed (the same gradients: the graph holds those tensors once).

    Returns:
        The :class:`GridTerms`, for :func:`grid_system`.
    """
    if previous is not None:
        fused = fused_affinities(image, K, geometry, weights, colour=previous.colour)
        _, normal, distance = _affinities(image, K, geometry, weights, previous.colour) if fused is None else fused
        return replace(previous, alpha=weights.alpha, beta=weights.beta, gamma=weights.gamma, delta=weights.delta,
                       eps=eps, normal=normal, distance=distance)
    s = sparse[:, 0]
    w = data_confidence((s > 0).to(s.dtype), weights.confidence)
    if gate is not None:
        w = w * gate[:, 0]
    if factors is not None:
        w = w * factors[0][:, 0]
    fused = fused_affinities(image, K, geometry, weights)
    if fused is not None:
        colour, normal, distance = fused
    else:
        colour, normal, distance = _affinities(image, K, geometry, weights)
    return GridTerms(alpha=weights.alpha, beta=weights.beta, gamma=weights.gamma, delta=weights.delta, eps=eps,
                     z=to_unknown(s, variable), prior=to_unknown(prior[:, 0], variable), w=w,
                     colour=colour, normal=normal, distance=distance,
                     edge_factor=None if factors is None else (factors[1][:, 0, :, :-1], factors[1][:, 1, :-1, :]))


def _affinities(image: torch.Tensor, K: torch.Tensor, geometry: torch.Tensor | None, weights: PotentialWeights,
                colour: Pair | None = None) -> tuple[Pair, Pair | None, Pair | None]:
    """The colour (unless given), normal and 3D-distance :data:`Pair` of :func:`grid_potentials` (None: off), in
    torch."""
    if colour is None:
        colour = tuple(gaussian_affinity(q, weights.sigma_d) for q in grid_pairs(image, "squared_distance"))
    normal = distance = None
    if geometry is not None:
        if weights.gamma is not None:
            n, _ = dense_normals(geometry, K)  # differentiable: gradients flow through the geometry
            normal = tuple(cosine_affinity(c, weights.sigma_n) for c in grid_pairs(n, "dot"))
        if weights.delta is not None:
            points = camera_points(geometry[:, 0], K)
            distance = tuple(gaussian_affinity(q, weights.sigma_p) for q in grid_pairs(points, "squared_distance"))
    return colour, normal, distance


def rhs_in(t: GridTerms, variable: Variable) -> torch.Tensor:
    """The right-hand side of ``grid_system(t)`` for terms in the depth unknown, with ``variable`` as the unknown
    instead: the diagonal and the edge weights do not depend on the unknown, only the targets of the unary
    terms do (the coarse solve's near blocks, docs/design.md section 17)."""
    _, b = unary_system((t.alpha * t.w, to_unknown(t.z, variable)), (t.eps, to_unknown(t.prior, variable)))
    return b


def grid_system(t: GridTerms) -> System:
    """The pixel-grid system of the potentials of :func:`grid_potentials` (one compiled pass per map where no
    gradient is needed, :func:`crfdepth.potentials.compiled.fused_system`; the same numbers)."""
    fused = fused_system(t)
    if fused is not None:
        return System.grid(*fused)
    wh = t.beta * t.colour[0]
    wv = t.beta * t.colour[1]
    for scale, term in ((t.gamma, t.normal), (t.delta, t.distance)):
        if term is not None:
            wh = wh + scale * term[0]
            wv = wv + scale * term[1]
    if t.edge_factor is not None:
        wh = wh * t.edge_factor[0]
        wv = wv * t.edge_factor[1]
    d, b = unary_system((t.alpha * t.w, t.z), (t.eps, t.prior))
    return System.grid(d, b, wh, wv)
