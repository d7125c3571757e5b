"""The superpixel-graph CRF (``mode="superpixel"``; docs/design.md sections 2, 3 and 6).

Stages, as :class:`~crfdepth.output.Stages` times them: the LiDAR evidence and fill, SLIC,
the graph and its nodes, normals, the potentials, the solve (then, with the normal or
3D-distance term on, rounds that refit them to the solution and solve again), painting
node depths back to pixels, the optional pixel-level refinement, and the std.

The stages read the model as :mod:`crfdepth.inference.pixel` says (``model.settings`` and the weights).
"""

from __future__ import annotations

import torch

from crfdepth.geometry.node_normals import graph_normals
from crfdepth.inference.nodes import Nodes, gather_nodes, gather_normals
from crfdepth.inference.pixel import evidence, grid_std, pixel_solve, predictive_std
from crfdepth.linalg import SolveInfo, solve_system
from crfdepth.output import CRFOutput, Stages
from crfdepth.potentials.energy import (
    EnergyTerms,
    colour_affinity,
    data_confidence,
    distance_affinity,
    graph_system,
    normal_affinity,
    std_in_metres,
    to_depth,
)
from crfdepth.superpixels.graph import build_checked_graphs
from crfdepth.superpixels.segments import slic_batch
from crfdepth.uncertainty.count import node_count_uncertainty
from crfdepth.uncertainty.posterior import posterior_std, system_conditional_variance


def graph_terms(model: torch.nn.Module, nodes: Nodes, normals: tuple[torch.Tensor, torch.Tensor] | None,
                scales: tuple[torch.Tensor, ...]) -> EnergyTerms:
    """The first solve's terms: data, prior, colour and (where both nodes have LiDAR normals) normal;
    ``scales`` are :meth:`CRFDepth.scales <crfdepth.model.CRFDepth.scales>`."""
    src, dst = nodes.edge_index
    alpha, beta, gamma, _, eps, _ = scales
    colour = colour_affinity(nodes.colour[src], nodes.colour[dst], model.sigma_d)
    normal = None
    if normals is not None:
        node_normal, known = normals
        both = (known[src] & known[dst]).to(nodes.prior.dtype)
        normal = normal_affinity(node_normal[src], node_normal[dst], model.sigma_n) * both
    return EnergyTerms(nodes.lidar, data_confidence(nodes.count, model.confidence), nodes.prior, nodes.edge_index,
                       colour, normal, None, alpha, beta, gamma if gamma is not None else torch.zeros_like(alpha),
                       torch.zeros_like(alpha), eps)


def refit_geometry(model: torch.nn.Module, terms: EnergyTerms, x: torch.Tensor, nodes: Nodes, K: torch.Tensor,
                   normals: tuple[torch.Tensor, torch.Tensor] | None, delta: torch.Tensor) -> None:
    """Refit the normal and 3D-distance terms to the solution ``x`` (in the unknown), in place:
    nodes without LiDAR normals take the normal fitted to their neighbours' 3D points."""
    src, dst = nodes.edge_index
    from kornia.geometry.camera import unproject_points  # at first use: kornia's import is 0.2 s

    points = unproject_points(nodes.centroid, to_depth(x, model.settings.structure.variable)[:, None], K[nodes.frame])
    if normals is not None:
        node_normal, known = normals
        fitted = graph_normals(points, nodes.edge_index, x.shape[0])
        normal = torch.where(known[:, None], node_normal, fitted)
        terms.normal = normal_affinity(normal[src], normal[dst], model.sigma_n)
    if "distance" in model.settings.potentials.on:
        terms.distance = distance_affinity(points[src], points[dst], model.sigma_p)
        terms.delta = delta


def superpixel_forward(model: torch.nn.Module, image: torch.Tensor, sparse: torch.Tensor, K: torch.Tensor,
                       return_std: bool) -> CRFOutput:
    """:meth:`CRFDepth.forward <crfdepth.model.CRFDepth.forward>` in superpixel mode, on checked inputs."""
    h, w = sparse.shape[2:]
    structure, on, solver = model.settings.structure, model.settings.potentials.on, model.solve_settings
    stage = Stages(sparse.device, model.progress)
    with stage("fill"):
        gate, kept, fill, distance = evidence(model, sparse, with_distance=True)
    with stage("slic"):
        labels = slic_batch(image.detach(), model.segments_for(h, w))  # (B, H, W), the whole batch at once
    with stage("graph"):
        graphs = build_checked_graphs(image.detach(), kept.detach()[:, 0], labels, structure.aggregate)
        nodes = gather_nodes(graphs, image, sparse, fill, gate, structure.variable)
    normals = None
    if "normal" in on:
        with stage("normals"):
            normals = gather_normals(graphs, kept, K, sparse.dtype)
    with stage("potentials"):
        scales = model.scales()
        terms = graph_terms(model, nodes, normals, scales)
    infos: list[SolveInfo] = []
    with stage("solve"):
        x, info = solve_system(graph_system(terms, nodes.ptr), nodes.prior, solver)
        infos.append(info)
    if "normal" in on or "distance" in on:
        for _ in range(structure.rounds):
            with stage("potentials"):
                refit_geometry(model, terms, x, nodes, K, normals, scales[3])
            with stage("solve"):
                x, info = solve_system(graph_system(terms, nodes.ptr), x, solver)
                infos.append(info)
    with stage("painting"):
        x = to_depth(x, structure.variable)  # node depths in metres from here on
        node_of_pixel = nodes.labels(graphs)
        depth = x[node_of_pixel][:, None]
        count_map = node_count_uncertainty(torch.cat([g.lidar_count for g in graphs]), sparse.dtype)[node_of_pixel][:, None]
    if structure.refine:
        with stage("refine"):
            depth, _, grid = pixel_solve(model, image, sparse, K, depth, model.refine_prior * scales[5], infos,
                                      geometry=depth, gate=gate, kept=kept)
    node_std = std = features = None
    if return_std:
        with stage("uncertainty"):
            system = graph_system(terms, nodes.ptr)
            std_settings = model.settings.uncertainty
            if std_settings.kind == "posterior":
                node_std = std_in_metres(posterior_std(system, model.std_scale, samples=std_settings.samples), x,
                                         structure.variable)
                std = node_std[node_of_pixel][:, None]
            else:
                if structure.refine:  # the last solve is the refinement's pixel grid
                    std, features = grid_std(model, depth, sparse, kept, gate, grid, distance)
                else:
                    variance = system_conditional_variance(system)[node_of_pixel][:, None]
                    std, features = predictive_std(model, depth, sparse, kept, gate, variance)
                node_std = torch.cat([g.node_mean(std[i])[:, 0] for i, g in enumerate(graphs)])
    return CRFOutput(depth, std, count_map, x, node_std, nodes.ptr, graphs, terms, infos, stage.seconds, features)
