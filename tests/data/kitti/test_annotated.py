"""crfdepth.data.kitti.KittiAnnotated: KITTI's annotated frames with the input drawn from the annotation or the scan."""

from __future__ import annotations

import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch

from crfdepth.data import build_dataset
from crfdepth.data.kitti import KittiAnnotated
from crfdepth.data.kitti.annotated import HDL64_ELEVATIONS_DEG, ring_pixels
from crfdepth.errors import InputError
from crfdepth.io.calibration import read_raw_calibration

DRIVE = "2011_09_26_drive_0001_sync"


@pytest.fixture(scope="module")
def annotated(kitti_root) -> Path:
    return kitti_root / "annotated"


@pytest.mark.kitti
def test_share_input_leaves_the_target(annotated, check_sample):
    ds = build_dataset("annotated", annotated, seed=0)
    assert len(ds) == 11
    assert ds.names[0] == f"{DRIVE}_velodyne_raw_0000000006_image_02"  # the depth-completion name
    s = ds[0]
    check_sample(s)
    given, scored = s.sparse > 0, s.target > 0
    assert not (given & scored).any()  # no pixel both input and target
    share = given.sum().item() / (given | scored).sum().item()
    assert share == pytest.approx(0.22, abs=0.01)
    # a fixed seed draws the same input; another seed another one
    assert torch.equal(ds[0].sparse, s.sparse)
    assert not torch.equal(KittiAnnotated(annotated, seed=1)[0].sparse, s.sparse)


@pytest.mark.kitti
def test_rings_input_is_a_scan_pattern(annotated, kitti_root):
    full = KittiAnnotated(annotated, input_from="rings", seed=0)[3]
    sixteen = KittiAnnotated(annotated, input_from="rings", keep_every_ring=4, seed=0)[3]
    density = (full.sparse > 0).float().mean().item()
    # 64 rings give about the density of KITTI's own velodyne_raw maps (4.4% of the crop), 16 about a quarter
    official = build_dataset("depth_completion", kitti_root / "depth_completion")[0]
    assert density == pytest.approx((official.sparse > 0).float().mean().item(), rel=0.3)
    assert (sixteen.sparse > 0).sum() == pytest.approx(0.25 * (full.sparse > 0).sum().item(), rel=0.25)
    assert not ((full.sparse > 0) & (full.target > 0)).any()


@pytest.mark.kitti
def test_ring_pixels_lie_on_the_kept_rings(annotated):
    calib = read_raw_calibration(annotated / "raw" / "2011_09_26", camera=2)
    P = calib.P_rect
    # a wall 20 m ahead seen by every pixel: the ring pixels' elevations, recomputed, are on the kept rings
    target = np.full(tuple(calib.image_size), 20.0, np.float32)
    keep = ring_pixels(target, calib, keep_every_ring=8, offset=0)
    v, u = np.nonzero(keep)
    assert v.size > 1000
    d = 20.0
    z = d - P[2, 3]
    rect = np.stack([(u * d - P[0, 2] * z - P[0, 3]) / P[0, 0], (v * d - P[1, 2] * z - P[1, 3]) / P[1, 1],
                     np.full(u.shape, z), np.ones(u.shape)])
    velo = np.linalg.inv(calib.R_rect @ calib.T_velo_to_cam) @ rect
    elevation = np.degrees(np.arctan2(velo[2], np.hypot(velo[0], velo[1])))
    kept = HDL64_ELEVATIONS_DEG[::8]
    assert np.abs(elevation[:, None] - kept[None]).min(axis=1).max() <= np.degrees(0.5 / P[1, 1]) + 1e-9
    # a ring seen in the image crosses it as one line per column: at most a few rows per ring and column
    rows_per_column = keep.sum(axis=0)
    assert rows_per_column.max() <= 3 * len(kept)


