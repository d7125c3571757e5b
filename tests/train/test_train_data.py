"""CRFDataModule: datasets per layout, disjoint train/validation splits, flip, loaders."""

from __future__ import annotations

import pytest
import torch
import yaml

from crfdepth.data import Batch, build_dataset
from crfdepth.errors import InputError
from train.data import CRFDataModule, TransformedDataset, dataset_names

SMALL = {"height": 48, "width": 160}


def test_synthetic_train_and_val_use_disjoint_seeds():
    dm = CRFDataModule(train_options={"count": 3, **SMALL}, flip=0.0)
    dm.setup("fit")
    assert dataset_names(dm.train_set) == ["synthetic-seed0", "synthetic-seed1", "synthetic-seed2"]
    assert dataset_names(dm.val_set)[0] == "synthetic-seed1000"
    assert len(dm.val_set) == 3


def test_synthetic_overlapping_seeds_are_refused():
    dm = CRFDataModule(train_options={"count": 4, "seed": 0}, val_options={"count": 2, "seed": 3})
    with pytest.raises(InputError, match=r"1 frame\(s\) are in both.*synthetic-seed3"):
        dm.setup("fit")


def test_train_frames_are_flipped_validation_frames_are_not():
    dm = CRFDataModule(train_options={"count": 1, **SMALL}, val_options={"count": 1, "seed": 1000, **SMALL},
                       flip=1.0, batch_size=1)
    dm.setup("fit")
    assert isinstance(dm.train_set, TransformedDataset)
    flipped, original = dm.train_set[0], dm.train_set.dataset[0]
    assert torch.equal(flipped.image, original.image.flip(-1))
    assert torch.equal(flipped.sparse, original.sparse.flip(-1))
    assert flipped.K[0, 2].item() == pytest.approx(SMALL["width"] - 1 - original.K[0, 2].item())
    val = dm.val_set[0]
    assert torch.equal(val.image, build_dataset("synthetic", count=1, seed=1000, **SMALL)[0].image)


def test_train_frames_are_cropped_and_thinned_validation_frames_are_not():
    dm = CRFDataModule(train_options={"count": 1, **SMALL}, val_options={"count": 1, "seed": 1000, **SMALL},
                       flip=0.0, crop=[32, 96], thin=[0.5, 0.5])
    dm.setup("fit")
    out, original = dm.train_set[0], dm.train_set.dataset[0]
    assert out.size == (32, 96) and dm.val_set[0].size == (SMALL["height"], SMALL["width"])
    left = round(original.K[0, 2].item() - out.K[0, 2].item())
    top = round(original.K[1, 2].item() - out.K[1, 2].item())
    window = original.sparse[:, top:top + 32, left:left + 96]
    assert torch.equal(out.image, original.image[:, top:top + 32, left:left + 96])
    share = (out.sparse > 0).sum().item() / (window > 0).sum().item()
    assert 0.35 < share < 0.65


def test_loaders_yield_batches():
    dm = CRFDataModule(train_options={"count": 2, **SMALL}, val_options={"count": 2, "seed": 1000, **SMALL},
                       batch_size=2, val_batch_size=1)
    dm.setup("fit")
    batch = next(iter(dm.train_dataloader()))
    assert isinstance(batch, Batch) and batch.image.shape == (2, 3, SMALL["height"], SMALL["width"])
    assert len(list(dm.val_dataloader())) == 2


def test_raw_split_by_drive_holds_out_whole_drives(kitti_root):
    dm = CRFDataModule(layout="raw", root=str(kitti_root / "raw"), val_names_contain="drive_0001")
    dm.setup("fit")
    train, val = dataset_names(dm.train_set), dataset_names(dm.val_set)
    assert val == ["2011_09_26_drive_0001_sync_0000000005_image_02"]
    assert len(train) == 13 and all("drive_0060" in n for n in train)


def test_raw_split_by_fraction_takes_the_last_frames(kitti_root):
    dm = CRFDataModule(layout="raw", root=str(kitti_root / "raw"), val_fraction=0.25)
    dm.setup("fit")
    names = build_dataset("raw", kitti_root / "raw").names
    assert dataset_names(dm.val_set) == names[-4:]  # ceil(0.25 * 14)
    assert dataset_names(dm.train_set) == names[:-4]


def test_kitti_raw_config_never_validates_on_training_frames(kitti_root, configs):
    data = yaml.safe_load((configs / "kitti_raw.yaml").read_text())["data"]
    data["root"] = str(kitti_root / "raw")
    dm = CRFDataModule(**data)
    dm.setup("fit")
    train, val = set(dataset_names(dm.train_set)), set(dataset_names(dm.val_set))
    assert val and train and not train & val
    drives = {n.split("_sync")[0] for n in train}
    assert not any(d in v for d in drives for v in val)  # held out by drive


def test_raw_without_a_split_is_refused(kitti_root):
    dm = CRFDataModule(layout="raw", root=str(kitti_root / "raw"))
    with pytest.raises(InputError, match="in both the training and the validation set"):
        dm.setup("fit")


