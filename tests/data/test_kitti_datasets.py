"""Tests for the KITTI datasets (crfdepth.data.kitti) on the shared real frames."""

from __future__ import annotations

import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch
from torch.utils.data import DataLoader

from crfdepth import projection
from crfdepth.data.kitti import KittiDepthCompletion, KittiRawScans, KittiTestCompletion, KittiValSelection
from crfdepth.data.sample import Sample, collate_samples
from crfdepth.data.transforms import HorizontalFlip
from crfdepth.errors import InputError
from crfdepth.io.kitti import read_intrinsics, read_object_calibration, read_raw_calibration, read_velodyne

DRIVE = "2011_09_26_drive_0001_sync"
VAL_NAMES = [f"{DRIVE}_velodyne_raw_0000000005_image_02", f"{DRIVE}_velodyne_raw_0000000005_image_03"]


@pytest.fixture(scope="module")
def completion(kitti_root) -> KittiDepthCompletion:
    return KittiDepthCompletion(kitti_root / "depth_completion", raw_root=kitti_root / "raw")


@pytest.fixture(scope="module")
def val_selection(kitti_root) -> KittiValSelection:
    return KittiValSelection(kitti_root / "depth_selection" / "val_selection_cropped")


def check_sample(s: Sample, size=(352, 1216)) -> None:
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


# --------------------------------------------------------------------------- official layout


@pytest.mark.kitti
def test_depth_completion_loads_cropped_frames(completion, kitti_root):
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
def test_depth_completion_full_frame_and_camera_choice(kitti_root):
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


# --------------------------------------------------------------------------- depth_selection


@pytest.mark.kitti
def test_val_selection_loads_with_file_intrinsics(val_selection, kitti_root):
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
def test_test_completion_has_no_target(kitti_root, tmp_path, val_selection):
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


# --------------------------------------------------------------------------- Velodyne scans


@pytest.mark.kitti
def test_raw_scans_fraction_holdout_partitions_the_projection(kitti_root):
    ds = KittiRawScans(kitti_root / "raw", layout="raw", holdout="fraction", holdout_fraction=0.2,
                       seed=0, transform=None)
    assert len(ds) == 14  # drive 0001 (1 frame) + drive 0060 (13 frames)
    assert ds.names[0] == f"{DRIVE}_0000000005_image_02"
    assert ds.names[1] == "2011_09_26_drive_0060_sync_0000000000_image_02"
    s = ds[0]
    check_sample(s, size=(375, 1242))
    calib = read_raw_calibration(kitti_root / "raw" / "2011_09_26", camera=2)
    np.testing.assert_allclose(s.K.numpy(), calib.K, atol=1e-4)
    points = read_velodyne(kitti_root / "raw" / "2011_09_26" / DRIVE / "velodyne_points" / "data" / "0000000005.bin")
    full = int((projection.project_velodyne(points, calib, (375, 1242)) > 0).sum())
    assert full == 19137  # README: 19,137 in-image pixels
    n_in, n_tgt = int((s.sparse > 0).sum()), int((s.target > 0).sum())
    assert int(((s.sparse > 0) & (s.target > 0)).sum()) == 0   # no leakage
    assert n_in + n_tgt == full                                # together: the whole projection
    assert 0.75 < n_in / full < 0.85                           # ~80% of points -> ~80% of pixels
    again = ds[0]
    assert torch.equal(again.sparse, s.sparse) and torch.equal(again.target, s.target)
    other_seed = KittiRawScans(kitti_root / "raw", seed=1, transform=None)[0]
    assert not torch.equal(other_seed.sparse, s.sparse)


@pytest.mark.kitti
def test_raw_scans_rings_holdout_keeps_a_quarter(kitti_root):
    ds = KittiRawScans(kitti_root / "raw", layout="raw", holdout="rings", keep_every_ring=4)
    s = ds[0]
    check_sample(s)
    n_in, n_tgt = int((s.sparse > 0).sum()), int((s.target > 0).sum())
    assert int(((s.sparse > 0) & (s.target > 0)).sum()) == 0
    assert 0.2 < n_in / (n_in + n_tgt) < 0.3                   # 16 of 64 beams
    points = read_velodyne(kitti_root / "raw" / "2011_09_26" / DRIVE / "velodyne_points" / "data" / "0000000005.bin")
    inp, held = ds.split_points(points, ds.names[0])
    assert not (inp & held).any() and (inp | held).all()
    assert inp.mean() == pytest.approx(0.25, abs=0.03)
    # Input rows are whole rings: every kept point's ring is a multiple of 4.
    assert (projection.recover_rings(points)[inp] % 4 == 0).all()


@pytest.mark.kitti
def test_raw_scans_keep_fraction_thins_the_input_only(kitti_root):
    base = KittiRawScans(kitti_root / "raw", holdout="fraction", seed=0)
    thin = KittiRawScans(kitti_root / "raw", holdout="fraction", seed=0, keep_fraction=0.5)
    a, b = base[0], thin[0]
    assert torch.equal(a.target, b.target)                       # same held-out points
    assert not ((b.sparse > 0) & (b.target > 0)).any()
    ratio = int((b.sparse > 0).sum()) / int((a.sparse > 0).sum())
    assert 0.45 < ratio < 0.6  # half of the points; slightly more than half of the pixels


@pytest.mark.kitti
def test_object_layout_crop_follows_image_size(kitti_root):
    root = kitti_root / "object" / "training"
    ds = KittiRawScans(root, layout="object", holdout="rings")
    assert len(ds) == 11 and ds.names[:2] == ["000000", "000001"]
    s = ds[0]  # 000000 is 1224x370: crop offsets top = 18, left = 4
    check_sample(s)
    K = read_object_calibration(root / "calib" / "000000.txt", camera=2).K
    np.testing.assert_allclose(s.K.numpy(), K - [[0, 0, 4], [0, 0, 18], [0, 0, 0]], atol=1e-4)
    assert not ((s.sparse > 0) & (s.target > 0)).any()


# --------------------------------------------------------------------------- bad input


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

    # Official layout: velodyne_raw present, the annotated copy lacks the frame.
    official = tmp_path / "depth_completion"
    src = kitti_root / "depth_completion" / "data_depth_velodyne"
    shutil.copytree(src, official / "data_depth_velodyne")
    (official / "data_depth_annotated" / "train").mkdir(parents=True)
    expected = (official / "data_depth_annotated" / "train" / DRIVE / "proj_depth" / "groundtruth"
                / "image_02" / "0000000005.png")
    with pytest.raises(InputError, match=f"missing ground truth .* expected {expected}"):
        KittiDepthCompletion(official, raw_root=kitti_root / "raw")


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
