"""The pixel-grid CRF (``mode="pixel"`` and the superpixel mode's refinement; docs/design.md
sections 3 and 6), and the stages both pipelines share: the LiDAR evidence and the predictive std.

Every stage takes the model (a :class:`crfdepth.model.CRFDepth`, typed as the ``nn.Module`` it is: inference
sits below the model and imports nothing of it) and reads its configuration, ``model.settings`` (:class:`crfdepth.config.CRFConfig`),
its current weights (``model.sigma_d``, ``model.scales()`` ...) and ``model.solve_settings``."""

from __future__ import annotations

from dataclasses import replace

import torch

from crfdepth.fill.nearest import trusted_nearest_fill
from crfdepth.inference.coarse import Block, block_mean, block_shape, coarse_frames, paint
from crfdepth.linalg import SolveInfo, System, solve_system
from crfdepth.output import CRFOutput, Stages
from crfdepth.potentials.data_term import lidar_evidence, lidar_gate, prior_fill
from crfdepth.potentials.energy import (
    GridTerms,
    grid_potentials,
    grid_system,
    rhs_in,
    std_in_metres,
    to_depth,
    to_unknown,
)
from crfdepth.potentials.robust import reweight
from crfdepth.uncertainty.count import pixel_count_uncertainty
from crfdepth.uncertainty.posterior import posterior_std, system_conditional_variance
from crfdepth.uncertainty.predictive import grid_std_compiled, std_features


def evidence(model: torch.nn.Module, sparse: torch.Tensor, *, with_distance: bool = False, fill: bool = True
             ) -> tuple:
    """``(gate, kept, fill)`` of :func:`crfdepth.potentials.data_term.lidar_evidence` (docs/design.md section 3b);
    ``with_distance``: and the distance to the nearest kept return where the fill found it (else None).
    ``fill`` False: no fill (None, and no distance): the caller fills later if it needs to
    (:func:`crfdepth.potentials.data_term.prior_fill`)."""
    settings = model.settings
    gate = (model.gate_threshold, model.gate_softness) if settings.gate.enabled else None
    if not fill:
        gate, kept = lidar_gate(sparse, gate, settings.gate.window)
        return (gate, kept, None, None) if with_distance else (gate, kept, None)
    return lidar_evidence(sparse, gate, settings.gate.window, settings.structure.prior, with_distance=with_distance)


def predictive_std(model: torch.nn.Module, depth, sparse, kept, gate, variance) -> tuple[torch.Tensor, torch.Tensor]:
    """The predictive std (:mod:`crfdepth.uncertainty.predictive`) and its signals, from the conditional
    variance of the last solve in the unknown's units."""
    variable = model.settings.structure.variable
    variance = (std_in_metres(variance.sqrt(), depth, variable) / depth.detach()) ** 2  # in (log z)^2
    features = std_features(depth, sparse, kept, gate, variance)
    return model.std_head(features), features


def grid_std(model: torch.nn.Module, depth, sparse, kept, gate, system, distance=None
             ) -> tuple[torch.Tensor, torch.Tensor]:
    """:func:`predictive_std` of a pixel-grid solve's ``system``: one compiled pass on the CPU where the kernels
    are built (:func:`crfdepth.uncertainty.predictive.grid_std_compiled`), the same numbers; ``distance``
    from the fill if it found it."""
    fused = grid_std_compiled(model.std_head, depth, sparse, kept, gate, distance, system.diagonal, *system.weights,
                              model.settings.structure.variable)
    if fused is not None:
        return fused
    return predictive_std(model, depth, sparse, kept, gate, system_conditional_variance(system)[:, None])


def pixel_solve(model: torch.nn.Module, image, sparse, K, prior, eps, infos: list[SolveInfo], geometry=None, gate=None,
                kept=None, variable=None) -> tuple[torch.Tensor, GridTerms, System]:
    """Pixel-level solve(s) of the grid CRF; without ``geometry`` a first pass provides it. ``variable``: the
    unknown, if not the model's.

    Returns the (B, 1, H, W) depth, the last round's potentials and the system they make (``grid_system``).
    """
    structure, on, irls = model.settings.structure, model.settings.potentials.on, model.settings.potentials.irls
    rounds, v, solver = 1, variable or structure.variable, model.solve_settings
    kept = sparse if kept is None else kept
    extra = dict(variable=v, gate=gate, factors=None if model.head is None else model.head(image, kept, prior))
    t = None  # a round's terms: the next round computes only those that depend on the geometry
    if geometry is None:
        t = grid_potentials(image, sparse, K, prior, eps, None, model.potential_weights(), **extra)
        system = grid_system(t)
        x, info = solve_system(system, t.prior, solver)
        infos.append(info)
        if "normal" not in on and "distance" not in on:
            return to_depth(x, v)[:, None], t, system
        geometry, rounds = to_depth(x, v)[:, None], structure.rounds
    for _ in range(rounds):
        t = grid_potentials(image, sparse, K, prior, eps, geometry, model.potential_weights(), **extra, previous=t)
        system = grid_system(t)
        x, info = solve_system(system, to_unknown(geometry[:, 0], v), solver)
        infos.append(info)
        geometry = to_depth(x, v)[:, None]
    if irls:
        geometry, t = reweight(t, x, sparse, irls, model.irls_scale, v, solver, infos)
        system = grid_system(t)
    return geometry, t, system


