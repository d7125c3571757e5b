"""The CRF as a refinement layer on top of any depth network (docs/design.md sections 3-5).

A network predicts a dense depth ``y``, a per-pixel confidence ``c >= 0`` and guidance
features ``f``; the layer returns the minimiser of the Gaussian CRF energy

    E(x) = sum_i c_i (x_i - y_i)^2                       the network's depth, weighted
         + lambda sum_{i: z_i > 0} (x_i - z_i)^2        the sparse LiDAR (optional)
         + sum_{(i,j)} w_ij (x_i - x_j)^2               4-connected pixel edges
         + eps sum_i (x_i - y_i)^2                      small prior, keeps A positive definite

with ``w_ij = s exp(-||P f_i - P f_j||^2)``, ``P`` a learnable linear projection of the
features (a 1x1 convolution) and ``s > 0`` an edge scale. The minimiser solves the sparse
SPD system ``A x = b`` of docs/design.md section 3 with

    A = diag(c + eps + lambda m) + L(w),    b = (c + eps) y + lambda m z,    m = [z > 0],

by :func:`crfdepth.linalg.solve_grid_laplacian` (Jacobi-preconditioned CG, warm start
from ``y``) and is differentiated by one adjoint solve (docs/design.md section 4), so gradients
reach ``y``, ``c``, ``f``, ``z``, ``P``, ``s`` and ``lambda`` and memory does not grow
with the iteration count. The predictive standard deviation is
``sigma * sqrt(diag(A^-1))`` (docs/design.md section 5, :func:`grid_posterior_variance`), with
a learnable scale ``sigma``; the variance itself carries no gradient, only ``sigma`` does.

Superpixel mode (``labels`` given): the same energy restricted to depth maps that are
constant on each segment (a Galerkin restriction). Node ``s`` gets
``d_s = sum_{i in s} (c_i + eps + lambda m_i)`` and ``b_s = sum_{i in s} ((c_i + eps) y_i
+ lambda m_i z_i)``; two adjacent segments get the sum of the pixel-edge weights ``w_ij``
across their common boundary. The solution (by :func:`crfdepth.linalg.solve_laplacian`)
minimises the pixel energy over piecewise-constant maps exactly, and is painted back to
pixels. All sums are ``index_add`` and stay differentiable.

:func:`crf_refine` is the pure function, :class:`CRFRefine` the ``nn.Module`` owning
``P``, ``s``, ``lambda`` and ``sigma``.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

import torch
from torch import nn

from crfdepth.checks import check_flag, check_map, check_scalar_tensor, describe
from crfdepth.config import check_std_samples
from crfdepth.errors import InputError
from crfdepth.layer_inputs import check_anchored, check_labels, check_not_empty, check_projection
from crfdepth.linalg import SolveInfo, System, solve_system, solver_settings
from crfdepth.potentials.energy import unary_system
from crfdepth.precision import full_dtype, full_precision
from crfdepth.superpixels.edges import boundary_pairs
from crfdepth.superpixels.segments import batch_segments, slic_batch
from crfdepth.uncertainty.posterior import posterior_std

__all__ = ["CRFRefine", "RefineOutput", "crf_refine"]


@dataclass
class RefineOutput:
    """Result of :func:`crf_refine` / :class:`CRFRefine`.

    Attributes:
        depth: (B, 1, H, W) refined depth in metres, dtype (float32 for float16 / bfloat16)
            and device of the input depth.
        std: (B, 1, H, W) predictive standard deviation in metres, or None unless asked.
        info: :class:`crfdepth.linalg.SolveInfo` of the solve (one entry per image).
    """

    depth: torch.Tensor
    std: torch.Tensor | None
    info: SolveInfo


# ----------------------------------------------------------------------------------------
# the pure function
# ----------------------------------------------------------------------------------------

def crf_edge_weights(features: torch.Tensor, projection: torch.Tensor,
                     edge_scale: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Pixel-grid edge weights ``s exp(-||P f_i - P f_j||^2)`` (no input checks).

    Args:
        features: (B, C, H, W); projection: (E, C); edge_scale: 0-d tensor > 0.

    Returns:
        ``weight_h`` (B, H, W-1) between (r, c) and (r, c+1), ``weight_v`` (B, H-1, W)
        between (r, c) and (r+1, c).
    """
    emb = torch.einsum("ec,bchw->behw", projection, features)
    dh = (emb[..., :, 1:] - emb[..., :, :-1]).pow(2).sum(1)
    dv = (emb[..., 1:, :] - emb[..., :-1, :]).pow(2).sum(1)
    return edge_scale * torch.exp(-dh), edge_scale * torch.exp(-dv)


