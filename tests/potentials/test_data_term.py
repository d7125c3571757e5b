"""crfdepth.potentials.data_term: the gated LiDAR evidence, its prior fill and per-node aggregates (design 3, 3b)."""

from __future__ import annotations

import math

import pytest
import torch

from crfdepth.fill.ip_basic import ip_basic_fill
from crfdepth.fill.nearest import nearest_fill
from crfdepth.potentials.data_term import lidar_evidence, node_lidar
from crfdepth.potentials.occlusion import DEFAULT_SOFTNESS, DEFAULT_THRESHOLD, OcclusionFallbackWarning
from tests.scenes import leaky_wall

GATE = (DEFAULT_THRESHOLD, DEFAULT_SOFTNESS)


def _street():
    """(1, 1, 5, 12) returns: a pole at 5 m with a wall return at 20 m leaked 1 px beside it, two
    wall returns at 20 m out of the pole's 5x5 window, and a gentle slope (10 m next to 10.1 m)."""
    sparse = torch.zeros(1, 1, 5, 12)
    sparse[0, 0, 2, 2] = 5.0    # the pole
    sparse[0, 0, 2, 3] = 20.0   # leaked: r = 1/5 - 1/20 = 0.15 1/m, ten times the threshold
    sparse[0, 0, 2, 6] = 20.0   # 4 columns from the pole: outside its 5x5 window
    sparse[0, 0, 0, 7] = 20.0
    sparse[0, 0, 4, 10] = 10.0  # r = 1/10 - 1/10.1 = 0.001 1/m: kept
    sparse[0, 0, 4, 11] = 10.1
    return sparse


def test_without_a_gate_every_return_is_kept_and_the_fill_is_the_nearest_fill():
    sparse = _street()
    gate, kept, fill = lidar_evidence(sparse, None, 5, "nearest")
    assert gate is None and kept is sparse
    torch.testing.assert_close(fill, nearest_fill(sparse), rtol=0, atol=0)
    assert float(fill[0, 0, 2, 3]) == 20.0  # the leaked return stands in the fill


def test_the_gate_drops_exactly_the_see_through_return_and_the_fill_closes_over_it():
    sparse = _street()
    before = sparse.clone()
    gate, kept, fill = lidar_evidence(sparse, GATE, 5, "nearest")
    assert torch.equal(sparse, before)  # input untouched
    assert gate.shape == kept.shape == fill.shape == sparse.shape
    assert gate.dtype == kept.dtype == fill.dtype == torch.float32
    dropped = (sparse > 0) & (kept == 0)
    assert dropped.nonzero().tolist() == [[0, 0, 2, 3]]
    assert float(gate[0, 0, 2, 3]) < 0.5
    others = (sparse > 0) & ~dropped
    assert torch.equal(kept[others], sparse[others])
    assert bool((gate[others] > 0.5).all()) and float(gate[0, 0, 2, 2]) == 1.0  # nothing nearer: exactly 1
    assert torch.equal(gate[sparse == 0], torch.ones_like(gate[sparse == 0]))
    # The hole takes the pole's depth (1 px away), not the leaked 20 m.
    torch.testing.assert_close(fill, nearest_fill(kept), rtol=0, atol=0)
    assert float(fill[0, 0, 2, 3]) == 5.0 and bool((fill > 0).all())


def test_the_gate_window_decides_which_returns_see_each_other():
    sparse = torch.zeros(1, 1, 5, 8)
    sparse[0, 0, 2, 2], sparse[0, 0, 2, 4] = 5.0, 20.0  # 2 columns apart
    _, kept5, _ = lidar_evidence(sparse, GATE, 5, "nearest")
    _, kept3, _ = lidar_evidence(sparse, GATE, 3, "nearest")
    assert float(kept5[0, 0, 2, 4]) == 0.0 and float(kept3[0, 0, 2, 4]) == 20.0


