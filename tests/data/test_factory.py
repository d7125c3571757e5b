"""Tests for build_dataset, datasets by layout name (crfdepth/data/factory.py)."""

from __future__ import annotations

import pytest

from crfdepth.data import LAYOUTS, build_dataset
from crfdepth.data.kitti import KittiRawScans, KittiValSelection
from crfdepth.data.synthetic import SyntheticScenes
from crfdepth.errors import InputError


def test_synthetic_needs_no_root():
    ds = build_dataset("synthetic", count=3, seed=7, height=16, width=32)
    assert isinstance(ds, SyntheticScenes) and len(ds) == 3
    assert ds.names[0] == "synthetic-seed7" and (ds.height, ds.width) == (16, 32)


def test_bad_layout_and_missing_root():
    assert set(LAYOUTS) == {"depth_completion", "annotated", "val_selection", "test_selection", "raw", "object",
                            "synthetic", "sequence", "nyu_sync", "nyu_raw", "nyu_h5"}
    with pytest.raises(InputError, match="layout: expected one of 'depth_completion', .*, got 'kitti'"):
        build_dataset("kitti", "somewhere")
    with pytest.raises(InputError, match="root: a data folder is needed for layout 'raw'"):
        build_dataset("raw")


@pytest.mark.kitti
def test_kitti_layouts(kitti_root):
    val = build_dataset("val_selection", kitti_root / "depth_selection" / "val_selection_cropped")
    assert type(val) is KittiValSelection and len(val) == 2
    raw = build_dataset("raw", kitti_root / "raw", holdout="rings")
    assert type(raw) is KittiRawScans and raw.layout == "raw" and raw.holdout == "rings"
    obj = build_dataset("object", kitti_root / "object" / "training")
    assert obj.layout == "object" and len(obj) == 11
    with pytest.raises(InputError, match="KittiTestCompletion: expected"):
        build_dataset("test_selection", kitti_root / "raw")
