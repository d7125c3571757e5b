"""The paper's count-based uncertainty map (crfdepth/uncertainty/count.py)."""

from __future__ import annotations

import torch

from crfdepth.uncertainty.count import node_count_uncertainty, pixel_count_uncertainty


def test_nodes_without_returns_are_most_uncertain_one_return_half():
    counts = torch.tensor([0, 1, 2, 7])
    assert node_count_uncertainty(counts, torch.float32).tolist() == [1.0, 0.5, 0.0, 0.0]


def test_on_the_pixel_grid_a_pixel_is_certain_only_with_its_own_return():
    sparse = torch.tensor([[[[0.0, 3.0], [12.5, 0.0]]]])
    out = pixel_count_uncertainty(sparse)
    assert out.dtype == sparse.dtype and out.tolist() == [[[[1.0, 0.0], [0.0, 1.0]]]]
