"""The superpixel nodes of a batch as one block-diagonal graph (docs/design.md section 2).

Each frame's :class:`~crfdepth.superpixels.graph.SuperpixelGraph` contributes its nodes; the
batch is concatenated once, with node offsets ``ptr``, so every later stage (potentials,
solve, painting) runs on the whole batch at once.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from crfdepth.geometry.node_normals import aggregate_normals
from crfdepth.geometry.normals import lidar_normals
from crfdepth.potentials.data_term import node_lidar
from crfdepth.potentials.energy import Variable, to_unknown
from crfdepth.superpixels.graph import SuperpixelGraph


@dataclass
class Nodes:
    """Per-node inputs of the graph CRF, all frames concatenated (N nodes, E edges)."""

    lidar: torch.Tensor  # (N,) LiDAR in the unknown: the mean, or the gate-weighted mean
    count: torch.Tensor  # (N,) LiDAR returns in the node (the sum of their gates when gated)
    colour: torch.Tensor  # (N, 3) mean colour, differentiable in the image
    centroid: torch.Tensor  # (N, 2) pixel centroid (x, y)
    prior: torch.Tensor  # (N,) the fill x0 in the unknown
    frame: torch.Tensor  # (N,) the frame each node belongs to
    edge_index: torch.Tensor  # (2, E) into the concatenated nodes
    ptr: torch.Tensor  # (B + 1,) node offsets of the frames

    def labels(self, graphs: list[SuperpixelGraph]) -> torch.Tensor:
        """(B, H, W) the concatenated node of every pixel (for painting node values back)."""
        return torch.stack([g.labels for g in graphs]) + self.ptr[:-1, None, None]


def gather_nodes(graphs: list[SuperpixelGraph], image: torch.Tensor, sparse: torch.Tensor, fill: torch.Tensor,
                 gate: torch.Tensor | None, variable: Variable) -> Nodes:
    """The nodes of ``graphs`` (one per frame of ``image`` (B, 3, H, W), ``sparse`` and ``fill``
    (B, 1, H, W)); with ``gate`` (B, 1, H, W) the LiDAR mean and count are gate-weighted,
    differentiable in the gate's parameters."""
    dtype, device = sparse.dtype, sparse.device
    lidar, count, colour, centroid, prior, frame, edges, offsets = [], [], [], [], [], [], [], [0]
    for i, g in enumerate(graphs):
        colour.append(g.node_mean(image[i]))
        prior.append(g.node_mean(fill[i])[:, 0])
        if gate is None:
            lidar.append(to_unknown(g.lidar_depth.to(dtype), variable))
            count.append(g.lidar_count)
        else:
            z, n = node_lidar(sparse[i, 0], gate[i, 0], g.labels, g.num_nodes, variable)
            lidar.append(z)
            count.append(n)
        centroid.append(g.centroid.to(dtype))
        frame.append(torch.full((g.num_nodes,), i, dtype=torch.long, device=device))
        edges.append(g.edge_index + offsets[-1])
        offsets.append(offsets[-1] + g.num_nodes)
    return Nodes(lidar=torch.cat(lidar), count=torch.cat(count), colour=torch.cat(colour),
                 centroid=torch.cat(centroid), prior=to_unknown(torch.cat(prior), variable), frame=torch.cat(frame),
                 edge_index=torch.cat(edges, 1), ptr=torch.tensor(offsets, device=device))


def gather_normals(graphs: list[SuperpixelGraph], kept: torch.Tensor, K: torch.Tensor,
                   dtype: torch.dtype) -> tuple[torch.Tensor, torch.Tensor]:
    """``(normal (N, 3), known (N,) bool)``: each node's normal from the LiDAR returns in it
    (:func:`crfdepth.geometry.normals.lidar_normals` on all frames at once, then aggregated)."""
    normals, ok = lidar_normals(kept.detach(), K.detach())
    per_frame = [aggregate_normals(normals[i], ok[i, 0], g.labels, g.num_nodes) for i, g in enumerate(graphs)]
    return torch.cat([n.to(dtype) for n, _ in per_frame]), torch.cat([v for _, v in per_frame])
