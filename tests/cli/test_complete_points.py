"""Tests of ``crfdepth complete --points CLOUD --calib CALIB`` (one frame from a raw point
cloud and a calibration file): equal to the two-step path (``crfdepth project`` then
``crfdepth complete --sparse``) and to :func:`crfdepth.api.complete_depth`, on the
shared KITTI raw frame and on a synthetic rig described by a YAML file; bad input."""

from __future__ import annotations

import json

import cv2
import numpy as np
import pytest
import torch

from crfdepth import cli
from crfdepth.api import complete_depth
from crfdepth.data.synthetic import make_scene
from crfdepth.fill.nearest import nearest_fill
from crfdepth.geometry.projection import ring_mask
from crfdepth.inputs import points_to_sparse
from crfdepth.io.calibration import load_any_calibration, load_calibration
from crfdepth.io.kitti import read_depth_png, read_rgb, read_velodyne
from crfdepth.io.pointcloud import write_pcd, write_ply
from crfdepth.metrics import depth_metrics
from crfdepth.model import CRFDepth

DRIVE = "raw/2011_09_26/2011_09_26_drive_0001_sync"
SCAN = f"{DRIVE}/velodyne_points/data/0000000005.bin"
IMAGE = f"{DRIVE}/image_02/data/0000000005.png"
FAST = ["--no-refine", "--potentials", "colour", "--quiet"]


@pytest.fixture
def main(monkeypatch):
    monkeypatch.setattr(cli, "_COMMANDS", ("crfdepth.cli.complete", "crfdepth.cli.project"))
    return cli.main


def _quantised(depth: np.ndarray) -> np.ndarray:
    """What write_depth_png + read_depth_png make of a completed depth map."""
    return np.round(np.maximum(depth.astype(np.float64), 1 / 256) * 256).astype(np.float32) / 256


def _rmse(depth, target) -> float:
    return float(depth_metrics(torch.as_tensor(depth), torch.as_tensor(target))["rmse"][0])


def test_kitti_points_equal_two_step_cli(main, kitti_root, tmp_path):
    """One step (--points --calib) against two (project -> PNG -> complete --sparse).

    Both outputs go through the depth PNG. The one-step path sees the unquantised sparse
    map, the two-step path the PNG's (1/256 m steps), so each is compared exactly with
    complete_depth on the same sparse map, and the two with each other statistically."""
    image, calib_dir = kitti_root / IMAGE, kitti_root / "raw/2011_09_26"
    K = load_calibration(calib_dir).K
    (tmp_path / "K.txt").write_text(" ".join(repr(float(v)) for v in K.ravel()) + "\n")
    assert main(["project", "--velodyne", str(kitti_root / SCAN), "--calib", str(calib_dir), "--image", str(image),
                 "--out", str(tmp_path / "sparse.png")]) == 0
    assert main(["complete", "--image", str(image), "--sparse", str(tmp_path / "sparse.png"), "--intrinsics",
                 str(tmp_path / "K.txt"), "--out", str(tmp_path / "two.png"), *FAST]) == 0
    assert main(["complete", "--image", str(image), "--points", str(kitti_root / SCAN), "--calib", str(calib_dir),
                 "--out", str(tmp_path / "one.png"), *FAST]) == 0
    one, two = read_depth_png(tmp_path / "one.png"), read_depth_png(tmp_path / "two.png")
    assert one.shape == two.shape == (375, 1242) and one.min() > 0

    model = CRFDepth.from_pretrained(potentials=["colour"], refine=False)  # the CLI default weights
    rgb = read_rgb(image)
    api_points, _ = complete_depth(rgb, points=read_velodyne(kitti_root / SCAN),
                                   calibration=load_any_calibration(calib_dir), model=model, return_std=False)
    api_sparse, _ = complete_depth(rgb, sparse=read_depth_png(tmp_path / "sparse.png"), K=K, model=model,
                                   return_std=False)
    assert np.abs(one - _quantised(api_points)).max() < 1e-3  # measured: 0 (identical PNG codes)
    assert np.abs(two - _quantised(api_sparse)).max() < 1e-3  # measured: 0
    # one step vs two steps: only the sparse quantisation differs
    # The CRF on log z is a weighted geometric mean of the returns, so an input change dz
    # at depth z moves a pixel at depth x by up to (x / z) dz: pixels farther than the
    # LiDAR they borrow from amplify the quantisation (on 1/z by (x / z)^2: up to two
    # PNG steps of 1/256 m were measured with the earlier 1/z weights).
    assert np.median(np.abs(one - two)) == 0
    assert np.abs(one - two).max() <= 2 / 256 + 1e-6
    assert np.sqrt(np.mean((one - two) ** 2)) < 0.003