@full_precision
def crf_refine(
    depth: torch.Tensor,
    confidence: torch.Tensor,
    features: torch.Tensor,
    projection_weight: torch.Tensor,
    *,
    sparse: torch.Tensor | None = None,
    sparse_weight: float | torch.Tensor | None = None,
    edge_scale: float | torch.Tensor = 1.0,
    prior_weight: float = 1e-3,
    labels: torch.Tensor | None = None,
    return_std: bool = False,
    std_scale: float | torch.Tensor = 1.0,
    std_samples: int = 16,
    seed: int | None = 0,
    rtol: float = 1e-5,
    max_iter: int | None = None,
    on_nonconvergence: str = "warn",
) -> RefineOutput:
    """Refine a network's dense depth with a Gaussian CRF (energy in the module docstring).

    Runs with ``torch.autocast`` off, float16 / bfloat16 tensors taken as float32
    (:mod:`crfdepth.precision`): inside a network trained under autocast the edge weights,
    the system and its solve stay in float32 or better, and the output is float32.

    Nothing is modified in place; the result is differentiable in ``depth``,
    ``confidence``, ``features``, ``sparse`` (its values at the LiDAR pixels; which pixels
    hold LiDAR is not differentiable), ``projection_weight``, ``edge_scale``,
    ``sparse_weight`` and (through ``std``) ``std_scale``. Multiplying ``confidence``,
    ``prior_weight``, ``sparse_weight`` and ``edge_scale`` by one constant leaves the depth
    unchanged (only their ratios matter) and divides the variance by it.

    Cost: one CG solve forward and one backward on the ``B x H x W`` grid; at 1216x352 with
    a warm start from ``depth`` about 0.4 s each on one CPU core (24 iterations in that
    measurement; fewer confident pixels need more). ``return_std`` adds ``std_samples``
    solves (about 7 s for 16 samples at 1216x352 on one core).

    Args:
        depth: (B, 1, H, W) the network's dense depth in metres (any finite value; it is
            the data term's target and the CG warm start, not a "missing" marker).
        confidence: (B, 1, H, W) data weight ``c_i >= 0`` per pixel, unit-free (relative
            to the edge weights, which are at most ``edge_scale``); 0 = trust the
            neighbours only.
        features: (B, C, H, W) guidance features, finite; edge weights are computed from
            their projection.
        projection_weight: (E, C) or (E, C, 1, 1) the projection ``P`` (e.g. the weight of
            an ``nn.Conv2d(C, E, 1, bias=False)``).
        sparse: optional (B, 1, H, W) LiDAR z-depth in metres, 0 = no return.
        sparse_weight: ``lambda >= 0``, weight of each LiDAR pixel; required with ``sparse``.
        edge_scale: ``s > 0``, the largest edge weight.
        prior_weight: ``eps > 0``, added to the confidence everywhere so that ``A`` is
            positive definite; small against ``c`` and ``s``, but in a frame with no
            confidence > 0 and no LiDAR at least machine epsilon times ``s``.
        labels: optional (B, H, W) int64 segment index per pixel (e.g. SLIC superpixels of
            each frame, :func:`crfdepth.superpixels.segments.slic_segments`): solve on the segment graph
            and paint back (piecewise-constant output). Labels need not be consecutive.
        return_std: also return ``std_scale * sqrt(diag(A^-1))`` (extra solves, no
            gradient except to ``std_scale``).
        std_scale: ``sigma > 0``, metres per unit of ``sqrt(diag(A^-1))``.
        std_samples: samples of the variance estimate
            (:func:`crfdepth.uncertainty.posterior.grid_posterior_variance`; superpixel graphs of up
            to 1,000 segments are exact).
        seed: seed of the variance estimate.
        rtol: tolerance of the CG solve (:func:`crfdepth.linalg.solve_grid_laplacian`).
        max_iter: iteration cap of the CG solve.
        on_nonconvergence: "warn", "raise" or "ignore" a CG solve that does not converge.

    Returns:
        :class:`RefineOutput` with ``depth`` (B, 1, H, W) metres, ``std`` or None, ``info``.

    Raises:
        InputError: before any solve, for a non-tensor or wrongly shaped argument,
            mismatched batch, size, dtype or device, NaN/inf in any tensor, negative
            ``confidence`` or ``sparse``, ``sparse`` without ``sparse_weight``,
            non-positive scales, an empty batch (B, H or W of 0), or a ``prior_weight``
            below machine precision times ``edge_scale`` in a frame with no confidence
            > 0 and no LiDAR pixel (numerically singular); the message names the argument.
        ConvergenceError: with ``on_nonconvergence="raise"``, a solve that did not converge.
            A solve whose result is NaN/inf (a numerically singular system) is never
            reported converged and warns even under "ignore", naming ``prior_weight``.

    Second-order gradients (``create_graph=True`` and a gradient of the gradient) through
    the solve are not supported and raise a RuntimeError naming ``create_graph``; first-order
    gradients are (:mod:`crfdepth.linalg.adjoint`).
    """
    check_map("depth", depth, None, 1)
    check_not_empty(depth)
    if check_flag("return_std", return_std):
        check_std_samples(std_samples)
    check_map("confidence", confidence, depth, 1, nonneg=True)
    check_map("features", features, depth, None)
    projection = check_projection(projection_weight, features.shape[1], depth, features)
    scale = check_scalar_tensor("edge_scale", edge_scale, depth, positive=True)
    eps = check_scalar_tensor("prior_weight", prior_weight, depth, positive=True)
    if sparse is not None:
        check_map("sparse", sparse, depth, 1, nonneg=True)
        if sparse_weight is None:
            raise InputError("sparse_weight: expected a number >= 0 when sparse is given, got None")
        lam = check_scalar_tensor("sparse_weight", sparse_weight, depth, positive=False)
    sigma = check_scalar_tensor("std_scale", std_scale, depth, positive=True) if return_std else None
    if labels is not None:
        labels = check_labels(labels, depth)
    settings = solver_settings(rtol=rtol, max_iter=max_iter, on_nonconvergence=on_nonconvergence)
    check_anchored(eps, scale, confidence, sparse, lam if sparse is not None else None)
    settings = dataclasses.replace(settings, singular_hint=(
        f"raise prior_weight (now {float(eps.detach()):g}, default 1e-3) against edge_scale "
        f"({float(scale.detach()):g}) where confidence is 0 and there is no LiDAR, or give those pixels some "
        f"confidence"))

    y = depth[:, 0]
    unaries = [(confidence[:, 0] + eps, y)]
    if sparse is not None:
        z = sparse[:, 0]
        unaries.append((lam * (z.detach() > 0).to(depth.dtype), z))
    d, b = unary_system(*unaries)
    weight_h, weight_v = crf_edge_weights(features, projection, scale)
    std_settings = dict(samples=std_samples, seed=seed, rtol=max(rtol, 1e-4))

    if labels is None:
        system = System.grid(d, b, weight_h, weight_v)
        x, info = solve_system(system, y, settings)
        std = posterior_std(system, sigma, **std_settings)[:, None] if return_std else None
        return RefineOutput(x[:, None], std, info)

    # Superpixel mode: the energy restricted to piecewise-constant maps (module docstring).
    node, ptr = batch_segments(labels)
    n = int(ptr[-1])
    flat = node.reshape(-1)
    d_s = torch.zeros(n, dtype=y.dtype, device=y.device).index_add(0, flat, d.reshape(-1))
    b_s = torch.zeros(n, dtype=y.dtype, device=y.device).index_add(0, flat, b.reshape(-1))
    area = torch.bincount(flat, minlength=n).to(y.dtype)
    x0 = torch.zeros(n, dtype=y.dtype, device=y.device).index_add(0, flat, y.detach().reshape(-1)) / area
    # Pixel edges that cross a segment boundary, summed per pair of segments.
    edge_index, crossing, pair_of_edge = boundary_pairs(node, n)
    pixel_weights = torch.cat([weight_h.reshape(-1), weight_v.reshape(-1)])[crossing]
    edge_weight = torch.zeros(edge_index.shape[1], dtype=y.dtype, device=y.device).index_add(
        0, pair_of_edge, pixel_weights)
    system = System.graph(d_s, b_s, edge_index, edge_weight, ptr)
    x, info = solve_system(system, x0, settings)
    std = None
    if return_std:
        std = posterior_std(system, sigma, **std_settings)[node][:, None]
    return RefineOutput(x[node][:, None], std, info)


