"""The edges of the superpixel graph: which segments touch and the paper's 4-neighbour rule
(docs/design.md section 2).

:func:`boundary_pairs` finds the segments that touch 4-connectedly and the pixel edges
between them (the region adjacency, :func:`region_adjacency`); from those pairs every node
keeps, for each of the directions 0, 90, 180 and 270 degrees, the adjacent node whose
centroid direction is closest to it (:func:`four_neighbour_picks`), and the edge set is the
undirected union of these picks, each pair once (:func:`undirected_edges`). Node indices are
``0 .. S-1``; an ``edge_index`` is (2, E) int64 with ``[0] < [1]``, each pair once, sorted
lexicographically.
"""

from __future__ import annotations

import math

import torch

from crfdepth.superpixels.segments import labels_tensor

__all__ = [
    "DIRECTIONS_DEG",
    "boundary_pairs",
    "four_neighbour_picks",
    "region_adjacency",
    "undirected_edges",
]

#: The four directions of the paper's neighbour rule, in degrees, in the order of the
#: columns of :func:`four_neighbour_picks`. Angles are measured in image coordinates
#: (x to the right, y **down**), so 0 = right, 90 = down, 180 = left, 270 = up.
DIRECTIONS_DEG = (0.0, 90.0, 180.0, 270.0)


def boundary_pairs(node: torch.Tensor, num_nodes: int) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """The segment graph of label maps: which segments touch, and through which pixel edges.

    The one superpixel-graph builder: :func:`region_adjacency` (the model's graph) and the
    superpixel mode of :func:`crfdepth.layer.crf_refine` (edge weights summed over each
    shared boundary) both use it.

    Args:
        node: (H, W) or (B, H, W) int64 node index per pixel, ``0 .. num_nodes-1`` (for a
            batch, global indices as from :func:`crfdepth.superpixels.segments.batch_segments`).
        num_nodes: number of nodes.

    Returns:
        ``pairs`` (2, A) int64 adjacent node pairs, ``[0] < [1]``, each once, sorted;
        ``crossing`` (P,) bool over the 4-connected pixel edges, horizontal ones (every
        frame, row-major) then vertical ones, true where the edge joins two segments;
        ``pair_of_edge`` (number of crossing edges,) the index into ``pairs`` of each
        crossing edge.
    """
    first = torch.cat([node[..., :, :-1].reshape(-1), node[..., :-1, :].reshape(-1)])
    second = torch.cat([node[..., :, 1:].reshape(-1), node[..., 1:, :].reshape(-1)])
    crossing = first != second
    low = torch.minimum(first[crossing], second[crossing])
    high = torch.maximum(first[crossing], second[crossing])
    key, pair_of_edge = torch.unique(low * num_nodes + high, return_inverse=True)  # sorted
    return torch.stack([key // num_nodes, key % num_nodes]), crossing, pair_of_edge


def region_adjacency(labels: torch.Tensor, num_nodes: int | None = None) -> torch.Tensor:
    """Pairs of labels that touch 4-connectedly (the region adjacency graph).

    Two labels are adjacent when some pixel of one has a horizontal or vertical
    neighbour pixel of the other (diagonal contact does not count), as in
    ``skimage.graph.rag_mean_color(..., connectivity=1)``.

    Args:
        labels: (H, W) int64 node labels ``0 .. S-1``.
        num_nodes: ``S``; taken as ``labels.max() + 1`` when omitted.

    Returns:
        (2, A) int64 on the labels' device, ``[0] < [1]``, each pair once, sorted
        lexicographically.
    """
    labels = labels_tensor(labels, None)
    n = int(labels.max()) + 1 if num_nodes is None else int(num_nodes)
    return boundary_pairs(labels, n)[0]


def four_neighbour_picks(adjacency: torch.Tensor, centroid: torch.Tensor, num_nodes: int) -> torch.Tensor:
    """The paper's neighbour rule (Sec. 3.2): per node, the neighbour closest to each direction.

    For node ``i`` and each direction ``phi`` in :data:`DIRECTIONS_DEG` (0, 90, 180, 270
    degrees), among the nodes adjacent to ``i`` pick the ``j`` whose centroid direction
    ``theta_ij = atan2(y_j - y_i, x_j - x_i)`` has the smallest angular distance
    ``|theta_ij - phi|`` (wrapped to [0, 180] degrees). Angles are in image coordinates
    with y pointing **down**, so 90 degrees is down in the image and 270 is up. The edge
    set built from the picks does not depend on this choice: flipping y swaps the picks
    for 90 and 270 and nothing else.

    There is no cut-off on the angular distance: a node with at least one neighbour gets
    a pick for every direction, and at image borders and corners some directions pick a
    neighbour that another direction already picked (so the node ends up with 3 or 2
    distinct neighbours, as the paper describes). Exact ties go to the smaller node index.

    Computed without a loop over nodes: every adjacency is taken in both orientations,
    the angular distances to the four directions are reduced per (node, direction) with
    ``scatter_reduce("amin")``, then the smallest index among the minimisers is taken the
    same way.

    Args:
        adjacency: (2, A) int64 adjacent pairs (either orientation; :func:`region_adjacency`).
        centroid: (S, 2) float node centroids ``(x, y)`` in pixels.
        num_nodes: ``S``.

    Returns:
        (S, 4) int64: column ``k`` is the node picked for direction ``DIRECTIONS_DEG[k]``,
        -1 where the node has no neighbour at all.
    """
    device = adjacency.device
    src = torch.cat([adjacency[0], adjacency[1]])
    dst = torch.cat([adjacency[1], adjacency[0]])
    delta = centroid.to(torch.float64)[dst] - centroid.to(torch.float64)[src]
    theta = torch.atan2(delta[:, 1], delta[:, 0])  # (D,), radians, y down
    targets = torch.tensor([math.radians(a) for a in DIRECTIONS_DEG], dtype=torch.float64, device=device)
    diff = theta[:, None] - targets[None, :]
    distance = torch.remainder(diff + math.pi, 2.0 * math.pi).sub(math.pi).abs().reshape(-1)  # (D*4,)
    group = (src[:, None] * 4 + torch.arange(4, device=device)[None, :]).reshape(-1)
    candidate = dst[:, None].expand(-1, 4).reshape(-1)

    best = torch.full((num_nodes * 4,), math.inf, dtype=torch.float64, device=device)
    best = best.scatter_reduce(0, group, distance, reduce="amin", include_self=True)
    is_best = distance == best[group]
    sentinel = num_nodes
    chosen = torch.where(is_best, candidate, torch.full_like(candidate, sentinel))
    picks = torch.full((num_nodes * 4,), sentinel, dtype=torch.int64, device=device)
    picks = picks.scatter_reduce(0, group, chosen, reduce="amin", include_self=True)
    picks[picks == sentinel] = -1
    return picks.view(num_nodes, 4)


def undirected_edges(picks: torch.Tensor) -> torch.Tensor:
    """Undirected union of per-node picks: each pair once, ``[0] < [1]``, sorted.

    Args:
        picks: (S, K) int64 neighbour indices per node, -1 = none (e.g.
            :func:`four_neighbour_picks`).

    Returns:
        (2, E) int64 edge index.
    """
    n, k = picks.shape
    node = torch.arange(n, device=picks.device)[:, None].expand(n, k)
    keep = (picks >= 0) & (picks != node)
    low = torch.minimum(node[keep], picks[keep])
    high = torch.maximum(node[keep], picks[keep])
    key = torch.unique(low * n + high)
    return torch.stack([key // n, key % n])
