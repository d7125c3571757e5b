"""The superpixel-graph pipeline (crfdepth/inference/superpixel.py): its solves, its count map, and the
settings it reads from ``model.settings``."""

from __future__ import annotations

import pytest
import torch

from crfdepth.inference import PIPELINES
from crfdepth.model import CRFDepth
from tests.test_model import small_scene


@pytest.mark.parametrize("rounds, refine, solves", [(1, False, 2), (2, False, 3), (2, True, 4)])
def test_one_solve_then_one_per_round_then_one_for_the_refinement(rounds, refine, solves):
    image, sparse, K, _ = small_scene(24, 32)
    model = CRFDepth(superpixels=60, scale_superpixels=False, rounds=rounds, refine=refine).double()
    out = PIPELINES["superpixel"](model, image, sparse, K[None], False)
    assert len(out.info) == solves and out.graphs is not None and out.std is None
    assert out.depth.shape == sparse.shape


def test_segments_follow_the_image_area_unless_told_not_to():
    assert CRFDepth(superpixels=5500).segments_for(352, 1216) == 5500
    assert CRFDepth(superpixels=5500).segments_for(176, 608) == 1375
    assert CRFDepth(superpixels=5500, scale_superpixels=False).segments_for(176, 608) == 5500
    assert CRFDepth(superpixels=100).segments_for(10, 10) == 16  # never fewer than 16


def test_potential_ablation_and_count_map():
    image, sparse, K, _ = small_scene(24, 32)
    model = CRFDepth(mode="superpixel", superpixels=60, scale_superpixels=False, potentials=("colour",),
                     refine=False).double()
    out = model(image, sparse, K)
    assert out.terms.normal is None and out.terms.distance is None and len(out.info) == 1
    assert set(torch.unique(out.count_uncertainty).tolist()) <= {0.0, 0.5, 1.0}
    nodes_without = out.count_uncertainty[0, 0][sparse[0, 0] > 0]
    assert bool((nodes_without < 1).all())  # a pixel with LiDAR is never in an empty node
