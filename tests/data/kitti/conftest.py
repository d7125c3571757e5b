"""KITTI datasets and a sample check shared by the tests of crfdepth.data.kitti."""

from __future__ import annotations

import pytest
import torch

from crfdepth.data.kitti import KittiDepthCompletion, KittiValSelection
from crfdepth.data.sample import Sample


@pytest.fixture(scope="session")
def completion(kitti_root) -> KittiDepthCompletion:
    return KittiDepthCompletion(kitti_root / "depth_completion", raw_root=kitti_root / "raw")


@pytest.fixture(scope="session")
def val_selection(kitti_root) -> KittiValSelection:
    return KittiValSelection(kitti_root / "depth_selection" / "val_selection_cropped")


def _check_sample(s: Sample, size=(352, 1216)) -> None:
    """Shapes, dtypes and units common to every dataset."""
    h, w = size
    assert s.image.shape == (3, h, w) and s.image.dtype == torch.float32
    assert s.sparse.shape == (1, h, w) and s.sparse.dtype == torch.float32
    assert s.target.shape == (1, h, w) and s.target.dtype == torch.float32
    assert s.K.shape == (3, 3) and s.K.dtype == torch.float32
    assert 0.0 <= s.image.min() and s.image.max() <= 1.0 and s.image.std() > 0.05
    valid = s.sparse[s.sparse > 0]
    # metres: KITTI LiDAR returns lie between ~1 m and ~100 m (not mm, not 1/256 m units)
    assert 0.5 < valid.min() and valid.max() < 120.0 and 5.0 < valid.median() < 40.0


@pytest.fixture
def check_sample():
    """``check_sample(sample, size=(352, 1216))``: shapes, dtypes and units common to every dataset."""
    return _check_sample
