"""Tests for SyntheticScenes, the torch Dataset of synthetic scenes (crfdepth/data/synthetic/dataset.py)."""

from __future__ import annotations

import pytest
import torch

from crfdepth.data import SyntheticScenes as FromData
from crfdepth.data.sample import Sample
from crfdepth.data.synthetic import SyntheticScenes, make_scene
from crfdepth.errors import InputError


def test_items_are_the_seeded_scenes():
    assert FromData is SyntheticScenes
    ds = SyntheticScenes(count=2, seed=5, height=24, width=64, beams=16)
    assert len(ds) == 2
    assert ds.names == ["synthetic-seed5", "synthetic-seed6"]
    item = ds[1]
    assert isinstance(item, Sample) and item.name == "synthetic-seed6" and item.has_target
    expected = make_scene(6, 24, 64, 16).to_tensors()
    for field in ("image", "sparse", "target", "K"):
        assert torch.equal(getattr(item, field), expected[field]), field
    assert torch.equal(ds[1].image, item.image)  # generated again on access, same arrays


def test_index_and_argument_errors():
    ds = SyntheticScenes(count=1, height=8, width=16)
    with pytest.raises(IndexError):
        ds[1]
    with pytest.raises(IndexError):
        ds[-1]
    with pytest.raises(InputError, match="count"):
        SyntheticScenes(count=0)
    with pytest.raises(InputError, match="seed"):
        SyntheticScenes(seed=-1)
