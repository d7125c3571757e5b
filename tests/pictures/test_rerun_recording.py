"""crfdepth.pictures.rerun_recording: frames logged into a .rrd file and read back (tests/recordings.py), the
back-projection of a sparse map, the poses of a targets run, no file left by a failed block, and the one line
when rerun-sdk is missing."""

from __future__ import annotations

import sys

import cv2
import numpy as np
import pytest

from crfdepth.errors import InputError
from crfdepth.io.calibration import RigCalibration
from crfdepth.pictures import rerun_recording as rec
from tests.recordings import depth_image, pinhole_K, pose, read_recording

pytest.importorskip("rerun")

H, W = 24, 40
K = np.array([[30.0, 0.0, 19.5], [0.0, 32.0, 11.0], [0.0, 0.0, 1.0]])


def _sparse(seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    sparse = np.zeros((H, W), np.float32)
    sparse[::3, ::2] = rng.uniform(2.0, 40.0, size=sparse[::3, ::2].shape)
    return sparse


def _rgb() -> np.ndarray:
    rows, cols = np.mgrid[0:H, 0:W]
    return np.stack([rows * 10, cols * 6, (rows + cols) * 4], axis=-1).astype(np.uint8)


def test_sparse_points_project_back_onto_their_pixels():
    sparse = _sparse()
    for matrix in (K, K + np.array([[0, 0.7, 0], [0, 0, 0], [0, 0, 0]])):  # with a skew too
        points = rec.sparse_points(sparse, matrix)
        v, u = np.nonzero(sparse)
        assert points.shape == (len(u), 3)
        uv, z = rec.project(points, matrix, (H, W))
        np.testing.assert_allclose(uv, np.stack([u, v], axis=1), atol=1e-9)
        np.testing.assert_allclose(z, sparse[v, u], rtol=1e-6)


def test_project_keeps_the_points_in_front_and_inside_the_image():
    points = np.array([[0.0, 0.0, 5.0], [0.0, 0.0, -5.0], [100.0, 0.0, 1.0], [0.0, 0.0, 0.0]])
    uv, z = rec.project(points, K, (H, W))
    np.testing.assert_allclose(uv, [[19.5, 11.0]])
    np.testing.assert_allclose(z, [5.0])


def test_a_frame_logged_into_a_file_reads_back(tmp_path):
    sparse, rgb = _sparse(), _rgb()
    depth = np.linspace(3.0, 30.0, H * W, dtype=np.float32).reshape(H, W)
    std = np.linspace(0.01, 2.0, H * W, dtype=np.float32).reshape(H, W)
    path = tmp_path / "frame.rrd"
    with rec.open_recording(path) as stream:
        rec.log_frame(stream, 0, image=rgb, K=K, points_cam=rec.sparse_points(sparse, K), depth=depth, std=std)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["frame.rrd"]  # the temporary file renamed
    found = read_recording(path)
    assert {rec.WORLD, rec.CAMERA, rec.IMAGE, rec.LIDAR_2D, rec.LIDAR_3D, rec.DEPTH, rec.STD} <= set(found)
    assert rec.TARGETS not in found and rec.TRAJECTORY not in found
    step = {entity: steps[0] for entity, steps in found.items() if 0 in steps}
    np.testing.assert_allclose(pinhole_K(step[rec.IMAGE]), K, rtol=1e-6)
    np.testing.assert_array_equal(step[rec.IMAGE]["Pinhole:resolution"][0], [W, H])
    np.testing.assert_array_equal(step[rec.IMAGE]["Image:buffer"].reshape(H, W, 3), rgb)
    np.testing.assert_array_equal(pose(step[rec.CAMERA]), np.eye(4))
    np.testing.assert_array_equal(depth_image(step[rec.DEPTH]), depth)
    np.testing.assert_array_equal(depth_image(step[rec.STD]), std)
    count = int(np.count_nonzero(sparse))
    assert step[rec.LIDAR_2D]["Points2D:positions"].shape == (count, 2)
    np.testing.assert_allclose(step[rec.LIDAR_3D]["Points3D:positions"], rec.sparse_points(sparse, K), rtol=1e-6)
    # near points red, far points blue, as the depth pictures
    colours = step[rec.LIDAR_2D]["Points2D:colors"].astype(np.uint32)
    red, blue = colours >> 24, (colours >> 8) & 0xFF
    z = sparse[np.nonzero(sparse)]
    assert red[z < 4].mean() > blue[z < 4].mean() and blue[z > 35].mean() > red[z > 35].mean()


def test_entities_without_a_value_are_left_out_and_frames_are_time_steps(tmp_path):
    path = tmp_path / "two.rrd"
    with rec.open_recording(path) as stream:
        recorder = rec.Recorder(stream)
        for seed in range(2):
            recorder.complete_frame(_rgb(), np.full((H, W), 5.0 + seed, np.float32), sparse=_sparse(seed), K=K)
    found = read_recording(path)
    assert rec.STD not in found and rec.TARGETS not in found and rec.TRAJECTORY not in found
    assert sorted(found[rec.DEPTH]) == [0, 1]
    assert [depth_image(found[rec.DEPTH][f])[0, 0] for f in (0, 1)] == [5.0, 6.0]
    assert [len(found[rec.LIDAR_3D][f]["Points3D:positions"]) for f in (0, 1)] == \
        [np.count_nonzero(_sparse(s)) for s in (0, 1)]


def test_a_point_cloud_is_moved_into_the_camera_and_a_distorted_image_undistorted(tmp_path):
    T = np.eye(4)
    T[:3, :3] = [[0.0, -1.0, 0.0], [0.0, 0.0, -1.0], [1.0, 0.0, 0.0]]  # LiDAR x forward, z up
    T[:3, 3] = [0.1, -0.2, 0.3]
    calibration = RigCalibration(K=K, T_cam_lidar=T, distortion=np.array([0.1, -0.05, 0.0, 0.0]))
    points = np.array([[10.0, 0.0, 0.0, 7.0], [5.0, 1.0, 0.5, 7.0], [-5.0, 0.0, 0.0, 7.0]])  # one behind
    path = tmp_path / "cloud.rrd"
    with rec.open_recording(path) as stream:
        rec.Recorder(stream).complete_frame(_rgb(), np.full((H, W), 9.0, np.float32), points=points,
                                            calibration=calibration)
    step = {entity: steps[0] for entity, steps in read_recording(path).items() if 0 in steps}
    np.testing.assert_allclose(step[rec.LIDAR_3D]["Points3D:positions"], points[:, :3] @ T[:3, :3].T + T[:3, 3],
                               rtol=1e-6)
    assert len(step[rec.LIDAR_2D]["Points2D:positions"]) == 2
    undistorted = cv2.undistort(_rgb(), K, calibration.distortion)
    np.testing.assert_array_equal(step[rec.IMAGE]["Image:buffer"].reshape(H, W, 3), undistorted)


def test_targets_frames_follow_the_poses_with_a_trajectory(tmp_path):
    T = np.eye(4)
    T[:3, :3] = [[0.0, -1.0, 0.0], [0.0, 0.0, -1.0], [1.0, 0.0, 0.0]]
    calibration = RigCalibration(K=K, T_cam_lidar=T)
    poses = [np.eye(4) for _ in range(3)]
    for i, P in enumerate(poses):
        P[0, 3] = 2.0 * i  # the LiDAR drives 2 m forward (its x) per frame
    scan = np.array([[10.0, 1.0, 0.0], [20.0, -1.0, 1.0]])
    targets = np.zeros((H, W), np.float32)
    targets[5, 6] = 12.5
    path = tmp_path / "targets.rrd"
    with rec.open_recording(path) as stream:
        recorder = rec.Recorder(stream)
        for P in poses:
            recorder.targets_frame(_rgb(), targets, scan=scan, calibration=calibration, pose=P)
    found = read_recording(path)
    assert rec.DEPTH not in found and rec.STD not in found
    for i in range(3):  # the camera moves 2 m along its z (forward) per frame, in the first camera's world
        expected = np.eye(4)
        expected[2, 3] = 2.0 * i
        np.testing.assert_allclose(pose(found[rec.CAMERA][i]), expected, atol=1e-6)
        world = found[rec.LIDAR_3D][i]["Points3D:positions"]
        np.testing.assert_allclose(world, (scan + [2.0 * i, 0, 0]) @ T[:3, :3].T + T[:3, 3], atol=1e-5)
        np.testing.assert_array_equal(depth_image(found[rec.TARGETS][i]), targets)
    strip = found[rec.TRAJECTORY][2]["LineStrips3D:strips"]
    np.testing.assert_allclose(strip, [[0, 0, 0], [0, 0, 2], [0, 0, 4]], atol=1e-6)


def test_a_failed_block_leaves_no_file(tmp_path):
    path = tmp_path / "failed.rrd"
    with pytest.raises(KeyboardInterrupt), rec.open_recording(path) as stream:
        rec.log_frame(stream, 0, image=_rgb(), K=K, points_cam=rec.sparse_points(_sparse(), K))
        raise KeyboardInterrupt
    assert list(tmp_path.iterdir()) == []


def test_log_frame_refuses_a_map_of_another_size(tmp_path):
    with rec.open_recording(tmp_path / "bad.rrd") as stream, pytest.raises(InputError) as error:
        rec.log_frame(stream, 0, image=_rgb(), K=K, points_cam=np.zeros((0, 3)), depth=np.ones((H, W + 1)))
    assert str(error.value) == f"depth: expected the image's size {H}x{W} (HxW), got {H}x{W + 1}"


def test_without_rerun_sdk_one_line_names_the_extra(monkeypatch):
    monkeypatch.setitem(sys.modules, "rerun", None)  # import rerun raises ImportError
    with pytest.raises(InputError) as error:
        rec.import_rerun("--rerun")
    assert str(error.value) == ("--rerun: needs the viewer extra: pip install 'crfdepth[viewer]' (rerun-sdk), got "
                                "no module rerun")
