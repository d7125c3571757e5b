"""The shipped indoor weights, ``--weights nyu`` (docs/design.md section 17; benchmarks/nyu_weights.py)."""

from __future__ import annotations

import dataclasses

import torch

from crfdepth.data.factory import build_dataset
from crfdepth.data.sampling import SparseSamples
from crfdepth.model import CRFDepth
from crfdepth.weights import read_weights, weights_path


def test_nyu_weights_have_the_sparse_regimes_structure_and_their_own_std():
    model = CRFDepth.from_pretrained("nyu")
    structure = model.settings.structure
    assert (structure.mode, structure.coarse, structure.variable) == ("pixel", 6, "depth")
    assert not model.settings.gate.enabled and model.sparse_regime is None
    assert model.settings.uncertainty.terms != CRFDepth().settings.uncertainty.terms  # re-fitted std


def test_nyu_weights_were_shipped_because_they_beat_the_kitti_weights_on_held_out_scenes():
    about = read_weights(weights_path("nyu"))["about"]
    rows = about["leave_one_scene_out"]
    assert {r["held_out"] for r in rows} == {"basement", "dining"} and {r["samples"] for r in rows} == {500, 200}
    assert all(r["learned_vs_kitti"] <= 0.95 for r in rows if r["samples"] == 500)  # the bar
    assert "nyu_weights.py" in about["recipe"]


def test_nyu_weights_complete_real_indoor_frames_better_than_the_kitti_weights(nyu_root):
    frames = [SparseSamples(500, seed=1)(dataclasses.replace(s, sparse=s.target))
              for s in build_dataset("nyu_sync", nyu_root / "official_test", protocol=True)]
    errors = {}
    for name in ("nyu", "kitti"):
        model = CRFDepth.from_pretrained(name, adaptive=False) if name == "kitti" else CRFDepth.from_pretrained(name)
        values = []
        for s in frames:
            with torch.no_grad():
                depth = model(s.image[None], s.sparse[None], s.K[None]).depth[0]
            valid = s.target > 0
            values.append(float(((depth[valid] - s.target[valid]) ** 2).mean().sqrt()))
        errors[name] = sum(values) / len(values)
    # in-sample for these frames (the file was fitted on them); held-out scenes: benchmarks/nyu_weights.py
    assert errors["nyu"] < 0.97 * errors["kitti"]
