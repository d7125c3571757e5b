"""The CRF graph of one frame: SLIC superpixels, node features and edges (docs/design.md section 2).

Two kinds of graph are supported:

- **Superpixel mode** (the paper's default, Sec. 3.2): nodes are SLIC superpixels
  (:func:`slic_segments`). Their features (mean colour, centroid, area, LiDAR count and
  aggregated LiDAR depth) are computed by :func:`build_superpixel_graph`. The edges
  follow the paper's 4-neighbour rule (:mod:`crfdepth.superpixels.edges`): from the region
  adjacency of the superpixels, every node keeps, for each of the directions 0, 90, 180
  and 270 degrees, the adjacent node whose centroid direction is closest to it; the edge
  set is the undirected union of these picks, each pair once.
- **Pixel mode**: every pixel is a node and the edges are the 4-connected grid,
  :func:`crfdepth.linalg.grid_edge_index`, ``H (W - 1) + W (H - 1)`` edges.

:func:`paint` maps node values back to pixels (piecewise constant, as in the paper).

Conventions used throughout:

- ``labels`` is an (H, W) int64 map of node indices ``0 .. S-1``; every index occurs.
- Pixel coordinates are ``x = column``, ``y = row``, in pixels, with the centre of pixel
  ``(row, col)`` at ``(x, y) = (col, row)``, the same convention as the intrinsics ``K``
  of :class:`crfdepth.data.sample.Sample`.
- Depth is camera z-depth in metres; 0 means "no LiDAR return at this pixel".
- ``edge_index`` is (2, E) int64 with ``edge_index[0] < edge_index[1]``, each undirected
  pair once, sorted lexicographically.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import numpy as np
import torch

from crfdepth.checks import check_depth_values, describe
from crfdepth.errors import InputError
from crfdepth.superpixels.edges import boundary_pairs, four_neighbour_picks, undirected_edges
from crfdepth.superpixels.segments import image_tensor, labels_tensor, slic_batch

__all__ = [
    "SuperpixelGraph",
    "batch_edge_index",
    "build_superpixel_graph",
    "build_superpixel_graphs",
]

Aggregate = Literal["mean", "median"]


# --------------------------------------------------------------------------- input checks


def _sparse_tensor(sparse: torch.Tensor, size: tuple[int, int], name: str = "sparse") -> torch.Tensor:
    """(H, W) view of a (1, H, W) or (H, W) depth tensor, checked finite and >= 0."""
    h, w = size
    if not isinstance(sparse, torch.Tensor):
        raise InputError(f"{name}: expected a (1, {h}, {w}) or ({h}, {w}) tensor, got {describe(sparse)}")
    if sparse.ndim == 3 and sparse.shape[0] == 1:
        sparse = sparse[0]
    if tuple(sparse.shape) != (h, w):
        raise InputError(
            f"{name}: expected a (1, {h}, {w}) or ({h}, {w}) depth tensor (the image size), "
            f"got {describe(sparse)}"
        )
    check_depth_values(name, sparse)
    return sparse


# --------------------------------------------------------------------------- graph


@dataclass
class SuperpixelGraph:
    """The superpixel CRF graph of one frame (docs/design.md section 2).

    ``S = num_nodes`` nodes, ``E`` edges, ``A`` adjacent pairs, on the device of the inputs.

    Attributes:
        labels: (H, W) int64 node index of every pixel, ``0 .. S-1``.
        num_nodes: ``S``.
        edge_index: (2, E) int64 edges of the paper's 4-neighbour rule
            (:func:`crfdepth.superpixels.edges.four_neighbour_picks`), ``[0] < [1]``, each pair
            once, sorted.
        adjacency: (2, A) int64 all 4-connected adjacent pairs
            (:func:`crfdepth.superpixels.edges.region_adjacency`);
            ``edge_index`` is a subset.
        colour: (S, 3) mean RGB in [0, 1] (dtype of the image).
        centroid: (S, 2) mean pixel coordinates ``(x, y) = (col, row)`` (float32, or
            float64 for a float64 image).
        area: (S,) int64 number of pixels.
        lidar_count: (S,) int64 number of pixels with LiDAR (``sparse > 0``).
        lidar_depth: (S,) aggregated LiDAR z-depth in metres (mean or median of the LiDAR
            pixels, see ``aggregate``); 0 where ``lidar_count == 0``. Dtype of ``sparse``.
        aggregate: how ``lidar_depth`` was aggregated, ``"mean"`` or ``"median"``.
    """

    labels: torch.Tensor
    num_nodes: int
    edge_index: torch.Tensor
    adjacency: torch.Tensor
    colour: torch.Tensor
    centroid: torch.Tensor
    area: torch.Tensor
    lidar_count: torch.Tensor
    lidar_depth: torch.Tensor
    aggregate: str = "mean"

    @property
    def num_edges(self) -> int:
        return int(self.edge_index.shape[1])

    def degree(self) -> torch.Tensor:
        """(S,) int64 number of edges at each node."""
        flat = self.edge_index.reshape(-1)
        return torch.bincount(flat, minlength=self.num_nodes)

    def node_mean(self, values: torch.Tensor) -> torch.Tensor:
        """(S, C) mean over each node's pixels of (C, H, W) ``values``, in their dtype and
        differentiable in them (the graph itself is not)."""
        sums = values.new_zeros(self.num_nodes, values.shape[0]).index_add(
            0, self.labels.reshape(-1), values.reshape(values.shape[0], -1).T)
        return sums / self.area.to(values.dtype)[:, None]


def _segment_sums(values: torch.Tensor, labels_flat: torch.Tensor, num_nodes: int) -> torch.Tensor:
    """(S, C) float64 per-label sums of (N, C) values."""
    out = torch.zeros(num_nodes, values.shape[1], dtype=torch.float64, device=values.device)
    return out.index_add_(0, labels_flat, values.to(torch.float64))


def _segment_median(depth: torch.Tensor, labels_flat: torch.Tensor, count: torch.Tensor) -> torch.Tensor:
    """Per-label median of ``depth`` (N,), mean of the two middle values for even counts; 0 if empty."""
    num_nodes = count.shape[0]
    out = torch.zeros(num_nodes, dtype=torch.float64, device=depth.device)
    if depth.numel() == 0:
        return out
    by_depth = torch.argsort(depth, stable=True)
    by_label = torch.argsort(labels_flat[by_depth], stable=True)
    ordered = depth[by_depth][by_label].to(torch.float64)  # sorted by (label, depth)
    start = torch.cumsum(count, 0) - count
    last = ordered.numel() - 1
    lo = (start + (count - 1).clamp(min=0) // 2).clamp(max=last)
    hi = (start + count // 2).clamp(max=last)
    has = count > 0
    out[has] = 0.5 * (ordered[lo[has]] + ordered[hi[has]])
    return out


def build_superpixel_graph(image: torch.Tensor, sparse: torch.Tensor, n_segments: int = 5500,
                           aggregate: Aggregate = "mean", labels: torch.Tensor | np.ndarray | None = None, *,
                           compactness: float = 20.0, sigma: float = 1.0, max_num_iter: int = 5) -> SuperpixelGraph:
    """Superpixel graph of one frame: segments, node features and the paper's edges.

    Nodes and features as in docs/design.md section 2; edges by
    :func:`crfdepth.superpixels.edges.four_neighbour_picks` over the region adjacency. All
    per-node sums use ``index_add``/``bincount`` (no loop over nodes); the median sorts the
    LiDAR pixels by (label, depth) and takes the middle elements.

    Args:
        image: (3, H, W) float RGB in [0, 1].
        sparse: (1, H, W) or (H, W) LiDAR z-depth in metres, 0 = no LiDAR return.
        n_segments: SLIC segments wanted (ignored when ``labels`` is given).
        aggregate: ``"mean"`` (default) or ``"median"`` of the LiDAR depths in a node.
        labels: optional precomputed (H, W) integer segmentation; label values that do not
            occur are dropped (node ``i`` is the ``i``-th smallest label present), so
            ``graph.labels`` is the map actually used.
        compactness, sigma, max_num_iter: passed to :func:`slic_segments`.

    Returns:
        :class:`SuperpixelGraph` on the image's device.

    Raises:
        InputError: image not (3, H, W) RGB in [0, 1]; ``sparse`` not the image size, NaN,
            infinite or negative; ``n_segments < 1``; bad ``labels``; unknown ``aggregate``.
    """
    image = image_tensor(image)
    size = (int(image.shape[1]), int(image.shape[2]))
    depth = _sparse_tensor(sparse, size).reshape(1, 1, *size).to(image.device)
    seg = None if labels is None else labels_tensor(labels, size)[None]
    return build_superpixel_graphs(image[None], depth, n_segments, aggregate, seg, compactness=compactness,
                                   sigma=sigma, max_num_iter=max_num_iter)[0]


def build_checked_graphs(image: torch.Tensor, depth: torch.Tensor, seg: torch.Tensor,
                         aggregate: str) -> list[SuperpixelGraph]:
    """The graphs of a checked batch: (B, 3, H, W) image, (B, H, W) depth and consecutive labels,
    all on one device (the model calls this on inputs it has checked once; the public builders
    check theirs first).

    All frames at once: frame ``k``'s labels are offset by the nodes of the frames before
    it, so every per-node sum, the adjacency and the neighbour picks run over the whole
    batch as one graph without edges between frames; the result is then cut into one
    :class:`SuperpixelGraph` per frame, equal to building each frame alone (node ``i`` of
    a frame keeps its place, and every sum adds the same pixels in the same order).
    """
    b, _, h, w = image.shape
    device = image.device
    sizes = seg.flatten(1).max(1).values + 1  # nodes per frame
    ptr = torch.cat([sizes.new_zeros(1), sizes.cumsum(0)])
    node = seg + ptr[:-1, None, None]  # (B, H, W) global node index
    num_nodes = int(ptr[-1])
    flat = node.reshape(-1)

    area = torch.bincount(flat, minlength=num_nodes)
    area_f = area.to(torch.float64)[:, None]
    colour = _segment_sums(image.permute(0, 2, 3, 1).reshape(-1, 3), flat, num_nodes) / area_f
    rows, cols = torch.meshgrid(
        torch.arange(h, device=device, dtype=torch.float64),
        torch.arange(w, device=device, dtype=torch.float64),
        indexing="ij",
    )
    xy = torch.stack([cols.reshape(-1), rows.reshape(-1)], dim=1).repeat(b, 1)
    centroid = _segment_sums(xy, flat, num_nodes) / area_f

    depth_flat = depth.reshape(-1)
    has_lidar = depth_flat > 0
    lidar_labels = flat[has_lidar]
    lidar_values = depth_flat[has_lidar]
    lidar_count = torch.bincount(lidar_labels, minlength=num_nodes)
    if aggregate == "mean":
        total = torch.zeros(num_nodes, dtype=torch.float64, device=device)
        total.index_add_(0, lidar_labels, lidar_values.to(torch.float64))
        lidar_depth = torch.where(lidar_count > 0, total / lidar_count.clamp(min=1), torch.zeros_like(total))
    else:
        lidar_depth = _segment_median(lidar_values, lidar_labels, lidar_count)

    adjacency = boundary_pairs(node, num_nodes)[0]  # no pixel edge joins two frames
    edge_index = undirected_edges(four_neighbour_picks(adjacency, centroid, num_nodes))
    coord_dtype = torch.float64 if image.dtype == torch.float64 else torch.float32
    colour, centroid, lidar_depth = colour.to(image.dtype), centroid.to(coord_dtype), lidar_depth.to(depth.dtype)
    # Pairs are sorted by their first node, so each frame's edges and pairs are one run.
    edge_cut = torch.searchsorted(edge_index[0].contiguous(), ptr).tolist()
    pair_cut = torch.searchsorted(adjacency[0].contiguous(), ptr).tolist()
    bounds = ptr.tolist()
    graphs = []
    for k in range(b):
        lo, hi = bounds[k], bounds[k + 1]
        graphs.append(SuperpixelGraph(
            labels=seg[k],
            num_nodes=hi - lo,
            edge_index=edge_index[:, edge_cut[k]:edge_cut[k + 1]] - lo,
            adjacency=adjacency[:, pair_cut[k]:pair_cut[k + 1]] - lo,
            colour=colour[lo:hi],
            centroid=centroid[lo:hi],
            area=area[lo:hi],
            lidar_count=lidar_count[lo:hi],
            lidar_depth=lidar_depth[lo:hi],
            aggregate=aggregate,
        ))
    return graphs


def build_superpixel_graphs(image: torch.Tensor, sparse: torch.Tensor, n_segments: int = 5500,
                            aggregate: Aggregate = "mean", labels: torch.Tensor | None = None, *,
                            compactness: float = 20.0, sigma: float = 1.0, max_num_iter: int = 5
                            ) -> list[SuperpixelGraph]:
    """Batched :func:`build_superpixel_graph`: one graph per frame, built for all frames at once.

    Args:
        image: (B, 3, H, W) float RGB in [0, 1].
        sparse: (B, 1, H, W) LiDAR z-depth in metres, 0 = no LiDAR return.
        labels: optional (B, H, W) precomputed segmentations.
        n_segments, aggregate, compactness, sigma, max_num_iter: as for the single frame.

    Returns:
        A list of B :class:`SuperpixelGraph`; use :func:`batch_edge_index` to lay them out
        as one block-diagonal graph.
    """
    if not isinstance(image, torch.Tensor) or image.ndim != 4 or image.shape[1] != 3:
        raise InputError(f"image: expected a (B, 3, H, W) tensor, got {describe(image)}")
    b, _, h, w = image.shape
    if not isinstance(sparse, torch.Tensor) or tuple(sparse.shape) != (b, 1, h, w):
        raise InputError(f"sparse: expected a ({b}, 1, {h}, {w}) tensor (the image size), got {describe(sparse)}")
    if labels is not None and (not isinstance(labels, torch.Tensor) or tuple(labels.shape) != (b, h, w)):
        raise InputError(f"labels: expected a ({b}, {h}, {w}) integer tensor, got {describe(labels)}")
    if aggregate not in ("mean", "median"):
        raise InputError(f"aggregate: expected 'mean' or 'median', got {aggregate!r}")
    for k in range(b):  # the per-frame checks, with their messages
        image_tensor(image[k])
        _sparse_tensor(sparse[k], (h, w))
    seg = slic_batch(image, n_segments, compactness=compactness, sigma=sigma, max_num_iter=max_num_iter) \
        if labels is None else torch.stack([labels_tensor(labels[k], (h, w)) for k in range(b)])
    return build_checked_graphs(image, sparse[:, 0].to(image.device), seg.to(image.device), aggregate)


def batch_edge_index(graphs: list[SuperpixelGraph]) -> tuple[torch.Tensor, torch.Tensor]:
    """Lay a list of graphs out as one block-diagonal graph.

    Returns:
        ``edge_index`` (2, sum E) int64 with node indices offset per graph, and ``ptr``
        (G + 1,) int64 node offsets (graph ``g`` owns nodes ``ptr[g]:ptr[g+1]``), the layout
        of :class:`crfdepth.linalg.operators.EdgeGraph`.
    """
    if len(graphs) == 0:
        raise InputError("graphs: expected at least one SuperpixelGraph, got an empty list")
    device = graphs[0].edge_index.device
    sizes = torch.tensor([g.num_nodes for g in graphs], dtype=torch.int64, device=device)
    ptr = torch.cat([torch.zeros(1, dtype=torch.int64, device=device), torch.cumsum(sizes, 0)])
    edges = [g.edge_index + ptr[i] for i, g in enumerate(graphs)]
    return torch.cat(edges, dim=1), ptr


