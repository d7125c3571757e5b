"""Tests for crfdepth.superpixels.graph and .edges: SLIC segments, node features and the paper's 4-neighbour edges."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from skimage.graph import rag_mean_color

from crfdepth.errors import InputError
from crfdepth.linalg import grid_edge_index
from crfdepth.superpixels.edges import DIRECTIONS_DEG, four_neighbour_picks, region_adjacency, undirected_edges
from crfdepth.superpixels.graph import batch_edge_index, build_superpixel_graph, build_superpixel_graphs
from crfdepth.superpixels.segments import slic_segments

RIGHT, DOWN, LEFT, UP = range(4)  # columns of four_neighbour_picks (y points down)


def rag_edges(image: torch.Tensor, labels: torch.Tensor) -> set[tuple[int, int]]:
    """Edge set of scikit-image's region adjacency graph (4-connectivity), pairs i < j."""
    rag = rag_mean_color(image.permute(1, 2, 0).numpy(), labels.numpy(), connectivity=1)
    return {(min(a, b), max(a, b)) for a, b in rag.edges()}


def edge_set(edge_index: torch.Tensor) -> set[tuple[int, int]]:
    return set(map(tuple, edge_index.T.tolist()))


def check_edge_index(edge_index: torch.Tensor, num_nodes: int) -> None:
    assert edge_index.dtype == torch.int64 and edge_index.shape[0] == 2
    assert bool((edge_index[0] < edge_index[1]).all())
    assert int(edge_index.min()) >= 0 and int(edge_index.max()) < num_nodes
    assert len(edge_set(edge_index)) == edge_index.shape[1]  # each pair once


def block_labels(rows: int, cols: int, block_h: int, block_w: int) -> torch.Tensor:
    """Regular grid of rows x cols rectangles of block_h x block_w pixels, row-major labels."""
    grid = torch.arange(rows * cols).view(rows, cols)
    return grid.repeat_interleave(block_h, 0).repeat_interleave(block_w, 1)


def coloured(labels: torch.Tensor, generator: torch.Generator) -> torch.Tensor:
    """(3, H, W) image, one random colour per label."""
    palette = torch.rand(int(labels.max()) + 1, 3, generator=generator)
    return palette[labels].permute(2, 0, 1).contiguous()


def brick_labels() -> tuple[torch.Tensor, dict[str, int]]:
    """Three rows of bricks (height 4, width 36); the middle brick C has six neighbours.

    Row 0 (y 0-3):  T0 cols 0-14,  T1 cols 15-26, T2 cols 27-35
    Row 1 (y 4-7):  L  cols 0-11,  C  cols 12-23, R  cols 24-35
    Row 2 (y 8-11): BL cols 0-8,   B0 cols 9-20,  B1 cols 21-35

    C's centroid is (17.5, 5.5). Its neighbours and their centroid directions (y down):
    R (29.5, 5.5) 0 deg; L (5.5, 5.5) 180 deg; T1 (20.5, 1.5) atan2(-4, 3) = 306.9 deg;
    T0 (7, 1.5) atan2(-4, -10.5) = 200.9 deg; B0 (14.5, 9.5) atan2(4, -3) = 126.9 deg;
    B1 (28, 9.5) atan2(4, 10.5) = 20.9 deg. Closest to 0 / 90 / 180 / 270 deg:
    R (0) / B0 (36.9 off; B1 is 69.1 off) / L (0) / T1 (36.9 off; T0 is 69.1 off).
    """
    names = ["T0", "T1", "T2", "L", "C", "R", "BL", "B0", "B1"]
    idx = {n: i for i, n in enumerate(names)}
    labels = torch.empty(12, 36, dtype=torch.int64)
    for name, (r0, c0, c1) in {
        "T0": (0, 0, 15), "T1": (0, 15, 27), "T2": (0, 27, 36),
        "L": (4, 0, 12), "C": (4, 12, 24), "R": (4, 24, 36),
        "BL": (8, 0, 9), "B0": (8, 9, 21), "B1": (8, 21, 36),
    }.items():
        labels[r0:r0 + 4, c0:c1] = idx[name]
    return labels, idx


def reference_picks(adjacency: torch.Tensor, centroid: torch.Tensor, num_nodes: int) -> torch.Tensor:
    """The rule written as plain loops: per node and direction, the closest neighbour."""
    neighbours: list[set[int]] = [set() for _ in range(num_nodes)]
    for a, b in adjacency.T.tolist():
        neighbours[a].add(b)
        neighbours[b].add(a)
    c = centroid.double().tolist()
    out = torch.full((num_nodes, 4), -1, dtype=torch.int64)
    for i in range(num_nodes):
        for k, phi in enumerate(DIRECTIONS_DEG):
            best = None
            for j in sorted(neighbours[i]):
                theta = math.degrees(math.atan2(c[j][1] - c[i][1], c[j][0] - c[i][0]))
                dist = abs((theta - phi + 180.0) % 360.0 - 180.0)
                if best is None or dist < best[0] - 1e-9:
                    best = (dist, j)
            if best is not None:
                out[i, k] = best[1]
    return out


