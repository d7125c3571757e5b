"""Tests for the shared loading path and folder checks (crfdepth/data/kitti/loading.py)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch

from crfdepth.data.kitti import KittiDepthCompletion, KittiRawScans, KittiTestCompletion, KittiValSelection
from crfdepth.data.kitti.loading import load_sample
from crfdepth.data.transforms import HorizontalFlip
from crfdepth.errors import InputError

DRIVE = "2011_09_26_drive_0001_sync"
K = np.array([[700.0, 0.0, 30.0], [0.0, 700.0, 10.0], [0.0, 0.0, 1.0]])


def test_load_sample_converts_to_the_library_convention():
    rgb = np.arange(4 * 6 * 3, dtype=np.uint8).reshape(4, 6, 3)
    sparse = np.zeros((4, 6), dtype=np.float32)
    sparse[1, 2] = 12.5
    target = np.full((4, 6), 7.0, dtype=np.float32)
    s = load_sample(rgb, sparse, target, K, "frame", {})
    assert s.name == "frame" and s.has_target and s.size == (4, 6)
    assert s.image.dtype == torch.float32 and s.image.shape == (3, 4, 6)
    torch.testing.assert_close(s.image, torch.from_numpy(rgb.transpose(2, 0, 1).astype(np.float32)) / 255.0)
    assert s.sparse.shape == (1, 4, 6) and s.sparse[0, 1, 2].item() == 12.5 and int((s.sparse > 0).sum()) == 1
    assert torch.equal(s.target, torch.full((1, 4, 6), 7.0))
    assert s.K.dtype == torch.float32 and torch.equal(s.K, torch.from_numpy(K).float())


def test_load_sample_without_target_and_with_transform():
    rgb = np.zeros((4, 6, 3), dtype=np.uint8)
    sparse = np.ones((4, 6), dtype=np.float32)
    s = load_sample(rgb, sparse, None, K, "t", {})
    assert not s.has_target and torch.equal(s.target, torch.zeros(1, 4, 6))
    flipped = load_sample(rgb, sparse, None, K, "t", {}, transform=HorizontalFlip(p=1.0))
    assert flipped.K[0, 2].item() == pytest.approx(6 - 1 - 30.0)


def test_load_sample_names_the_files_of_different_sizes():
    files = {"image": Path("a/rgb.png"), "sparse": Path("a/sparse.png"), "target": Path("a/gt.png")}
    rgb = np.zeros((4, 6, 3), dtype=np.uint8)
    with pytest.raises(InputError, match=r"f: RGB and depth sizes differ: image a/rgb.png is 4x6 \(HxW\) "
                                         r"but sparse a/sparse.png is 4x5"):
        load_sample(rgb, np.zeros((4, 5), np.float32), None, K, "f", files)
    with pytest.raises(InputError, match="but target a/gt.png is 3x6"):
        load_sample(rgb, np.zeros((4, 6), np.float32), np.zeros((3, 6), np.float32), K, "f", files)


def test_root_that_is_a_file(tmp_path):
    file = tmp_path / "file.txt"
    file.write_text("")
    with pytest.raises(InputError, match=f"root: expected a directory, got a file: {file}"):
        KittiValSelection(file)


def test_missing_root_raises_file_not_found(tmp_path):
    missing = tmp_path / "nowhere"
    for make in (lambda: KittiDepthCompletion(missing, raw_root=tmp_path),
                 lambda: KittiValSelection(missing),
                 lambda: KittiTestCompletion(missing),
                 lambda: KittiRawScans(missing)):
        with pytest.raises(FileNotFoundError, match=str(missing)):
            make()


def test_root_of_wrong_layout_names_expected_folder(tmp_path):
    with pytest.raises(InputError, match=f"expected {tmp_path}/data_depth_velodyne/train"):
        KittiDepthCompletion(tmp_path, raw_root=tmp_path)
    with pytest.raises(InputError, match=f"expected {tmp_path}/velodyne_raw"):
        KittiValSelection(tmp_path)
    with pytest.raises(InputError, match=f"expected {tmp_path}/velodyne"):
        KittiRawScans(tmp_path, layout="object")
    with pytest.raises(InputError, match=r"expected .*/<date> folders"):
        KittiRawScans(tmp_path, layout="raw")
    with pytest.raises(InputError, match="split: expected 'train' or 'val'"):
        KittiDepthCompletion(tmp_path, split="test", raw_root=tmp_path)


def test_zero_frames_is_an_error_not_an_empty_dataset(tmp_path):
    (tmp_path / "data_depth_velodyne" / "val").mkdir(parents=True)
    (tmp_path / "data_depth_annotated" / "val").mkdir(parents=True)
    with pytest.raises(InputError, match=f"KittiDepthCompletion: found no frames under {tmp_path}"):
        KittiDepthCompletion(tmp_path, split="val", raw_root=tmp_path)
    for sub in ("velodyne_raw", "image", "intrinsics", "groundtruth_depth"):
        (tmp_path / sub).mkdir()
    with pytest.raises(InputError, match=f"KittiValSelection: found no frames under {tmp_path}"):
        KittiValSelection(tmp_path)
    (tmp_path / "2011_09_26" / DRIVE).mkdir(parents=True)
    with pytest.raises(InputError, match=rf"KittiRawScans\(raw\): found no frames under {tmp_path}"):
        KittiRawScans(tmp_path)
