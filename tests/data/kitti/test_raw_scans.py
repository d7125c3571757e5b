"""Tests for KittiRawScans, input and target held out of one scan (crfdepth/data/kitti/raw_scans.py)."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from crfdepth import projection
from crfdepth.data.kitti import KittiRawScans
from crfdepth.errors import InputError
from crfdepth.io.calibration import read_object_calibration, read_raw_calibration
from crfdepth.io.kitti import read_velodyne

DRIVE = "2011_09_26_drive_0001_sync"


@pytest.mark.kitti
def test_raw_scans_fraction_holdout_partitions_the_projection(kitti_root, check_sample):
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
def test_raw_scans_rings_holdout_keeps_a_quarter(kitti_root, check_sample):
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
def test_object_layout_crop_follows_image_size(kitti_root, check_sample):
    root = kitti_root / "object" / "training"
    ds = KittiRawScans(root, layout="object", holdout="rings")
    assert len(ds) == 11 and ds.names[:2] == ["000000", "000001"]
    s = ds[0]  # 000000 is 1224x370: crop offsets top = 18, left = 4
    check_sample(s)
    K = read_object_calibration(root / "calib" / "000000.txt", camera=2).K
    np.testing.assert_allclose(s.K.numpy(), K - [[0, 0, 4], [0, 0, 18], [0, 0, 0]], atol=1e-4)
    assert not ((s.sparse > 0) & (s.target > 0)).any()


@pytest.mark.parametrize(
    "kwargs, message",
    [
        ({"layout": "velodyne"}, "layout: expected 'raw' or 'object', got 'velodyne'"),
        ({"holdout": "beams"}, "holdout: expected 'fraction' or 'rings', got 'beams'"),
        ({"holdout_fraction": 1.0}, r"holdout_fraction: expected a value in \(0, 1\), got 1.0"),
        ({"keep_every_ring": 1}, "keep_every_ring: expected an integer >= 2, got 1"),
        ({"keep_fraction": 0.0}, r"keep_fraction: expected a value in \(0, 1\], got 0.0"),
        ({"seed": -1}, "seed: expected a non-negative integer, got -1"),
        ({"camera": 0}, "camera: expected 2 or 3 \\(KITTI colour cameras\\), got 0"),
    ],
)
def test_bad_options_name_the_argument(tmp_path, kwargs, message):
    with pytest.raises(InputError, match=message):
        KittiRawScans(tmp_path, **kwargs)
