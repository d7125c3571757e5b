"""Tests of crfdepth.io.calibration: the KITTI Calibration and its two file formats (raw
day folder, object benchmark), rig YAML/JSON files with the checks on K and T_cam_lidar,
and load_any_calibration on the shared KITTI calibrations (projection identical to
crfdepth.geometry.projection.project_velodyne)."""

from __future__ import annotations

import ast
import json
import re
import shutil
from pathlib import Path

import numpy as np
import pytest

import crfdepth.io
from crfdepth.checks import check_rigid
from crfdepth.errors import InputError
from crfdepth.geometry.projection import project_points, project_to_depth, project_velodyne
from crfdepth.io.calibration import (
    Calibration,
    RigCalibration,
    load_any_calibration,
    load_calibration,
    read_object_calibration,
    read_raw_calibration,
    read_rig_calibration,
)
from crfdepth.io.kitti import read_velodyne

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
DRIVE = "2011_09_26_drive_0001_sync"
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
    depth = project_points(np.array([[10.0, 0.0, 0.0]]), rig, (480, 640))
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
    missing = tmp_path / "nope" / "0000000005"
    for reader, suffix in [(read_object_calibration, ".txt"), (load_calibration, ".txt"), (read_raw_calibration, ""),
                           (read_rig_calibration, ".yaml")]:
        path = missing.with_suffix(suffix)
        with pytest.raises(FileNotFoundError, match=re.escape(str(path))):
            reader(path)


def test_kitti_raw_calibration_projects_like_project_velodyne(kitti_root):
    calib = load_calibration(kitti_root / RAW_CALIB, 2)
    rig = load_any_calibration(kitti_root / RAW_CALIB, camera=2)
    assert rig.kitti == calib and rig.image_size == (375, 1242)
    np.testing.assert_array_equal(rig.K, calib.K)
    points = read_velodyne(kitti_root / SCAN)
    expected = project_velodyne(points, calib)
    np.testing.assert_array_equal(project_points(points, rig, (375, 1242)), expected)
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


# --------------------------------------------------------------------------- KITTI calibration files


def test_calibration_matrices_compose():
    rng = np.random.default_rng(1)
    P = rng.normal(size=(3, 4))
    R = np.eye(4)
    R[:3, :3] = np.linalg.qr(rng.normal(size=(3, 3)))[0]
    T = np.eye(4)
    T[:3] = rng.normal(size=(3, 4))
    calib = Calibration(P_rect=P, R_rect=R, T_velo_to_cam=T)
    assert calib.image_size is None
    np.testing.assert_allclose(calib.K, P[:, :3])
    np.testing.assert_allclose(calib.velo_to_rect_cam(), R @ T)
    np.testing.assert_allclose(calib.velo_to_image(), P @ R @ T)
    assert calib.velo_to_image().shape == (3, 4)
    assert calib == Calibration(P_rect=P.tolist(), R_rect=R, T_velo_to_cam=T)
    assert calib != Calibration(P_rect=P, R_rect=R, T_velo_to_cam=T, image_size=(375, 1242))


@pytest.mark.parametrize("field, value, match", [
    ("P_rect", np.eye(3), r"Calibration.P_rect: expected shape \(3, 4\), got \(3, 3\)"),
    ("R_rect", np.eye(3), r"Calibration.R_rect: expected shape \(4, 4\), got \(3, 3\)"),
    ("T_velo_to_cam", np.eye(3, 4), r"Calibration.T_velo_to_cam: expected shape \(4, 4\)"),
    ("image_size", (375.5, 1242), r"Calibration.image_size: expected \(height, width\)"),
    ("image_size", (375,), r"Calibration.image_size"),
])
def test_calibration_checks_shapes(field, value, match):
    fields = {"P_rect": np.zeros((3, 4)), "R_rect": np.eye(4), "T_velo_to_cam": np.eye(4), field: value}
    with pytest.raises(InputError, match=match):
        Calibration(**fields)


