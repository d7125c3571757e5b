"""Matrix-free operators (crfdepth/linalg/operators.py) against the dense scaled matrix."""

from __future__ import annotations

import torch

from crfdepth.linalg.operators import EdgeGraph, PixelGrid, grid_edge_index


def test_grid_edge_index_lists_horizontal_then_vertical_edges_row_major():
    ei = grid_edge_index(2, 3)
    assert ei.T.tolist() == [[0, 1], [1, 2], [3, 4], [4, 5], [0, 3], [1, 4], [2, 5]]


def test_pixel_grid_and_edge_graph_apply_the_same_scaled_operator():
    g = torch.Generator().manual_seed(0)
    h, w = 3, 4
    d = torch.rand(1, h, w, generator=g, dtype=torch.float64) + 0.5
    wh = torch.rand(1, h, w - 1, generator=g, dtype=torch.float64)
    wv = torch.rand(1, h - 1, w, generator=g, dtype=torch.float64)
    v = torch.randn(1, h, w, generator=g, dtype=torch.float64)
    grid = PixelGrid(1, h, w)
    diag = d + PixelGrid.degree(wh, wv)
    s = diag.rsqrt()
    by_grid = grid.from_rows(grid.scaled_matvec(wh, wv, s)(grid.to_rows(v)))
    ei = grid_edge_index(h, w)
    weights = torch.cat([wh.reshape(-1), wv.reshape(-1)])
    graph = EdgeGraph(ei, torch.tensor([0, h * w]))
    assert torch.allclose(graph.degree(weights), PixelGrid.degree(wh, wv).reshape(-1))
    s_flat = s.reshape(-1)
    by_graph = graph.from_rows(graph.scaled_matvec(weights, s_flat)(graph.to_rows(v.reshape(-1))))
    A = torch.diag(d.reshape(-1) + graph.degree(weights))
    A[ei[0], ei[1]] -= weights
    A[ei[1], ei[0]] -= weights
    dense = (s_flat[:, None] * A * s_flat[None, :]) @ v.reshape(-1)  # M = D^-1/2 A D^-1/2
    assert torch.allclose(by_grid.reshape(-1), dense, rtol=1e-12, atol=1e-12)
    assert torch.allclose(by_graph, dense, rtol=1e-12, atol=1e-12)


def test_ragged_graph_batches_round_trip_through_rows():
    graph = EdgeGraph(torch.tensor([[0, 3], [1, 4]]), torch.tensor([0, 2, 5]))
    v = torch.arange(5.0)
    rows = graph.to_rows(v, fill=-1.0)
    assert rows.tolist() == [[0.0, 1.0, -1.0], [2.0, 3.0, 4.0]]
    assert torch.equal(graph.from_rows(rows), v)
