"""Tests for KittiDepthCompletion, the official layout (crfdepth/data/kitti/completion.py)."""

from __future__ import annotations

import shutil

import numpy as np
import pytest
import torch

from crfdepth.data.kitti import KittiDepthCompletion
from crfdepth.errors import InputError
from crfdepth.io.calibration import read_raw_calibration

DRIVE = "2011_09_26_drive_0001_sync"
VAL_NAMES = [f"{DRIVE}_velodyne_raw_0000000005_image_02", f"{DRIVE}_velodyne_raw_0000000005_image_03"]


@pytest.mark.kitti
def test_depth_completion_loads_cropped_frames(completion, kitti_root, check_sample):
    assert len(completion) == 2
    assert completion.names == VAL_NAMES
    for index, camera in enumerate((2, 3)):
        s = completion[index]
        check_sample(s)
        assert s.has_target
        sparse_share = (s.sparse > 0).float().mean().item()
        target_share = (s.target > 0).float().mean().item()
        assert 0.03 < sparse_share < 0.06      # velodyne_raw ~4% of the crop
        assert 0.15 < target_share < 0.25      # annotated ground truth ~19-21%
        K = read_raw_calibration(kitti_root / "raw" / "2011_09_26", camera=camera).K
        np.testing.assert_allclose(s.K.numpy(), K - [[0, 0, 13], [0, 0, 23], [0, 0, 0]], atol=1e-4)


@pytest.mark.kitti
def test_depth_completion_full_frame_and_camera_choice(kitti_root, check_sample):
    full = KittiDepthCompletion(kitti_root / "depth_completion", split="train", camera="image_03",
                                raw_root=kitti_root / "raw", transform=None)
    assert full.names == VAL_NAMES[1:]
    s = full[0]
    check_sample(s, size=(375, 1242))
    K = read_raw_calibration(kitti_root / "raw" / "2011_09_26", camera=3).K
    np.testing.assert_allclose(s.K.numpy(), K, atol=1e-4)  # uncropped: K is P_rect_03[:, :3]
    # raw_root=None: the sibling folder <root>/../raw, as in the shared data.
    assert KittiDepthCompletion(kitti_root / "depth_completion").raw_root == kitti_root / "raw"


@pytest.mark.kitti
def test_official_crop_equals_val_selection_pixel_for_pixel(completion, val_selection):
    """Same frames, two layouts: the bottom-centre crop reproduces val_selection_cropped."""
    assert val_selection.names == completion.names
    for a, b in zip(completion, val_selection):
        for field in ("image", "sparse", "target"):
            assert torch.equal(getattr(a, field), getattr(b, field)), field
        torch.testing.assert_close(a.K, b.K, atol=1e-4, rtol=0)


@pytest.mark.kitti
def test_missing_annotation_names_the_path(kitti_root, tmp_path):
    # Official layout: velodyne_raw present, the annotated copy lacks the frame.
    official = tmp_path / "depth_completion"
    src = kitti_root / "depth_completion" / "data_depth_velodyne"
    shutil.copytree(src, official / "data_depth_velodyne")
    (official / "data_depth_annotated" / "train").mkdir(parents=True)
    expected = (official / "data_depth_annotated" / "train" / DRIVE / "proj_depth" / "groundtruth"
                / "image_02" / "0000000005.png")
    with pytest.raises(InputError, match=f"missing ground truth .* expected {expected}"):
        KittiDepthCompletion(official, raw_root=kitti_root / "raw")


def test_drive_folders_must_be_named_like_kitti(tmp_path):
    (tmp_path / "data_depth_velodyne" / "train" / "not_a_drive").mkdir(parents=True)
    (tmp_path / "data_depth_annotated" / "train").mkdir(parents=True)
    with pytest.raises(InputError, match=r"expected drive folders named <date>_drive_<NNNN>_sync .* got 'not_a_drive'"):
        KittiDepthCompletion(tmp_path, raw_root=tmp_path)
    with pytest.raises(InputError, match="camera: expected 'image_02', 'image_03' or both, got 'image_01'"):
        KittiDepthCompletion(tmp_path, camera="image_01", raw_root=tmp_path)