@pytest.mark.kitti
def test_read_raw_calibration(kitti_root):
    calib = read_raw_calibration(kitti_root / "raw" / "2011_09_26", camera=2)
    assert calib.image_size == (375, 1242)  # S_rect_02: 1242 375 (width height)
    assert calib.P_rect.shape == (3, 4) and calib.R_rect.shape == (4, 4)
    assert calib.T_velo_to_cam.shape == (4, 4)
    np.testing.assert_array_equal(calib.P_rect[:, 3], [44.85728, 0.2163791, 0.002745884])
    np.testing.assert_array_equal(calib.K, [[721.5377, 0, 609.5593], [0, 721.5377, 172.854], [0, 0, 1]])
    assert calib.R_rect[0, 1] == 0.00983776 and calib.R_rect[3, 3] == 1 and calib.R_rect[0, 3] == 0
    np.testing.assert_array_equal(calib.T_velo_to_cam[:3, 3], [-0.004069766, -0.07631618, -0.2717806])
    assert calib.T_velo_to_cam[0, 1] == -0.9999714
    np.testing.assert_array_equal(calib.T_velo_to_cam[3], [0, 0, 0, 1])
    right = read_raw_calibration(kitti_root / "raw" / "2011_09_26", camera=3)
    assert right.P_rect[0, 3] == -339.5242
    np.testing.assert_array_equal(right.R_rect, calib.R_rect)  # R_rect_00 for every camera


@pytest.mark.kitti
def test_read_object_calibration(kitti_root):
    calib = read_object_calibration(kitti_root / "object" / "training" / "calib" / "000000.txt")
    assert calib.image_size is None
    np.testing.assert_array_equal(calib.P_rect[:, 3], [45.75831, -0.3454157, 0.004981016])
    assert calib.K[0, 0] == 707.0493 and calib.K[1, 2] == 180.5066
    assert calib.R_rect[2, 1] == 0.004123522
    np.testing.assert_array_equal(calib.T_velo_to_cam[:3, 3], [-0.02457729, -0.06127237, -0.3321029])
    np.testing.assert_array_equal(calib.T_velo_to_cam[3], [0, 0, 0, 1])
    left_grey = read_object_calibration(kitti_root / "object" / "training" / "calib" / "000000.txt", camera=0)
    np.testing.assert_array_equal(left_grey.P_rect[:, 3], [0, 0, 0])


@pytest.mark.kitti
def test_load_calibration_dispatch(kitti_root):
    day = kitti_root / "raw" / "2011_09_26"
    raw = read_raw_calibration(day, camera=3)
    for path in (day, day / "calib_cam_to_cam.txt", day / "calib_velo_to_cam.txt", str(day)):
        loaded = load_calibration(path, camera=3)
        np.testing.assert_array_equal(loaded.velo_to_image(), raw.velo_to_image())
        assert loaded.image_size == (375, 1242)
    object_file = kitti_root / "object" / "training" / "calib" / "000010.txt"
    loaded = load_calibration(object_file)
    np.testing.assert_array_equal(loaded.velo_to_image(), read_object_calibration(object_file).velo_to_image())
    assert loaded.image_size is None


@pytest.mark.kitti
def test_load_calibration_detects_raw_files_by_key(kitti_root, tmp_path):
    day = kitti_root / "raw" / "2011_09_26"
    for name in ("calib_cam_to_cam.txt", "calib_velo_to_cam.txt"):
        shutil.copy(day / name, tmp_path / name)
    renamed = tmp_path / "cam_to_cam_copy.txt"
    shutil.copy(day / "calib_cam_to_cam.txt", renamed)
    np.testing.assert_array_equal(load_calibration(renamed).P_rect, read_raw_calibration(day).P_rect)


def test_raw_calibration_missing_file_names_it(tmp_path):
    (tmp_path / "calib_cam_to_cam.txt").write_text("R_rect_00: 1 0 0 0 1 0 0 0 1\n")
    with pytest.raises(FileNotFoundError, match=re.escape(str(tmp_path / "calib_velo_to_cam.txt"))):
        read_raw_calibration(tmp_path)


