"""The superpixel nodes of a batch as one block-diagonal graph (crfdepth/inference/nodes.py)."""

from __future__ import annotations

import pytest
import torch

from crfdepth.inference.nodes import gather_nodes
from crfdepth.model import CRFDepth
from crfdepth.superpixels.graph import build_checked_graphs
from crfdepth.superpixels.segments import slic_batch
from tests.test_model import small_scene


def test_the_frames_nodes_are_concatenated_with_their_offsets():
    a, b = small_scene(24, 32, 0), small_scene(24, 32, 1)
    image, sparse = torch.cat([a[0], b[0]]), torch.cat([a[1], b[1]])
    graphs = build_checked_graphs(image, sparse[:, 0], slic_batch(image, 30), "mean")
    nodes = gather_nodes(graphs, image, sparse, sparse, None, "depth")
    sizes = [g.num_nodes for g in graphs]
    assert nodes.ptr.tolist() == [0, sizes[0], sum(sizes)] and nodes.lidar.shape == (sum(sizes),)
    assert nodes.frame.tolist() == [0] * sizes[0] + [1] * sizes[1]
    labels = nodes.labels(graphs)  # frame 1's pixels point past frame 0's nodes
    assert int(labels[0].max()) == sizes[0] - 1 and int(labels[1].min()) == sizes[0]
    src, dst = nodes.edge_index  # no edge joins two frames
    assert bool((nodes.frame[src] == nodes.frame[dst]).all())


@pytest.mark.parametrize("mode", ["pixel", "superpixel"])
def test_batch_equals_frames_alone(mode):
    a, b = small_scene(24, 32, 0), small_scene(24, 32, 1)
    model = CRFDepth(mode=mode, superpixels=60, scale_superpixels=False, rtol=1e-11).double()
    both = model(torch.cat([a[0], b[0]]), torch.cat([a[1], b[1]]), torch.stack([a[2], b[2]]), return_std=True)
    for k, (image, sparse, K, _) in enumerate((a, b)):
        alone = model(image, sparse, K, return_std=True)
        assert torch.allclose(both.depth[k], alone.depth[0], atol=1e-8)
        if mode == "superpixel":  # exact variances on small graphs
            assert torch.allclose(both.std[k], alone.std[0], atol=1e-8)
