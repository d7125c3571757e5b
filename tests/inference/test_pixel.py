"""The pixel-grid pipeline and the stages both pipelines share (crfdepth/inference/pixel.py), reading the
model's one configuration, ``model.settings``."""

from __future__ import annotations

import pytest
import torch

from crfdepth.inference import PIPELINES
from crfdepth.inference.pixel import evidence, pixel_solve
from crfdepth.model import CRFDepth
from tests.test_model import small_scene


def test_evidence_has_a_gate_only_when_the_configuration_turns_it_on():
    _, sparse, _, _ = small_scene(24, 32)
    gate, kept, fill = evidence(CRFDepth(mode="pixel").double(), sparse)
    assert gate is None and torch.equal(kept, sparse) and bool((fill > 0).all())
    gate, kept, _ = evidence(CRFDepth(mode="pixel", gate=True, gate_window=3).double(), sparse)
    assert gate.shape == sparse.shape and bool(((gate >= 0) & (gate <= 1)).all())


@pytest.mark.parametrize("options, solves", [
    ({}, 2), ({"rounds": 3}, 4), ({"potentials": ("colour",)}, 1), ({"irls": 2}, 4),
])
def test_one_solve_then_one_per_round_then_the_reweighting(options, solves):
    image, sparse, K, _ = small_scene(24, 32)
    model = CRFDepth(mode="pixel", **options).double()
    _, _, fill = evidence(model, sparse)
    infos = []
    depth, _, _ = pixel_solve(model, image, sparse, K[None], fill, model.scales()[4], infos)
    assert len(infos) == solves and depth.shape == sparse.shape


def test_the_pipeline_is_the_models_forward_on_checked_inputs():
    image, sparse, K, _ = small_scene(24, 32)
    model = CRFDepth(mode="pixel", variable="log", uncertainty="posterior", std_samples=8).double()
    direct = PIPELINES["pixel"](model, image, sparse, K[None], True)
    forward = model(image, sparse, K, return_std=True)
    assert torch.equal(direct.depth, forward.depth) and direct.std.shape == sparse.shape