# --------------------------------------------------------------------------- edges


def test_regular_grid_picks_left_right_up_down_and_equals_rag():
    rows, cols = 5, 7
    labels = block_labels(rows, cols, 4, 6)
    image = coloured(labels, torch.Generator().manual_seed(0))
    sparse = torch.zeros(1, *labels.shape)
    g = build_superpixel_graph(image, sparse, labels=labels)
    assert g.num_nodes == rows * cols

    picks = four_neighbour_picks(g.adjacency, g.centroid, g.num_nodes)
    for r in range(1, rows - 1):
        for c in range(1, cols - 1):
            i = r * cols + c
            assert picks[i].tolist() == [i + 1, i + cols, i - 1, i - cols]  # right, down, left, up

    # Corner (0, 0) has only right and down; a top-edge node has right, down and left.
    assert set(picks[0].tolist()) == {1, cols}
    assert set(picks[3].tolist()) == {4, 3 + cols, 2}

    check_edge_index(g.edge_index, g.num_nodes)
    assert g.num_edges == rows * (cols - 1) + cols * (rows - 1)
    assert edge_set(g.edge_index) == rag_edges(image, labels)
    assert edge_set(g.adjacency) == rag_edges(image, labels)


def test_irregular_node_with_six_neighbours_keeps_the_four_closest_to_the_directions():
    labels, n = brick_labels()
    image = coloured(labels, torch.Generator().manual_seed(1))
    g = build_superpixel_graph(image, torch.zeros(labels.shape), labels=labels)
    c = n["C"]
    assert torch.allclose(g.centroid[c], torch.tensor([17.5, 5.5]))

    adjacent = {b if a == c else a for a, b in edge_set(g.adjacency) if c in (a, b)}
    assert adjacent == {n["L"], n["R"], n["T0"], n["T1"], n["B0"], n["B1"]}

    picks = four_neighbour_picks(g.adjacency, g.centroid, g.num_nodes)
    assert picks[c].tolist() == [n["R"], n["B0"], n["L"], n["T1"]]
    # Nobody else picks C, so C keeps exactly these four edges.
    incident = {b if a == c else a for a, b in edge_set(g.edge_index) if c in (a, b)}
    assert incident == {n["R"], n["B0"], n["L"], n["T1"]}

    rag = rag_edges(image, labels)
    assert edge_set(g.adjacency) == rag
    assert edge_set(g.edge_index) <= rag
    assert edge_set(g.edge_index) < rag  # T0-C and C-B1 are dropped
    check_edge_index(g.edge_index, g.num_nodes)


def test_picks_match_a_loop_reference_on_slic_segments():
    gen = torch.Generator().manual_seed(2)
    # Smooth random colours so that SLIC produces irregular segments.
    coarse = torch.rand(1, 3, 6, 8, generator=gen)
    image = torch.nn.functional.interpolate(coarse, size=(60, 80), mode="bilinear", align_corners=False)[0]
    labels = slic_segments(image, 120, compactness=5.0)
    g = build_superpixel_graph(image, torch.zeros(60, 80), labels=labels)
    picks = four_neighbour_picks(g.adjacency, g.centroid, g.num_nodes)
    assert torch.equal(picks, reference_picks(g.adjacency, g.centroid, g.num_nodes))

    rag = rag_edges(image, labels)
    assert edge_set(g.adjacency) == rag
    assert edge_set(g.edge_index) <= rag
    check_edge_index(g.edge_index, g.num_nodes)
    assert int(g.degree().min()) >= 1


def test_undirected_edges_deduplicates_and_orders_pairs():
    picks = torch.tensor([[1, 1, -1, 2], [0, 2, 0, -1], [0, 1, 1, 1]])
    assert undirected_edges(picks).tolist() == [[0, 0, 1], [1, 2, 2]]


def test_node_without_neighbours_has_no_picks():
    labels = torch.zeros(4, 5, dtype=torch.int64)
    g = build_superpixel_graph(torch.full((3, 4, 5), 0.5), torch.zeros(4, 5), labels=labels)
    assert g.num_nodes == 1 and g.num_edges == 0
    assert four_neighbour_picks(g.adjacency, g.centroid, 1).tolist() == [[-1, -1, -1, -1]]