@pytest.mark.kitti
def test_scan_input_from_the_depth_completion_root(kitti_root):
    ds = KittiAnnotated(kitti_root / "depth_completion", input_from="scan", camera="image_02")
    official = build_dataset("depth_completion", kitti_root / "depth_completion", camera="image_02")
    assert ds.names == official.names
    s, o = ds[0], official[0]
    assert torch.equal(s.sparse, o.sparse) and torch.equal(s.target, o.target)


def _fake_root(tmp_path: Path, kitti_root: Path, frames=("0000000006",)) -> Path:
    """A copy of one annotated frame of the shared data: root/{data_depth_annotated,raw}."""
    src = kitti_root / "annotated"
    root = tmp_path / "annotated"
    gt = root / "data_depth_annotated" / "train" / DRIVE / "proj_depth" / "groundtruth" / "image_02"
    img = root / "raw" / "2011_09_26" / DRIVE / "image_02" / "data"
    gt.mkdir(parents=True)
    img.mkdir(parents=True)
    for name in ("calib_cam_to_cam.txt", "calib_velo_to_cam.txt"):
        shutil.copy(src / "raw" / "2011_09_26" / name, root / "raw" / "2011_09_26" / name)
    for f in frames:
        shutil.copy(src / "data_depth_annotated" / "train" / DRIVE / "proj_depth" / "groundtruth" / "image_02" / f"{f}.png",
                    gt / f"{f}.png")
        shutil.copy(src / "raw" / "2011_09_26" / DRIVE / "image_02" / "data" / f"{f}.png", img / f"{f}.png")
    return root


@pytest.mark.kitti
def test_an_annotation_without_pixels_is_refused(tmp_path, kitti_root):
    root = _fake_root(tmp_path, kitti_root)
    png = next((root / "data_depth_annotated").rglob("*.png"))
    cv2.imwrite(str(png), np.zeros((375, 1242), np.uint16))
    with pytest.raises(InputError, match=r"^annotation: expected annotated pixels \(depth > 0\), got none in .*0000000006.png"):
        KittiAnnotated(root)[0]


@pytest.mark.kitti
def test_an_annotation_of_another_size_is_refused(tmp_path, kitti_root):
    root = _fake_root(tmp_path, kitti_root)
    png = next((root / "data_depth_annotated").rglob("*.png"))
    cv2.imwrite(str(png), np.full((370, 1224), 2560, np.uint16))
    with pytest.raises(InputError, match=r"RGB and annotation sizes differ: image .* is 375x1242 \(HxW\) but "
                                         r"annotation .* is 370x1224"):
        KittiAnnotated(root)[0]


@pytest.mark.kitti
def test_scan_input_without_a_scan_is_refused(annotated):
    with pytest.raises(InputError, match=r"^input_from: 'scan' needs the frame's LiDAR, expected .*velodyne_raw.*"
                                         r"or .*velodyne_points.*\.bin"):
        KittiAnnotated(annotated, input_from="scan")


@pytest.mark.kitti
@pytest.mark.parametrize(("options", "message"), [
    ({"input_from": "radar"}, r"^input_from: expected one of 'share', 'rings', 'lidar', 'scan', got 'radar'"),
    ({"input_from": "lidar", "input_share": 0.5}, r"^input_share: not used with input_from 'lidar'"),
    ({"input_share": 0.0}, r"^input_share: expected a number in \(0, 1\]"),
    ({"input_share": 1.0}, r"^input_share: expected a number below 1 for input_from 'share'"),
    ({"keep_every_ring": 0}, r"^keep_every_ring: expected an integer in \[1, 64\]"),
    ({"seed": 0.5}, r"^seed: expected an integer or None, got 0.5"),
    ({"split": "test"}, r"^split: expected one of 'train', 'val', got 'test'"),
])
def test_bad_options_are_named(annotated, options, message):
    with pytest.raises(InputError, match=message):
        KittiAnnotated(annotated, **options)


def test_a_root_without_annotation_is_refused(tmp_path):
    (tmp_path / "raw").mkdir()
    with pytest.raises(InputError, match=r"KittiAnnotated: expected .*data_depth_annotated.train"):
        KittiAnnotated(tmp_path)