# ----------------------------------------------------------------------------------------
# the module
# ----------------------------------------------------------------------------------------

class CRFRefine(nn.Module):
    """Learnable CRF refinement layer; ``forward`` calls :func:`crf_refine`.

    Parameters (all learnable): ``projection`` the 1x1 convolution ``P`` (C -> embed_dim,
    no bias), ``log_edge_scale`` (``s = exp``), ``log_sparse_weight`` (``lambda = exp``)
    and ``log_std_scale`` (``sigma = exp``). ``lambda`` gets a gradient only when
    ``sparse`` is passed, ``sigma`` only through ``std``.

    Args:
        in_channels: C, channels of the guidance features.
        embed_dim: E, dimension of the projected features.
        edge_scale: initial ``s`` > 0.
        sparse_weight: initial ``lambda`` > 0.
        prior_weight: fixed ``eps`` > 0 (see :func:`crf_refine`).
        std_scale: initial ``sigma`` > 0.
        superpixels: None (pixel grid, default) or the number of SLIC segments per frame;
            then ``forward`` needs ``image`` (B, 3, H, W) RGB in [0, 1] (segmented with
            :func:`crfdepth.superpixels.segments.slic_segments`, no gradient) or precomputed ``labels``,
            and the output is piecewise constant on the segments.
        init_scale: standard deviation of the initial projection weights (small, so that
            edges start close to ``s``: a smooth prior that the training sharpens).
        std_samples: as in :func:`crf_refine`.
        rtol: as in :func:`crf_refine`.
        max_iter: as in :func:`crf_refine`.
    """

    def __init__(
        self,
        in_channels: int,
        embed_dim: int = 8,
        *,
        edge_scale: float = 1.0,
        sparse_weight: float = 10.0,
        prior_weight: float = 1e-3,
        std_scale: float = 1.0,
        superpixels: int | None = None,
        init_scale: float = 0.1,
        std_samples: int = 16,
        rtol: float = 1e-5,
        max_iter: int | None = None,
    ) -> None:
        super().__init__()
        for name, value in (("in_channels", in_channels), ("embed_dim", embed_dim)):
            if not isinstance(value, int) or isinstance(value, bool) or value < 1:
                raise InputError(f"{name}: expected a positive int, got {value!r}")
        for name, value in (("edge_scale", edge_scale), ("sparse_weight", sparse_weight),
                            ("prior_weight", prior_weight), ("std_scale", std_scale),
                            ("init_scale", init_scale)):
            if not isinstance(value, (int, float)) or not (math.isfinite(value) and value > 0):
                raise InputError(f"{name}: expected a finite number > 0, got {value!r}")
        if superpixels is not None and (not isinstance(superpixels, int) or superpixels < 1):
            raise InputError(f"superpixels: expected None or a positive int, got {superpixels!r}")
        self.projection = nn.Conv2d(in_channels, embed_dim, 1, bias=False)
        nn.init.normal_(self.projection.weight, std=init_scale)
        self.log_edge_scale = nn.Parameter(torch.tensor(math.log(edge_scale)))
        self.log_sparse_weight = nn.Parameter(torch.tensor(math.log(sparse_weight)))
        self.log_std_scale = nn.Parameter(torch.tensor(math.log(std_scale)))
        self.prior_weight = float(prior_weight)
        self.superpixels = superpixels
        self.std_samples = check_std_samples(std_samples)
        self.rtol = rtol
        self.max_iter = max_iter

    @property
    def edge_scale(self) -> torch.Tensor:
        return self.log_edge_scale.exp()

    @property
    def sparse_weight(self) -> torch.Tensor:
        return self.log_sparse_weight.exp()

    @property
    def std_scale(self) -> torch.Tensor:
        return self.log_std_scale.exp()

    def forward(self, depth: torch.Tensor, confidence: torch.Tensor, features: torch.Tensor,
                sparse: torch.Tensor | None = None, *, image: torch.Tensor | None = None,
                labels: torch.Tensor | None = None, return_std: bool = False) -> RefineOutput:
        """Refine ``depth``; arguments as in :func:`crf_refine`.

        ``image`` (B, 3, H, W) RGB in [0, 1] is used only with ``superpixels`` set and no
        ``labels``. Parameters are cast to ``depth``'s dtype (the module may stay float32
        while the inputs are float64), never below float32: under ``torch.autocast`` or with
        float16 / bfloat16 inputs the layer computes in float32 (:func:`crf_refine`).
        """
        channels = self.projection.in_channels
        if isinstance(features, torch.Tensor) and features.dim() == 4 and features.shape[1] != channels:
            raise InputError(f"features: expected {channels} channels (CRFRefine(in_channels={channels})), got "
                             f"{features.shape[1]} ({describe(features)}); build the layer with "
                             f"in_channels={features.shape[1]} or give it {channels}-channel features")
        if labels is None and self.superpixels is not None:
            check_map("depth", depth, None, 1)
            check_not_empty(depth)
            labels = self._segment(image, depth)
        dtype = full_dtype(depth.dtype) if isinstance(depth, torch.Tensor) and depth.is_floating_point() else None
        cast = (lambda t: t.to(dtype)) if dtype is not None else (lambda t: t)
        return crf_refine(
            depth, confidence, features, cast(self.projection.weight),
            sparse=sparse, sparse_weight=cast(self.sparse_weight) if sparse is not None else None,
            edge_scale=cast(self.edge_scale), prior_weight=self.prior_weight, labels=labels,
            return_std=return_std, std_scale=cast(self.std_scale), std_samples=self.std_samples,
            rtol=self.rtol, max_iter=self.max_iter,
        )

    def _segment(self, image, depth) -> torch.Tensor:
        if not isinstance(depth, torch.Tensor) or depth.dim() != 4:
            raise InputError(f"depth: expected a (B, 1, H, W) tensor, got {describe(depth)}")
        b, _, h, w = depth.shape
        if not isinstance(image, torch.Tensor) or tuple(image.shape) != (b, 3, h, w):
            raise InputError(f"image: expected a ({b}, 3, {h}, {w}) RGB tensor in [0, 1] (superpixels="
                             f"{self.superpixels} needs it, or pass labels), got {describe(image)}")
        return slic_batch(image, self.superpixels).to(depth.device)

    def extra_repr(self) -> str:
        scale, lam = float(self.edge_scale.detach()), float(self.sparse_weight.detach())
        return (f"edge_scale={scale:.3g}, sparse_weight={lam:.3g}, prior_weight={self.prior_weight:g}, "
                f"superpixels={self.superpixels}")
