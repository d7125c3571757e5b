"""Tests for KittiRawScans, input and target held out of one scan (crfdepth/data/kitti/raw_scans.py)."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from crfdepth.data.kitti import KittiRawScans
from crfdepth.data.kitti.raw_scans import remove_see_through
from crfdepth.errors import InputError
from crfdepth.geometry import projection
from crfdepth.io.calibration import read_object_calibration, read_raw_calibration
from crfdepth.io.kitti import read_velodyne
from crfdepth.potentials.occlusion import see_through_mask

DRIVE = "2011_09_26_drive_0001_sync"


@pytest.mark.kitti
def test_raw_scans_fraction_holdout_partitions_the_projection(kitti_root, check_sample):
    # Uncleaned targets: input and target pixels together are the whole projection.
    ds = KittiRawScans(kitti_root / "raw", layout="raw", holdout="fraction", holdout_fraction=0.2,
                       seed=0, transform=None, clean_target=False)
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


def test_remove_see_through_drops_a_leaked_target_and_keeps_a_slanted_road():
    """A hand-built scan: a box at 8 m before a wall at 25 m, a background return leaked
    1 px inside the box (between its returns), and a road 1.65 m below the camera
    (f = 720 px, principal row 40) on scan rows 5 px apart, 59 m to 22 m."""
    full = np.zeros((100, 60), np.float32)
    full[0:36:5, 0:60:2] = 25.0                        # wall
    full[5:31:5, 20:41:2] = 8.0                        # box, rows 5-30, columns 20-40
    full[15, 21] = 25.0                                # leaked background between box returns
    rows = np.arange(60, 100, 5)
    full[rows[:, None], np.arange(0, 60, 2)[None, :]] = (720.0 * 1.65 / (rows - 40.0))[:, None]
    target = np.zeros_like(full)
    for r, c in ((15, 21), (70, 30), (85, 30), (20, 30), (0, 10)):  # leaked, road x2, box, wall
        target[r, c] = full[r, c]
    before = target.copy()
    cleaned = remove_see_through(target, full)
    np.testing.assert_array_equal(target, before)       # input untouched
    assert cleaned[15, 21] == 0.0                        # the leaked return is gone
    for r, c in ((70, 30), (85, 30), (20, 30), (0, 10)):
        assert cleaned[r, c] == full[r, c]              # road, box and wall stay
    assert full[65, 30] - full[70, 30] > 5.0            # metres between road rings (47.5 / 39.6 m)


@pytest.mark.kitti
@pytest.mark.parametrize("holdout", ["fraction", "rings"])
def test_clean_target_drops_only_see_through_target_pixels(kitti_root, holdout):
    raw = KittiRawScans(kitti_root / "raw", holdout=holdout, transform=None, clean_target=False)
    clean = KittiRawScans(kitti_root / "raw", holdout=holdout, transform=None)
    assert clean.clean_target  # the default
    calib = read_raw_calibration(kitti_root / "raw" / "2011_09_26", camera=2)
    shares = []
    for i in (0, 7):  # drive 0001 frame 5, drive 0060 frame 36
        a, b = raw[i], clean[i]
        assert torch.equal(a.sparse, b.sparse)                      # the input is never cleaned
        assert not ((b.target > 0) & (a.target == 0)).any()         # nothing added
        kept = b.target > 0
        assert torch.equal(b.target[kept], a.target[kept])          # kept values unchanged
        drive, frame = raw.names[i].rsplit("_", 3)[0], raw.names[i].split("_")[-3]
        points = read_velodyne(kitti_root / "raw" / "2011_09_26" / drive / "velodyne_points" / "data" / f"{frame}.bin")
        full = torch.from_numpy(projection.project_velodyne(points, calib, (375, 1242)))[None]
        removed = (a.target > 0) & (b.target == 0)
        assert torch.equal(removed, see_through_mask(full[None])[0] & (a.target > 0))  # exactly the flagged ones
        shares.append(int(removed.sum()) / int((a.target > 0).sum()))
    # Drive 0001 frame 5 has few occluders, drive 0060 frame 36 many (module docstring).
    assert 0.002 < shares[0] < 0.015 and 0.02 < shares[1] < 0.06, shares


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
def test_raw_scans_drop_rings_holds_out_a_quarter_between_the_input_lines(kitti_root, check_sample):
    ds = KittiRawScans(kitti_root / "raw", layout="raw", holdout="drop_rings", drop_every_ring=4)
    s = ds[0]
    check_sample(s)
    n_in, n_tgt = int((s.sparse > 0).sum()), int((s.target > 0).sum())
    assert int(((s.sparse > 0) & (s.target > 0)).sum()) == 0
    assert 0.12 < n_tgt / (n_in + n_tgt) < 0.27                # 16 of 64 beams, less occluded pixels
    points = read_velodyne(kitti_root / "raw" / "2011_09_26" / DRIVE / "velodyne_points" / "data" / "0000000005.bin")
    inp, held = ds.split_points(points, ds.names[0])
    assert not (inp & held).any() and (inp | held).all()
    assert held.mean() == pytest.approx(0.25, abs=0.03)
    assert (projection.recover_rings(points)[held] % 4 == 0).all()   # targets are whole rings


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
        ({"holdout": "beams"}, "holdout: expected 'fraction', 'rings' or 'drop_rings', got 'beams'"),
        ({"holdout_fraction": 1.0}, r"holdout_fraction: expected a value in \(0, 1\), got 1.0"),
        ({"keep_every_ring": 1}, "keep_every_ring: expected an integer >= 2, got 1"),
        ({"drop_every_ring": 2.5}, "drop_every_ring: expected an integer >= 2, got 2.5"),
        ({"keep_fraction": 0.0}, r"keep_fraction: expected a value in \(0, 1\], got 0.0"),
        ({"seed": -1}, "seed: expected a non-negative integer, got -1"),
        ({"camera": 0}, "camera: expected 2 or 3 \\(KITTI colour cameras\\), got 0"),
        ({"clean_target": "yes"}, "clean_target: expected True or False, got 'yes'"),
    ],
)
def test_bad_options_name_the_argument(tmp_path, kwargs, message):
    with pytest.raises(InputError, match=message):
        KittiRawScans(tmp_path, **kwargs)