@pytest.mark.kitti
@pytest.mark.parametrize("key", ["P2", "R0_rect", "Tr_velo_to_cam"])
def test_object_calibration_missing_key(kitti_root, tmp_path, key):
    source = kitti_root / "object" / "training" / "calib" / "000001.txt"
    path = tmp_path / "000001.txt"
    path.write_text("".join(line for line in source.read_text().splitlines(keepends=True)
                            if not line.startswith(key + ":")))
    with pytest.raises(InputError, match=rf"key '{key}' not found in .*000001\.txt"):
        read_object_calibration(path)
    with pytest.raises(InputError, match=rf"'{key}'"):
        load_calibration(path)


@pytest.mark.kitti
@pytest.mark.parametrize("file_name, key", [("calib_cam_to_cam.txt", "P_rect_02"),
                                            ("calib_cam_to_cam.txt", "S_rect_02"),
                                            ("calib_cam_to_cam.txt", "R_rect_00"),
                                            ("calib_velo_to_cam.txt", "T")])
def test_raw_calibration_missing_key(kitti_root, tmp_path, file_name, key):
    day = kitti_root / "raw" / "2011_09_26"
    for name in ("calib_cam_to_cam.txt", "calib_velo_to_cam.txt"):
        lines = (day / name).read_text().splitlines(keepends=True)
        if name == file_name:
            lines = [line for line in lines if not line.startswith(key + ":")]
        (tmp_path / name).write_text("".join(lines))
    with pytest.raises(InputError, match=rf"key '{key}' not found in .*{re.escape(file_name)}"):
        read_raw_calibration(tmp_path)


def test_calibration_key_with_wrong_count(tmp_path):
    path = tmp_path / "calib.txt"
    path.write_text("P2: 1 2 3\nR0_rect: 1 0 0 0 1 0 0 0 1\nTr_velo_to_cam: 0 0 0 0 0 0 0 0 0 0 0 0\n")
    with pytest.raises(InputError, match=r"key 'P2' in .*calib\.txt: expected 12 numbers \(3, 4\), got 3"):
        read_object_calibration(path)


@pytest.mark.parametrize("camera", [4, -1, "2", True])
def test_bad_camera_index(tmp_path, camera):
    with pytest.raises(InputError, match=r"camera: expected one of 0, 1, 2, 3"):
        read_object_calibration(tmp_path / "unused.txt", camera=camera)


# --------------------------------------------------------------------------- module structure


def _imports(path: Path) -> set[str]:
    """Modules imported anywhere in ``path`` (including inside functions and TYPE_CHECKING)."""
    names = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.ImportFrom) and node.module:
            names.add(node.module)
        elif isinstance(node, ast.Import):
            names.update(alias.name for alias in node.names)
    return names


def test_calibration_and_projection_import_one_way():
    """Calibration types in one module, projection math in another, neither importing the other: geometry sits
    below io and reads a calibration by its fields (docs/design.md section 8)."""
    package = Path(crfdepth.io.__file__).resolve().parents[1]
    calibration = _imports(package / "io" / "calibration.py")
    assert not any(name.startswith(("crfdepth.geometry.projection", "crfdepth.api")) for name in calibration), calibration
    assert not any(name.startswith("crfdepth.io") for name in _imports(package / "geometry" / "projection.py"))
    assert not (package / "io" / "rig.py").exists()
    assert all(len((package / "io" / f).read_text().splitlines()) <= 400
               for f in ("calibration.py", "key_values.py", "kitti.py", "pointcloud.py", "files.py"))


def test_io_reexports():
    for name in ("Calibration", "RigCalibration", "load_calibration", "load_any_calibration", "read_raw_calibration",
                 "read_object_calibration", "read_rig_calibration", "read_depth_png", "read_velodyne"):
        assert getattr(crfdepth.io, name) is not None and name in crfdepth.io.__all__
    assert crfdepth.io.Calibration is Calibration and crfdepth.io.RigCalibration is RigCalibration