def test_grid_edge_index_is_the_pixel_mode_graph():
    h, w = 7, 5
    e = grid_edge_index(h, w)
    assert e.shape == (2, h * (w - 1) + w * (h - 1))
    check_edge_index(e, h * w)
    # Every edge joins 4-neighbours: same row and adjacent columns, or the pixel below.
    d = e[1] - e[0]
    assert set(d.unique().tolist()) == {1, w}
    with pytest.raises(InputError, match="height"):
        grid_edge_index(0, 5)


# --------------------------------------------------------------------------- features


def test_node_features_match_a_per_label_numpy_computation():
    gen = torch.Generator().manual_seed(3)
    h, w = 24, 30
    labels = block_labels(4, 5, 6, 6)
    labels[10:14, 3:20] = 7  # one non-rectangular, non-convex label
    image = torch.rand(3, h, w, generator=gen)
    sparse = torch.rand(1, h, w, generator=gen) * 60 + 1
    sparse[torch.rand(1, h, w, generator=gen) > 0.15] = 0
    sparse[0, labels == 0] = 0  # one node without LiDAR

    g_mean = build_superpixel_graph(image, sparse, labels=labels)
    g_med = build_superpixel_graph(image, sparse[0], labels=labels, aggregate="median")
    assert g_med.aggregate == "median"
    lab, img, dep = labels.numpy(), image.numpy(), sparse[0].numpy()
    rows, cols = np.mgrid[0:h, 0:w]
    counts = []
    for s in range(g_mean.num_nodes):
        m = lab == s
        assert g_mean.area[s] == m.sum()
        np.testing.assert_allclose(g_mean.colour[s].numpy(), img[:, m].mean(axis=1), rtol=1e-6)
        np.testing.assert_allclose(g_mean.centroid[s].numpy(), [cols[m].mean(), rows[m].mean()], rtol=1e-6)
        d = dep[m & (dep > 0)]
        counts.append(d.size)
        assert g_mean.lidar_count[s] == d.size
        want_mean = d.mean() if d.size else 0.0
        want_med = np.median(d) if d.size else 0.0
        assert g_mean.lidar_depth[s].item() == pytest.approx(want_mean, rel=1e-6)
        assert g_med.lidar_depth[s].item() == pytest.approx(want_med, rel=1e-6)
    # The case mix the median code must handle: empty, odd and even counts.
    assert 0 in counts and any(c % 2 == 1 for c in counts) and any(c > 0 and c % 2 == 0 for c in counts)
    assert g_mean.colour.dtype == torch.float32 and g_mean.lidar_depth.dtype == torch.float32
    assert g_mean.area.dtype == torch.int64 and g_mean.lidar_count.dtype == torch.int64


def test_labels_with_gaps_are_renumbered():
    labels = torch.tensor([[0, 0, 5, 5], [9, 9, 5, 5]])
    g = build_superpixel_graph(torch.full((3, 2, 4), 0.25), torch.zeros(2, 4), labels=labels)
    assert g.num_nodes == 3
    assert g.labels.tolist() == [[0, 0, 1, 1], [2, 2, 1, 1]]
    assert g.area.tolist() == [2, 4, 2]


def test_batched_build_and_block_diagonal_layout():
    gen = torch.Generator().manual_seed(4)
    labels = torch.stack([block_labels(3, 4, 5, 5), block_labels(3, 4, 5, 5).flip(1)])
    image = torch.rand(2, 3, 15, 20, generator=gen)
    sparse = torch.zeros(2, 1, 15, 20)
    sparse[:, :, ::4, ::3] = 10.0
    graphs = build_superpixel_graphs(image, sparse, labels=labels)
    single = build_superpixel_graph(image[1], sparse[1], labels=labels[1])
    assert torch.equal(graphs[1].edge_index, single.edge_index)
    assert torch.equal(graphs[1].lidar_depth, single.lidar_depth)
    edges, ptr = batch_edge_index(graphs)
    assert ptr.tolist() == [0, 12, 24]
    assert edges.shape[1] == graphs[0].num_edges + graphs[1].num_edges
    assert torch.equal(edges[:, graphs[0].num_edges:], graphs[1].edge_index + 12)


@pytest.mark.parametrize("aggregate", ["mean", "median"])
def test_batched_build_equals_each_frame_built_alone(aggregate):
    """All frames at once (global node numbers, one adjacency) gives each frame's own graph, field by field."""
    gen = torch.Generator().manual_seed(7)
    image = torch.rand(3, 3, 40, 56, generator=gen)
    image[1] = image[1] * 0.2 + 0.4  # frames with different segment counts
    sparse = torch.where(torch.rand(3, 1, 40, 56, generator=gen) < 0.1, 1 + 30 * torch.rand(3, 1, 40, 56), 0.0)
    graphs = build_superpixel_graphs(image, sparse, n_segments=30, aggregate=aggregate)
    assert len({g.num_nodes for g in graphs}) > 1
    for k, g in enumerate(graphs):
        alone = build_superpixel_graph(image[k], sparse[k], n_segments=30, aggregate=aggregate)
        for field in ("labels", "edge_index", "adjacency", "colour", "centroid", "area", "lidar_count",
                      "lidar_depth"):
            assert torch.equal(getattr(g, field), getattr(alone, field)), (k, field)
        assert g.num_nodes == alone.num_nodes