def test_empty_root_names_root_and_layout(tmp_path):
    dm = CRFDataModule(layout="raw", root=str(tmp_path), val_fraction=0.5)
    with pytest.raises(InputError) as err:
        dm.setup("fit")
    assert str(tmp_path) in str(err.value) and "'raw'" in str(err.value)
    missing = tmp_path / "nope"
    dm = CRFDataModule(layout="val_selection", root=str(missing))
    with pytest.raises(InputError) as err:
        dm.setup("fit")
    assert str(missing) in str(err.value) and "'val_selection'" in str(err.value)


def test_split_that_leaves_no_validation_frame(kitti_root):
    dm = CRFDataModule(layout="raw", root=str(kitti_root / "raw"), val_names_contain="drive_9999")
    with pytest.raises(InputError, match="0 validation frames"):
        dm.setup("fit")


@pytest.mark.parametrize("kwargs, match", [
    ({"layout": "kitti"}, "layout: expected one of"),
    ({"val_names_contain": "a", "val_fraction": 0.5}, "at most one"),
    ({"val_fraction": 1.5}, r"val_fraction: expected a value in \(0, 1\)"),
    ({"flip": 2.0}, "flip"),
    ({"crop": [352]}, r"crop: expected \[height, width\], two integers > 0, got \[352\]"),
    ({"crop": [0, 10]}, "crop: expected"),
    ({"thin": [0.0, 1.0]}, r"thin: expected \[low, high\] with 0 < low <= high <= 1, got \[0.0, 1.0\]"),
    ({"batch_size": 0}, "batch_size"),
])
def test_bad_arguments(kwargs, match):
    with pytest.raises(InputError, match=match):
        CRFDataModule(**kwargs)


def test_bad_dataset_option_is_named():
    dm = CRFDataModule(train_options={"cuont": 2})
    with pytest.raises(InputError, match="cuont"):
        dm.setup("fit")


def test_same_frames_in_two_layouts_are_refused(kitti_root):
    # The shared depth-completion frames are the val_selection frames, cropped.
    dm = CRFDataModule(layout="depth_completion", root=str(kitti_root / "depth_completion"),
                       val_layout="val_selection", val_root=str(kitti_root / "depth_selection"))
    with pytest.raises(InputError, match=r"2 frame\(s\) are in both"):
        dm.setup("fit")


def test_kitti_weights_config_trains_on_48_frames_and_never_on_drive_0001(kitti_root, configs):
    data = yaml.safe_load((configs / "kitti_weights.yaml").read_text())["data"]
    for source in [data, *data["extra_train"]]:  # config paths are relative to the repository root
        source["root"] = source["root"].replace("../shared/data/kitti", str(kitti_root))
    dm = CRFDataModule(**{**data, "flip": 0.0, "crop": None, "thin": None})
    dm.setup("fit")
    train, val = dataset_names(dm.train_set), dataset_names(dm.val_set)
    assert val == ["2011_09_26_drive_0001_sync_0000000005_image_02"]
    assert len(train) == 48 and not any("drive_0001" in n for n in train)
    assert sum("drive_0060" in n for n in train) == 26 and len(set(train)) == 24  # two hold-outs per scan
    # The second copy of a scan has its 16-beam input: fewer LiDAR pixels than the 80% one.
    first, second = dm.train_set[0], dm.train_set[13]
    assert first.name == second.name
    assert (second.sparse > 0).sum() < 0.5 * (first.sparse > 0).sum()


def test_extra_train_names_contain_keeps_matching_frames(kitti_root):
    dm = CRFDataModule(layout="raw", root=str(kitti_root / "raw"), val_names_contain="drive_0001", flip=0.0,
                       extra_train=[{"layout": "object", "root": str(kitti_root / "object" / "training"),
                                     "names_contain": ["000010", "000011"]}])
    dm.setup("fit")
    assert dataset_names(dm.train_set)[13:] == ["000010", "000011"]


@pytest.mark.parametrize("extra, match", [
    ("raw", r"extra_train\[0\]: expected a mapping"),
    ({"layout": "lidar"}, r"extra_train\[0\].layout: expected one of"),
    ({"layout": "raw", "folder": "x"}, r"extra_train\[0\]: expected keys.*folder"),
    ({"layout": "raw", "options": [1]}, r"extra_train\[0\].options: expected a mapping"),
    ({"layout": "raw", "names_contain": 5}, r"extra_train\[0\].names_contain: expected a string"),
])
def test_bad_extra_train_is_named(extra, match):
    with pytest.raises(InputError, match=match):
        CRFDataModule(extra_train=[extra])


def test_extra_train_that_keeps_nothing_is_named(kitti_root):
    dm = CRFDataModule(layout="raw", root=str(kitti_root / "raw"), val_names_contain="drive_0001",
                       extra_train=[{"layout": "raw", "root": str(kitti_root / "raw"), "names_contain": "drive_0001"}])
    with pytest.raises(InputError, match=r"extra_train\[0\]: none of the 14 frames"):
        dm.setup("fit")
