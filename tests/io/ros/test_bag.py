"""crfdepth.io.ros.bag: topic names, storage, stamps (pairing is tested in tests/cli/test_complete_bag.py)."""

from __future__ import annotations

import logging

import numpy as np
import pytest

from crfdepth.errors import InputError
from crfdepth.io.ros.bag import camera_info_topic

pytest.importorskip("rosbags")

from crfdepth.io.ros.bag import Recording  # noqa: E402
from crfdepth.io.ros.writer import BagWriter  # noqa: E402


@pytest.mark.parametrize("image,info", [("/cam/image_raw", "/cam/camera_info"),
                                        ("/cam/image_raw/compressed", "/cam/camera_info"),
                                        ("/stereo/left/image_rect_color", "/stereo/left/camera_info")])
def test_camera_info_topic(image, info):
    assert camera_info_topic(image) == info


def _bag(path, stamps, log_times):
    with BagWriter(path) as bag:
        for stamp, log in zip(stamps, log_times):
            bag.write("/rgb", log, bag.image(np.zeros((2, 3, 3), np.uint8), stamp, "/cam"))
    return path


@pytest.mark.parametrize("name,storage", [("r.bag", "ros1"), ("r2", "mcap")])
def test_scan_stamps_frames_and_storage(tmp_path, name, storage):
    path = _bag(tmp_path / name, [30, 10, 20], [100, 200, 300])
    with Recording(path) as bag:
        assert bag.storage == storage
        stream = bag.scan("/rgb")
    np.testing.assert_array_equal(stream.stamps_ns, [30, 10, 20])  # header stamps, record order
    np.testing.assert_array_equal(stream.log_ns, [100, 200, 300])
    assert stream.frame_ids == ("cam",) * 3  # leading slash of ROS 1 frames dropped


def test_unstamped_topic_uses_record_time(tmp_path, caplog):
    path = _bag(tmp_path / "r.bag", [0, 0], [100, 200])
    with Recording(path) as bag, caplog.at_level(logging.WARNING):
        stream = bag.scan("/rgb")
    np.testing.assert_array_equal(stream.stamps_ns, [100, 200])
    assert "every header.stamp is 0" in caplog.text


def test_ros2_storage_file_opens_too(tmp_path):
    _bag(tmp_path / "r2", [1], [1])
    (data,) = (tmp_path / "r2").glob("*.mcap")
    with Recording(data, "--bag x") as bag:
        assert list(bag.topics) == ["/rgb"]
        with pytest.raises(InputError, match=r"^--points-topic: expected a point cloud topic of --bag x, got "
                                             r"'/p', which is not in it; image topics: /rgb; point-cloud topics: "
                                             r"none$"):
            bag.check_topic("/p", "--points-topic", ("sensor_msgs/msg/PointCloud2",), "point cloud")


def test_missing_path(tmp_path):
    with pytest.raises(FileNotFoundError, match="bag: no such file or folder"):
        Recording(tmp_path / "none.bag")
