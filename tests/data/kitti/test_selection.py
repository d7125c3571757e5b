"""Tests for the depth_selection folders (crfdepth/data/kitti/selection.py)."""

from __future__ import annotations

import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch
from torch.utils.data import DataLoader

from crfdepth.data import open_completion_folder as from_data
from crfdepth.data.kitti import KittiTestCompletion, KittiValSelection, open_completion_folder
from crfdepth.data.sample import collate_samples
from crfdepth.data.transforms import HorizontalFlip
from crfdepth.errors import InputError
from crfdepth.io.calibration import read_raw_calibration
from crfdepth.io.kitti import read_intrinsics

DRIVE = "2011_09_26_drive_0001_sync"
VAL_NAMES = [f"{DRIVE}_velodyne_raw_0000000005_image_02", f"{DRIVE}_velodyne_raw_0000000005_image_03"]


@pytest.mark.kitti
def test_val_selection_loads_with_file_intrinsics(val_selection, kitti_root, check_sample):
    assert len(val_selection) == 2
    s = val_selection[0]
    check_sample(s)
    assert s.name == VAL_NAMES[0] and s.has_target
    K_file = read_intrinsics(kitti_root / "depth_selection" / "val_selection_cropped" / "intrinsics"
                             / f"{DRIVE}_image_0000000005_image_02.txt")
    np.testing.assert_allclose(s.K.numpy(), K_file, atol=1e-4)
    K_raw = read_raw_calibration(kitti_root / "raw" / "2011_09_26", camera=2).K
    np.testing.assert_allclose(K_file[:2, 2], K_raw[:2, 2] - [13, 23], atol=1e-6)
    # The parent folder is accepted too.
    assert KittiValSelection(kitti_root / "depth_selection").names == VAL_NAMES


@pytest.mark.kitti
def test_flip_twice_on_real_frame(val_selection):
    s = val_selection[0]
    flip = HorizontalFlip(p=1.0)
    once = flip(s)
    assert once.K[0, 2].item() == pytest.approx(1215 - s.K[0, 2].item(), abs=1e-3)
    assert torch.equal(once.sparse[0, :, 0], s.sparse[0, :, 1215])
    twice = flip(once)
    assert all(torch.equal(getattr(twice, f), getattr(s, f)) for f in ("image", "sparse", "target", "K"))


def make_test_layout(kitti_root: Path, dest: Path) -> Path:
    """A fake test_depth_completion_anonymous folder: val_selection files under anonymous names."""
    val = kitti_root / "depth_selection" / "val_selection_cropped"
    root = dest / "depth_selection" / "test_depth_completion_anonymous"
    for sub in ("image", "velodyne_raw", "intrinsics"):
        (root / sub).mkdir(parents=True)
    for n, camera in enumerate(("image_02", "image_03")):
        anon = f"{n:010d}"
        shutil.copy(val / "image" / f"{DRIVE}_image_0000000005_{camera}.png", root / "image" / f"{anon}.png")
        shutil.copy(val / "velodyne_raw" / f"{DRIVE}_velodyne_raw_0000000005_{camera}.png",
                    root / "velodyne_raw" / f"{anon}.png")
        shutil.copy(val / "intrinsics" / f"{DRIVE}_image_0000000005_{camera}.txt",
                    root / "intrinsics" / f"{anon}.txt")
    return root


@pytest.mark.kitti
def test_test_completion_has_no_target(kitti_root, tmp_path, val_selection, check_sample):
    root = make_test_layout(kitti_root, tmp_path)
    test = KittiTestCompletion(root)
    assert test.names == ["0000000000", "0000000001"]
    assert KittiTestCompletion(root.parent).names == test.names
    s = test[1]
    check_sample(s)
    assert not s.has_target and int((s.target != 0).sum()) == 0
    reference = val_selection[1]
    assert torch.equal(s.sparse, reference.sparse) and torch.equal(s.image, reference.image)
    torch.testing.assert_close(s.K, reference.K, atol=0, rtol=0)
    batch = next(iter(DataLoader(test, batch_size=2, collate_fn=collate_samples)))
    assert batch.image.shape == (2, 3, 352, 1216) and batch.has_target.tolist() == [False, False]
    assert batch.names == ["0000000000", "0000000001"]


def copy_val_selection(kitti_root: Path, dest: Path) -> Path:
    root = dest / "val_selection_cropped"
    shutil.copytree(kitti_root / "depth_selection" / "val_selection_cropped", root)
    return root


@pytest.mark.kitti
def test_missing_target_file_names_the_path(kitti_root, tmp_path):
    root = copy_val_selection(kitti_root, tmp_path)
    missing = root / "groundtruth_depth" / f"{DRIVE}_groundtruth_depth_0000000005_image_03.png"
    missing.unlink()
    with pytest.raises(InputError, match=f"missing ground truth .* expected {missing}"):
        KittiValSelection(root)


@pytest.mark.kitti
def test_rgb_and_depth_of_different_sizes_names_both_files(kitti_root, tmp_path):
    root = copy_val_selection(kitti_root, tmp_path)
    image = root / "image" / f"{DRIVE}_image_0000000005_image_02.png"
    rgb = cv2.imread(str(image))
    cv2.imwrite(str(image), rgb[:, :1200])
    ds = KittiValSelection(root)
    sparse = root / "velodyne_raw" / f"{DRIVE}_velodyne_raw_0000000005_image_02.png"
    with pytest.raises(InputError) as info:
        ds[0]
    message = str(info.value)
    assert str(image) in message and str(sparse) in message
    assert "352x1200" in message and "352x1216" in message


@pytest.mark.kitti
def test_open_completion_folder_picks_the_layout(kitti_root, tmp_path):
    val = kitti_root / "depth_selection" / "val_selection_cropped"
    for root in (val, val.parent):  # the folder itself or its parent depth_selection
        ds = open_completion_folder(root)
        assert type(ds) is KittiValSelection and ds.names == VAL_NAMES and ds.root == val
    test_root = make_test_layout(kitti_root, tmp_path)
    for root in (test_root, test_root.parent):
        ds = open_completion_folder(root)
        assert type(ds) is KittiTestCompletion and ds.names == ["0000000000", "0000000001"]
    flip = HorizontalFlip(p=1.0)
    assert open_completion_folder(val, transform=flip).transform is flip
    assert open_completion_folder(val).transform is None


def test_open_completion_folder_errors(tmp_path):
    with pytest.raises(FileNotFoundError, match=str(tmp_path / "nowhere")):
        open_completion_folder(tmp_path / "nowhere")
    # Neither layout: named as the test layout (the one without ground truth) would be.
    with pytest.raises(InputError, match=f"KittiTestCompletion: expected {tmp_path}/velodyne_raw"):
        open_completion_folder(tmp_path)
    (tmp_path / "groundtruth_depth").mkdir()
    with pytest.raises(InputError, match=f"KittiValSelection: expected {tmp_path}/velodyne_raw"):
        open_completion_folder(tmp_path)


def test_open_completion_folder_is_exported():
    assert from_data is open_completion_folder
