"""crfdepth.io.ros.writer: what BagWriter writes reads back through crfdepth.io.ros.images and .messages, atomically."""

from __future__ import annotations

import numpy as np
import pytest

pytest.importorskip("rosbags")

from crfdepth.io.ros.bag import Recording  # noqa: E402
from crfdepth.io.ros.images import decode_image  # noqa: E402
from crfdepth.io.ros.messages import camera_from_info, points_from_cloud, stamp_ns  # noqa: E402
from crfdepth.io.ros.writer import BagWriter  # noqa: E402

STAMP = 1_700_000_000_123_456_789


@pytest.mark.parametrize("name", ["out.bag", "out_ros2"])
def test_round_trip(tmp_path, name):
    rng = np.random.default_rng(0)
    rgb = rng.integers(0, 256, (5, 7, 3), dtype=np.uint8)
    depth = rng.uniform(1, 80, (5, 7)).astype(np.float32)
    points = rng.normal(size=(50, 4)).astype(np.float32)
    points[3] = np.nan
    K = np.array([[100.0, 0, 3.5], [0, 100.0, 2.5], [0, 0, 1]])
    T = np.eye(4)
    T[:3, 3] = [0.1, -0.2, 0.3]
    T[:3, :3] = np.array([[0, -1, 0], [0, 0, -1], [1, 0, 0]])
    with BagWriter(tmp_path / name) as bag:
        bag.write("/rgb", STAMP, bag.image(rgb, STAMP, "cam"))
        bag.write("/depth", STAMP, bag.image(depth, STAMP, "cam", "32FC1"))
        bag.write("/info", STAMP, bag.camera_info(K, (5, 7), STAMP, "cam", distortion=[0.1, -0.01, 0, 0, 0]))
        bag.write("/points", STAMP, bag.point_cloud(points, STAMP, "lidar"))
        bag.write("/tf_static", STAMP, bag.transforms([("lidar", "cam", T)], STAMP))
    with Recording(tmp_path / name) as recording:
        assert recording.is_ros1 == name.endswith(".bag")
        read = {topic: msg for topic, _, msg in recording.messages(recording.topics)}
        tree = recording.transforms()
    np.testing.assert_array_equal(decode_image(read["/rgb"], "rgb"), rgb)
    assert read["/depth"].encoding == "32FC1" and stamp_ns(read["/depth"].header) == STAMP
    np.testing.assert_array_equal(np.frombuffer(read["/depth"].data.tobytes(), "<f4").reshape(5, 7), depth)
    camera = camera_from_info(read["/info"], "info")
    np.testing.assert_array_equal(camera.K, K)
    np.testing.assert_array_equal(camera.distortion, [0.1, -0.01, 0, 0, 0])
    assert camera.image_size == (5, 7)
    np.testing.assert_array_equal(points_from_cloud(read["/points"], "points"), points[:, :3])
    np.testing.assert_allclose(tree.lookup("lidar", "cam"), T, atol=1e-12)


def test_abort_and_exception_leave_nothing(tmp_path):
    bag = BagWriter(tmp_path / "a.bag")
    bag.write("/rgb", STAMP, bag.image(np.zeros((2, 2, 3), np.uint8), STAMP, "cam"))
    bag.abort()
    with pytest.raises(RuntimeError), BagWriter(tmp_path / "b") as bag:
        bag.write("/rgb", STAMP, bag.image(np.zeros((2, 2, 3), np.uint8), STAMP, "cam"))
        raise RuntimeError("stop")
    assert list(tmp_path.iterdir()) == []