# --------------------------------------------------------------------------- bad input


@pytest.mark.parametrize(
    "image, sparse, kwargs, name",
    [
        (torch.rand(4, 8, 8), torch.zeros(8, 8), {}, "image"),
        (torch.rand(8, 8), torch.zeros(8, 8), {}, "image"),
        (torch.rand(3, 8, 8) + 1.0, torch.zeros(8, 8), {}, "image"),
        (torch.rand(3, 8, 8), torch.zeros(8, 9), {}, "sparse"),
        (torch.rand(3, 8, 8), torch.zeros(2, 8, 8), {}, "sparse"),
        (torch.rand(3, 8, 8), torch.full((8, 8), -1.0), {}, "sparse"),
        (torch.rand(3, 8, 8), torch.full((8, 8), float("nan")), {}, "sparse"),
        (torch.rand(3, 8, 8), torch.zeros(8, 8), {"n_segments": 0}, "n_segments"),
        (torch.rand(3, 8, 8), torch.zeros(8, 8), {"aggregate": "mode"}, "aggregate"),
        (torch.rand(3, 8, 8), torch.zeros(8, 8), {"labels": torch.zeros(8, 7, dtype=torch.int64)}, "labels"),
        (torch.rand(3, 8, 8), torch.zeros(8, 8), {"labels": torch.full((8, 8), -1)}, "labels"),
    ],
)
def test_bad_input_names_the_argument(image, sparse, kwargs, name):
    with pytest.raises(InputError, match=rf"^{name}: expected"):
        build_superpixel_graph(image, sparse, **kwargs)


def test_slic_bad_input():
    with pytest.raises(InputError, match=r"^n_segments: expected an integer >= 1, got -3"):
        slic_segments(torch.rand(3, 8, 8), -3)
    with pytest.raises(InputError, match=r"^image: expected an \(H, W, 3\)"):
        slic_segments(np.zeros((8, 8, 4)), 4)


# --------------------------------------------------------------------------- real frame


@pytest.mark.kitti
def test_real_frame_5500_segments(kitti_root):
    from crfdepth.data.kitti import KittiValSelection

    sample = KittiValSelection(kitti_root / "depth_selection" / "val_selection_cropped")[0]
    g = build_superpixel_graph(sample.image, sample.sparse, n_segments=5500)
    assert abs(g.num_nodes - 5500) <= 0.2 * 5500  # measured: 5199
    degree = g.degree()
    assert int(degree.min()) >= 1
    mean_degree = degree.float().mean().item()
    assert 2.5 <= mean_degree <= 4.5  # measured: 4.00
    check_edge_index(g.edge_index, g.num_nodes)
    rag = rag_edges(sample.image, g.labels)
    assert edge_set(g.adjacency) == rag
    assert edge_set(g.edge_index) <= rag
    # About 4% of pixels have LiDAR; most superpixels below the top LiDAR row get some.
    assert int(g.lidar_count.sum()) == int((sample.sparse > 0).sum())
    assert 0.5 < (g.lidar_count > 0).float().mean().item() < 0.8  # measured: 0.63
    has = g.lidar_count > 0
    assert bool((g.lidar_depth[has] > 0).all()) and bool((g.lidar_depth[~has] == 0).all())


def test_region_adjacency_by_hand_and_against_skimage():
    labels = torch.tensor([[0, 0, 1],
                           [2, 3, 1],
                           [2, 2, 2]])
    # 0-1, 0-2, 0-3 (0 above 3), 1-3, 1-2 (1 above the last 2), 2-3; diagonal contact does not count
    assert region_adjacency(labels).tolist() == [[0, 0, 0, 1, 1, 2], [1, 2, 3, 2, 3, 3]]
    diagonal = torch.tensor([[0, 1], [1, 0]])  # the two 0 pixels touch only diagonally: 0-1 still adjacent
    assert region_adjacency(diagonal).tolist() == [[0], [1]]
    from skimage.graph import RAG

    rng = np.random.default_rng(0)
    random = rng.integers(0, 12, size=(20, 30))
    expected = sorted((min(a, b), max(a, b)) for a, b in RAG(random, connectivity=1).edges)
    got = region_adjacency(torch.from_numpy(random), num_nodes=12)
    assert list(zip(*got.tolist())) == expected
