"""train.sources: a training source's weight (frames per epoch) and its checks; the annotated layout as a source."""

from __future__ import annotations

import pytest
import torch
from torch.utils.data import TensorDataset

from crfdepth.errors import InputError
from train.data import CRFDataModule, dataset_names
from train.sources import check_weight, weighted

SMALL = {"height": 48, "width": 64}


@pytest.mark.parametrize(("weight", "count"), [(1.0, 10), (2.0, 20), (0.5, 5), (2.5, 25), (0.01, 1)])
def test_a_weight_scales_the_frames_of_an_epoch(weight, count):
    data = TensorDataset(torch.arange(10))
    out = weighted(data, weight)
    assert len(out) == count
    items = sorted(int(out[i][0]) for i in range(len(out)))
    # whole copies of every frame, then a fixed choice of distinct frames for the rest
    assert all(items.count(v) in (int(weight), int(weight) + 1) for v in set(items))
    assert sorted(int(weighted(data, weight, seed=0)[i][0]) for i in range(len(out))) == items


def test_weight_one_is_the_dataset_itself():
    data = TensorDataset(torch.arange(3))
    assert weighted(data, 1.0) is data


@pytest.mark.parametrize("weight", [0, -1, float("nan"), float("inf"), 101, True, "2"])
def test_bad_weights_are_named(weight):
    with pytest.raises(InputError, match=r"^extra_train\[1\]\.weight: expected a number in \(0, 100\]"):
        check_weight("extra_train[1].weight", weight)


def test_extra_sources_are_weighted_in_the_training_set():
    extra = {"layout": "synthetic", "options": {"count": 2, "seed": 500, **SMALL}, "weight": 3}
    dm = CRFDataModule(train_options={"count": 2, **SMALL}, val_options={"count": 1, "seed": 1000, **SMALL},
                       extra_train=[extra], train_weight=0.5, flip=0.0)
    train, _ = dm.build_datasets()
    names = dataset_names(train)
    assert len(names) == 1 + 6  # half of the 2 first-source frames, 3 x the 2 extra ones
    assert sum(n == dataset_names(train)[-1] for n in names) == 3


def test_a_bad_source_weight_is_refused_by_the_data_module():
    with pytest.raises(InputError, match=r"^extra_train\[0\]\.weight: expected a number in \(0, 100\]"):
        CRFDataModule(extra_train=[{"layout": "synthetic", "weight": 0}])
    with pytest.raises(InputError, match=r"^train_weight: expected a number in \(0, 100\]"):
        CRFDataModule(train_weight=-2)


@pytest.mark.kitti
def test_annotated_frames_train_beside_the_scans(kitti_root):
    dm = CRFDataModule(layout="annotated", root=str(kitti_root / "annotated"), train_weight=2,
                       val_layout="val_selection", val_root=str(kitti_root / "depth_selection" / "val_selection_cropped"),
                       extra_train=[{"layout": "raw", "root": str(kitti_root / "stereo"),
                                     "options": {"holdout": "fraction", "holdout_fraction": 0.2, "seed": 0}}])
    train, val = dm.build_datasets()
    names = dataset_names(train)
    assert len(names) == 2 * 11 + 3 and sum("drive_0048" in n for n in names) == 3
    assert not set(names) & set(dataset_names(val))  # the annotated frames are not the official ones