def coarse_solve(model: torch.nn.Module, image, kept, K, block: Block, infos: list[SolveInfo]) -> torch.Tensor:
    """The depth of the pixel-grid CRF solved on ``block`` = (height, width) blocks (:mod:`crfdepth.inference.coarse`,
    docs/design.md section 17), painted back to the full resolution: the prior and first geometry of the
    full-resolution solve, as the superpixel mode's painted solution is its refinement's.

    With ``structure.near_inverse = a`` the coarse grid is solved a second time with inverse depth as the unknown
    (the same system, another right-hand side: :func:`~crfdepth.potentials.energy.rhs_in`), and a block takes
    that solution where the first is nearer than ``a`` metres, the first beyond ``3 a``, and a linear blend
    between: a plane seen in perspective is affine in inverse depth, which the membrane interpolates exactly,
    while across a near and a far return the depth unknown's mean in metres is the better guess (section 17).

    With ``structure.coarse_shifts = 2`` a second grid, starting half a block up and left of the frame, is solved
    the same way (its normals from the first grid's depth: one pass) and the two painted depths are averaged:
    the answer no longer depends on where the block grid happens to fall, and for a convex loss the average of
    two answers is no worse than their mean loss (cycle spinning)."""
    structure, size = model.settings.structure, tuple(kept.shape[2:])
    first, *shifted = coarse_frames(image, kept, K, block, structure.variable, structure.coarse_shifts)
    depth = _painted(model, *first, block, size, infos)
    if shifted:  # the second grid: its normals and 3D distances from the first grid's depth, one pass
        depth = 0.5 * (depth + _painted(model, *shifted[0], block, size, infos, geometry=depth))
    return depth


def _painted(model: torch.nn.Module, frame: tuple, offset: tuple[int, int], block: Block, size: tuple[int, int],
             infos: list[SolveInfo], geometry=None) -> torch.Tensor:
    """The depth of one coarse grid of :func:`coarse_solve`, ``frame`` = :func:`coarse_frame`'s ``(image, sparse,
    K)`` of the grid starting ``offset`` above and left of the frame, painted at the full resolution ``size``.
    ``geometry``: a full-resolution depth whose block means give the normals and 3D distances (one pass);
    None: a first pass finds them."""
    structure = model.settings.structure
    solve = (model, *frame, trusted_nearest_fill(frame[1]), model.scales()[4], infos)
    depth, t, system = pixel_solve(*solve, geometry=None if geometry is None else block_mean(geometry, block, offset))
    if structure.near_inverse > 0:  # the same system in inverse depth: only its right-hand side changes
        x, info = solve_system(replace(system, rhs=rhs_in(t, "inverse")), to_unknown(depth[:, 0], "inverse"),
                               model.solve_settings)
        infos.append(info)
        near = to_depth(x, "inverse")[:, None]
        far = ((depth - structure.near_inverse) / (2.0 * structure.near_inverse)).clamp(0.0, 1.0)
        depth = far * depth + (1.0 - far) * near
    return paint(depth, block, size, offset)


def pixel_forward(model: torch.nn.Module, image: torch.Tensor, sparse: torch.Tensor, K: torch.Tensor,
                  return_std: bool, lines: bool | None = None) -> CRFOutput:
    """:meth:`CRFDepth.forward <crfdepth.model.CRFDepth.forward>` in pixel mode, on checked inputs. ``lines``:
    whether every frame's returns lie on scan lines, if the caller knows (:func:`crfdepth.inference.regime.assign`
    has read it); None: read here when there is a coarse solve."""
    bsz, _, h, w = sparse.shape
    stage = Stages(sparse.device, model.progress)
    with stage("fill"):
        gate, kept, fill, distance = evidence(model, sparse, with_distance=True, fill=False)
        # the caller read the layout of ``sparse``; with a gate the blocks follow the returns it kept
        block = block_shape(model.settings.structure.coarse, kept, lines if kept is sparse else None)
        if block == (1, 1) or return_std:  # the prior, or the distance the std reads; a coarse solve fills itself
            fill, distance = prior_fill(kept, model.settings.structure.prior)
    infos: list[SolveInfo] = []
    prior, eps, geometry = fill, model.scales()[4], None
    if block != (1, 1):
        with stage("coarse"):
            prior = geometry = coarse_solve(model, image, kept, K, block, infos)
            eps = model.refine_prior * model.scales()[5]  # the weight of the superpixel mode's painted prior
    with stage("solve"):  # potentials, normals and solves of all rounds
        depth, t, system = pixel_solve(model, image, sparse, K, prior, eps, infos, geometry=geometry, gate=gate,
                                       kept=kept)
    std = node_std = features = None
    if return_std:
        with stage("uncertainty"):
            settings = model.settings
            if settings.uncertainty.kind == "posterior":
                std = posterior_std(system, model.std_scale, samples=settings.uncertainty.samples)[:, None]
                std = std_in_metres(std, depth, settings.structure.variable)
            else:
                std, features = grid_std(model, depth, sparse, kept, gate, system, distance)
            node_std = std.reshape(-1)
    return CRFOutput(depth, std, pixel_count_uncertainty(sparse), depth.reshape(-1), node_std,
                     torch.arange(bsz + 1, device=sparse.device) * (h * w), None, t.energy_terms, infos,
                     stage.seconds, features)