def test_kitti_16_rings_from_pcd_beats_nearest_fill(main, kitti_root, tmp_path):
    """A 16-ring cloud (every 4th ring) saved as PCD, default model, scored on the held-out rings."""
    points = read_velodyne(kitti_root / SCAN)
    keep = ring_mask(points, 4)
    write_pcd(tmp_path / "16.pcd", points[keep])
    assert main(["complete", "--image", str(kitti_root / IMAGE), "--points", str(tmp_path / "16.pcd"),
                 "--calib", str(kitti_root / "raw/2011_09_26/calib_cam_to_cam.txt"),
                 "--out", str(tmp_path / "d.png"), "--out-std", str(tmp_path / "s.png")]) == 0
    rig = load_any_calibration(kitti_root / "raw/2011_09_26")
    sparse = points_to_sparse(points[keep], rig, (375, 1242))
    target = points_to_sparse(points[~keep], rig, (375, 1242))
    target[sparse > 0] = 0
    crf = _rmse(read_depth_png(tmp_path / "d.png"), target)
    nn = _rmse(nearest_fill(torch.from_numpy(sparse)), target)
    assert crf < 0.8 * nn, (crf, nn)  # measured: 2231 mm vs 3481 mm
    assert read_depth_png(tmp_path / "s.png").min() > 0


@pytest.fixture(scope="module")
def rig(tmp_path_factory):
    """A synthetic 16-beam rig at 640x480: image PNG, cloud PLY, calibration YAML and JSON."""
    folder = tmp_path_factory.mktemp("rig")
    scene = make_scene(0, height=480, width=640, beams=16)
    rgb = np.round(scene.image * 255).astype(np.uint8)
    cv2.imwrite(str(folder / "image.png"), cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR))
    write_ply(folder / "cloud.ply", scene.points)
    (folder / "rig.yaml").write_text(
        f"K: {json.dumps(scene.K.tolist())}\nT_cam_lidar: {json.dumps(scene.T_cam_lidar.tolist())}\n"
        "image_size: [480, 640]\n")
    (folder / "inverted.json").write_text(json.dumps({"K": scene.K.ravel().tolist(),
                                                      "T_cam_lidar": np.linalg.inv(scene.T_cam_lidar).tolist()}))
    return {"folder": folder, "scene": scene, "rgb": rgb}


def test_rig_yaml_equals_api(main, rig, tmp_path):
    folder, scene = rig["folder"], rig["scene"]
    assert main(["complete", "--image", str(folder / "image.png"), "--points", str(folder / "cloud.ply"),
                 "--calib", str(folder / "rig.yaml"), "--out", str(tmp_path / "d.png")]) == 0
    depth = read_depth_png(tmp_path / "d.png")
    expected, _ = complete_depth(rig["rgb"], points=scene.points, T_cam_lidar=scene.T_cam_lidar, K=scene.K,
                                 return_std=False)
    assert np.abs(depth - _quantised(expected)).max() < 1e-3  # measured: 0
    crf = _rmse(depth, scene.target())
    nn = _rmse(nearest_fill(torch.from_numpy(scene.sparse)), scene.target())
    assert crf < 0.85 * nn, (crf, nn)


@pytest.mark.parametrize("case,expected", [
    ("inverted", ["no point lands", "opposite direction", "--calib"]),
    ("no calib", ["needs --image, --points, --calib and --out", "missing --calib"]),
    ("with sparse", ["--sparse", "cannot be combined with --points"]),
    ("bad cloud", ["--points", "unsupported point-cloud format", ".xyz"]),
    ("size", ["640x480", "calibration", "1242x375"]),
    ("out is input", ["--out", "is the --points input"]),
])
def test_bad_input(main, rig, tmp_path, capsys, kitti_root, case, expected):
    folder = rig["folder"]
    args = ["complete", "--image", str(folder / "image.png"), "--points", str(folder / "cloud.ply"),
            "--calib", str(folder / "rig.yaml"), "--out", str(tmp_path / "d.png"), *FAST]
    if case == "inverted":
        scene = rig["scene"]
        T, K = scene.T_cam_lidar, scene.K
        cam = scene.points[:, :3] @ T[:3, :3].T + T[:3, 3]
        z = np.where(cam[:, 2] > 0, cam[:, 2], 1)
        u, v = K[0, 0] * cam[:, 0] / z + K[0, 2], K[1, 1] * cam[:, 1] / z + K[1, 2]
        inside = (cam[:, 2] > 0) & (u >= 0) & (u < 640) & (v >= 0) & (v < 480)
        write_ply(tmp_path / "fov.ply", scene.points[inside])  # a camera-FOV export of the cloud
        args[4], args[6] = str(tmp_path / "fov.ply"), str(folder / "inverted.json")
    elif case == "no calib":
        del args[5:7]
    elif case == "with sparse":
        args += ["--sparse", str(folder / "image.png")]
    elif case == "bad cloud":
        (tmp_path / "c.xyz").write_text("1 2 3\n")
        args[4] = str(tmp_path / "c.xyz")
    elif case == "size":
        args[6] = str(kitti_root / "raw/2011_09_26")
    elif case == "out is input":
        args[8] = str(tmp_path / "cloud.png")
        (tmp_path / "cloud.png").symlink_to(folder / "cloud.ply")
    assert main(args) == 2
    err = capsys.readouterr().err
    for part in expected:
        assert part in err, err
    assert not (tmp_path / "d.png").exists()