def test_the_ip_basic_prior_fills_the_kept_returns():
    _, sparse, _, _, leaked = leaky_wall()
    _, kept, fill = lidar_evidence(sparse, GATE, 5, "ip_basic")
    # The gate drops the leaks, and on the box's last scan line (row 38, no leak) the wall returns within
    # 2 px of its sides: inside and just outside a silhouette look alike to a 5x5 window.
    beside = torch.zeros_like(leaked)
    beside[38, [28, 29, 60, 61]] = True
    assert torch.equal((sparse > 0) & (kept == 0), (leaked | beside)[None, None])
    torch.testing.assert_close(fill, ip_basic_fill(kept), rtol=0, atol=0)
    assert bool((fill > 0).all())


def test_the_gate_is_differentiable_in_its_parameters_and_the_rest_is_not():
    threshold = torch.tensor(DEFAULT_THRESHOLD, requires_grad=True)
    softness = torch.tensor(DEFAULT_SOFTNESS, requires_grad=True)
    gate, kept, fill = lidar_evidence(_street(), (threshold, softness), 5, "nearest")
    assert gate.requires_grad and not kept.requires_grad and not fill.requires_grad
    gate.sum().backward()
    assert float(threshold.grad) > 0 and float(softness.grad) != 0  # a higher threshold keeps more


def test_a_frame_the_gate_would_empty_keeps_all_its_returns_with_a_warning():
    """Frame 1: one return at 2 m among 24 at 50 m in its 5x5 window; the gate keeps 1/25 < 10%."""
    sparse = torch.cat([_street(), torch.zeros(1, 1, 5, 12)])
    sparse[1, 0, :, 3:8] = 50.0
    sparse[1, 0, 2, 5] = 2.0
    with pytest.warns(OcclusionFallbackWarning, match="frame 1 would keep"):
        gate, kept, _ = lidar_evidence(sparse, GATE, 5, "nearest")
    assert torch.equal(gate[1], torch.ones_like(gate[1])) and torch.equal(kept[1], sparse[1])
    assert float(kept[0, 0, 2, 3]) == 0.0  # the other frame is still gated


@pytest.mark.parametrize(("variable", "unknown"), [
    ("depth", lambda z: z),
    ("inverse", lambda z: 1.0 / z),
    ("log", math.log),
])
def test_node_lidar_is_the_gate_weighted_mean_of_the_returns_in_the_unknown(variable, unknown):
    sparse = torch.tensor([[2.0, 4.0, 0.0], [5.0, 0.0, 0.0]], dtype=torch.float64)
    gate = torch.tensor([[1.0, 0.5, 1.0], [0.25, 1.0, 1.0]], dtype=torch.float64)
    labels = torch.tensor([[0, 0, 1], [1, 2, 2]])
    z, n = node_lidar(sparse, gate, labels, 4, variable)
    assert z.shape == n.shape == (4,) and z.dtype == n.dtype == torch.float64
    # Node 0: returns 2 m (gate 1) and 4 m (gate 1/2); node 1: 5 m (gate 1/4), its empty pixel's gate
    # does not count; nodes 2 (no return) and 3 (no pixel): 0.
    torch.testing.assert_close(n, torch.tensor([1.5, 0.25, 0.0, 0.0], dtype=torch.float64))
    expected = [(unknown(2.0) + 0.5 * unknown(4.0)) / 1.5, unknown(5.0), 0.0, 0.0]
    torch.testing.assert_close(z, torch.tensor(expected, dtype=torch.float64))


def test_node_lidar_gradient_in_the_gate_matches_finite_differences():
    sparse = torch.tensor([[2.0, 4.0, 0.0], [5.0, 3.0, 0.0]], dtype=torch.float64)
    labels = torch.tensor([[0, 0, 1], [1, 0, 2]])
    gate = torch.tensor([[0.9, 0.5, 1.0], [0.25, 0.7, 1.0]], dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(lambda g: node_lidar(sparse, g, labels, 3, "inverse"), (gate,))
