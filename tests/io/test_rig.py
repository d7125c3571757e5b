"""Tests of crfdepth.io.rig: rig YAML/JSON calibration files, the checks on K and
T_cam_lidar, and load_any_calibration on the shared KITTI calibrations (projection
identical to crfdepth.projection.project_velodyne)."""

from __future__ import annotations

import json

import numpy as np
import pytest

from crfdepth.errors import InputError
from crfdepth.io.kitti import load_calibration, read_velodyne
from crfdepth.io.rig import RigCalibration, check_rigid, load_any_calibration, read_rig_calibration
from crfdepth.projection import project_to_depth, project_velodyne

K = [[500.0, 0.0, 320.0], [0.0, 500.0, 240.0], [0.0, 0.0, 1.0]]
# LiDAR x forward, y left, z up -> camera x right, y down, z forward; 10 cm offsets.
T = [[0.0, -1.0, 0.0, 0.02], [0.0, 0.0, -1.0, -0.08], [1.0, 0.0, 0.0, -0.05], [0.0, 0.0, 0.0, 1.0]]
YAML = """\
K: [[500.0, 0.0, 320.0], [0.0, 500.0, 240.0], [0.0, 0.0, 1.0]]
T_cam_lidar:
  - [0.0, -1.0,  0.0,  0.02]
  - [0.0,  0.0, -1.0, -0.08]
  - [1.0,  0.0,  0.0, -0.05]
  - [0.0,  0.0,  0.0,  1.0]
distortion: [0.1, -0.25, 0.001, 0.002, 0.1]
image_size: [480, 640]
"""
RAW_CALIB = "raw/2011_09_26"
SCAN = "raw/2011_09_26/2011_09_26_drive_0001_sync/velodyne_points/data/0000000005.bin"


def test_yaml_and_json_read_the_same(tmp_path):
    (tmp_path / "rig.yaml").write_text(YAML)
    (tmp_path / "rig.json").write_text(json.dumps({"K": sum(K, []), "T_cam_lidar": T,
                                                   "distortion": [0.1, -0.25, 0.001, 0.002, 0.1],
                                                   "image_size": [480, 640]}))
    for name in ("rig.yaml", "rig.json"):
        rig = load_any_calibration(tmp_path / name)
        np.testing.assert_array_equal(rig.K, K)
        np.testing.assert_array_equal(rig.T_cam_lidar, T)
        np.testing.assert_array_equal(rig.distortion, [0.1, -0.25, 0.001, 0.002, 0.1])
        assert rig.image_size == (480, 640) and rig.kitti is None


def test_optional_keys(tmp_path):
    (tmp_path / "rig.yml").write_text("K: [500, 0, 320, 0, 500, 240, 0, 0, 1]\nT_cam_lidar: " + json.dumps(T) + "\n")
    rig = read_rig_calibration(tmp_path / "rig.yml")
    assert rig.distortion is None and rig.image_size is None
    # A point 10 m ahead of the LiDAR: camera (x, y, z) = (0.02, -0.08, 9.95) m, hand-projected with K.
    depth = rig.project(np.array([[10.0, 0.0, 0.0]]), (480, 640))
    v, u = np.argwhere(depth > 0)[0]
    assert depth[v, u] == pytest.approx(9.95) and (u, v) == (round(320 + 500 * 0.02 / 9.95),
                                                             round(240 - 500 * 0.08 / 9.95))


BASE = "K: " + json.dumps(K) + "\nT_cam_lidar: " + json.dumps(T)


@pytest.mark.parametrize("text,expected", [
    ("K: [1, 2, 3]\nT_cam_lidar: " + json.dumps(T), ["K", "3x3", "(3,)"]),
    ("T_cam_lidar: " + json.dumps(T), ["missing key(s) K"]),
    (BASE + "\ndistorsion: [0, 0, 0, 0]", ["unknown key(s) distorsion"]),
    (BASE + "\ndistortion: [0.1, 0.2]", ["distortion", "k1 k2 p1 p2"]),
    (BASE + "\nimage_size: [480]", ["image_size", "[height, width]"]),
    ("K: [[-500, 0, 320], [0, 500, 240], [0, 0, 1]]\nT_cam_lidar: " + json.dumps(T), ["fx=-500", "> 0"]),
    (BASE + "\nimage_size: [48, 64]",
     ["principal point", "far outside", "64x48"]),
    ("K: " + json.dumps(K) + "\nT_cam_lidar: " + json.dumps(np.multiply(T, [[1000]] * 3 + [[1]]).tolist()),
     ["not orthonormal"]),
    ("K: " + json.dumps(K) + "\nT_cam_lidar: " + json.dumps(T[:3] + [[0, 0, 1, 1]]), ["last row", "0 0 0 1"]),
    ("- just a list", ["expected a mapping"]),
    ("K: [unclosed", ["not valid YAML"]),
])
def test_bad_rig_files(tmp_path, text, expected):
    path = tmp_path / "rig.yaml"
    path.write_text(text)
    with pytest.raises(InputError) as info:
        read_rig_calibration(path)
    for part in expected:
        assert part in str(info.value)
    assert "rig.yaml" in str(info.value)


def test_check_rigid_tolerance_and_reflection():
    R = np.array(T, dtype=float)
    R[0, 1] += 4e-4  # within 1e-3
    check_rigid(R)
    R[0, 1] += 2e-3
    with pytest.raises(InputError, match="not orthonormal"):
        check_rigid(R)
    flip = np.diag([1.0, 1.0, -1.0, 1.0])
    with pytest.raises(InputError, match="reflection"):
        check_rigid(flip)


def test_missing_file(tmp_path):
    with pytest.raises(FileNotFoundError, match="nope.yaml"):
        load_any_calibration(tmp_path / "nope.yaml")


def test_kitti_raw_calibration_projects_like_project_velodyne(kitti_root):
    calib = load_calibration(kitti_root / RAW_CALIB, 2)
    rig = load_any_calibration(kitti_root / RAW_CALIB, camera=2)
    assert rig.kitti == calib and rig.image_size == (375, 1242)
    np.testing.assert_array_equal(rig.K, calib.K)
    points = read_velodyne(kitti_root / SCAN)
    expected = project_velodyne(points, calib)
    np.testing.assert_array_equal(rig.project(points, (375, 1242)), expected)
    # K [I | 0] T_cam_lidar is the same projection (T includes camera 2's baseline):
    # identical pixels and depths to float rounding.
    T_ = rig.T_cam_lidar
    via_K = project_to_depth(points[:, :3].astype(np.float64) @ T_[:3, :3].T + T_[:3, 3], rig.K, (375, 1242))
    assert np.array_equal(via_K > 0, expected > 0)
    assert np.abs(via_K - expected).max() < 1e-5
    assert (expected > 0).sum() == 19137  # the README's count


def test_kitti_object_calibration(kitti_root):
    path = kitti_root / "object/training/calib/000010.txt"
    rig = load_any_calibration(path)
    assert rig.image_size is None and rig.kitti == load_calibration(path)
    np.testing.assert_allclose(rig.K @ rig.T_cam_lidar[:3], rig.kitti.velo_to_image(), atol=1e-9)


def test_rig_calibration_copies_and_checks():
    K_in = np.array(K)
    rig = RigCalibration(K=K_in, T_cam_lidar=np.array(T))
    rig.K[0, 0] = 1.0
    assert K_in[0, 0] == 500.0
    with pytest.raises(InputError, match="T_cam_lidar"):
        RigCalibration(K=K, T_cam_lidar=np.eye(3))
