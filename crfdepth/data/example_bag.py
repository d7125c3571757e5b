"""An example ROS recording of the synthetic street, to try ``crfdepth complete --bag`` on.

``python -m crfdepth.data.example_bag street.bag`` (ROS 1; a name without ``.bag`` gives a
ROS 2 bag folder, mcap, or sqlite3 with ``--storage sqlite3``) writes a few frames of the
own-sensor example's street (:func:`crfdepth.data.example.example_scene`, one scene per
frame), recorded the way a robot's drivers publish them:

- ``/camera/image_raw``: ``sensor_msgs/Image`` rgb8, 640 x 480, 10 Hz, frame ``camera_optical``;
- ``/camera/camera_info``: its ``sensor_msgs/CameraInfo`` (no distortion);
- ``/velodyne_points``: ``sensor_msgs/PointCloud2`` x y z intensity, 16 beams, 10 Hz,
  frame ``velodyne``, stamped 12 ms after the images (the two sensors are not triggered
  together);
- ``/tf_static``: the mounts as three transforms, ``base_link -> velodyne``, ``base_link
  -> camera_link`` and ``camera_link -> camera_optical`` (:func:`rig_edges`), whose
  chain is the scene's ``T_cam_lidar``.

It needs the optional extra ``crfdepth[ros]`` (rosbags). The output is the same on every
run (fixed seeds and times).
"""

from __future__ import annotations

import argparse
import os
import sys
from collections.abc import Sequence
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from crfdepth.data.example import EXAMPLE_SEED, example_scene
from crfdepth.errors import InputError

__all__ = ["EXAMPLE_TOPICS", "T_BASE_CAMLINK", "T_BASE_LIDAR", "main", "rig_edges", "write_example_bag"]

EXAMPLE_TOPICS = {"image": "/camera/image_raw", "camera_info": "/camera/camera_info", "points": "/velodyne_points"}
START_NS = 1_700_000_000_000_000_000  # a wall-clock time of 2023, as real recordings carry
PERIOD_NS = 100_000_000  # 10 Hz camera and LiDAR
CLOUD_DELAY_NS = 12_000_000


def _rigid(rotvec, translation) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = Rotation.from_rotvec(rotvec).as_matrix()
    T[:3, 3] = translation
    return T


# Where the two sensors are mounted on the robot (base_link: x forward, y left, z up), metres.
T_BASE_LIDAR = _rigid([0.0, 0.02, 0.05], [1.1, 0.0, 1.7])
T_BASE_CAMLINK = _rigid([0.01, -0.03, 0.0], [1.5, 0.1, 1.4])


def rig_edges(T_cam_lidar: np.ndarray) -> list[tuple[str, str, np.ndarray]]:
    """Three tf edges ``(parent, child, T_parent_child)`` whose chain from ``velodyne`` to
    ``camera_optical`` is ``T_cam_lidar``: the two mounts above and, from ``camera_link``
    to the optical frame (x right, y down, z forward), whatever closes the chain."""
    T_base_optical = T_BASE_LIDAR @ np.linalg.inv(T_cam_lidar)
    return [("base_link", "velodyne", T_BASE_LIDAR), ("base_link", "camera_link", T_BASE_CAMLINK),
            ("camera_link", "camera_optical", np.linalg.inv(T_BASE_CAMLINK) @ T_base_optical)]


def write_example_bag(path: str | os.PathLike, *, frames: int = 5, seed: int = EXAMPLE_SEED,
                      storage: str = "mcap") -> Path:
    """Write the example recording (module docstring) to ``path``; returns it.

    Args:
        path: ``*.bag`` for ROS 1, another name for a ROS 2 bag folder; must not exist.
        frames: number of camera frames (and clouds), >= 1.
        seed: frame k is ``example_scene(seed + k)``.
        storage: ``"mcap"`` or ``"sqlite3"``, for ROS 2.

    Raises:
        InputError: ``path`` exists or its folder does not; bad ``frames`` or ``storage``.
    """
    from crfdepth.io.ros.writer import BagWriter

    path = Path(path)
    if path.exists():
        raise InputError(f"path: expected a new bag, got {path}, which exists")
    if not path.parent.is_dir():
        raise InputError(f"path: the folder of {path} does not exist")
    if not isinstance(frames, int) or frames < 1:
        raise InputError(f"frames: expected an integer >= 1, got {frames!r}")
    if storage not in ("mcap", "sqlite3"):
        raise InputError(f"storage: expected 'mcap' or 'sqlite3', got {storage!r}")
    with BagWriter(path, storage=storage) as bag:
        for k in range(frames):
            scene = example_scene(seed + k)
            if k == 0:
                bag.write("/tf_static", START_NS - PERIOD_NS,
                          bag.transforms(rig_edges(scene.T_cam_lidar), START_NS - PERIOD_NS))
            stamp = START_NS + k * PERIOD_NS
            rgb = np.clip(np.rint(scene.image * 255.0), 0, 255).astype(np.uint8)
            bag.write(EXAMPLE_TOPICS["image"], stamp + 3_000_000, bag.image(rgb, stamp, "camera_optical"))
            bag.write(EXAMPLE_TOPICS["camera_info"], stamp + 3_000_000,
                      bag.camera_info(scene.K, rgb.shape[:2], stamp, "camera_optical"))
            cloud_stamp = stamp + CLOUD_DELAY_NS
            bag.write(EXAMPLE_TOPICS["points"], cloud_stamp + 5_000_000,
                      bag.point_cloud(scene.points, cloud_stamp, "velodyne"))
    return path


def main(argv: Sequence[str] | None = None) -> int:
    """``python -m crfdepth.data.example_bag OUT [--frames N] [--storage mcap|sqlite3]``; exit status."""
    parser = argparse.ArgumentParser(prog="python -m crfdepth.data.example_bag",
                                     description="Write an example ROS recording of the synthetic street: "
                                                 "OUT.bag (ROS 1) or a ROS 2 bag folder OUT.")
    parser.add_argument("out", metavar="OUT", help="OUT.bag for ROS 1, or a new folder name for ROS 2")
    parser.add_argument("--frames", type=int, default=5, help="camera frames (default 5)")
    parser.add_argument("--storage", choices=("mcap", "sqlite3"), default="mcap", help="ROS 2 storage (default mcap)")
    args = parser.parse_args(argv)
    try:
        path = write_example_bag(args.out, frames=args.frames, storage=args.storage)
    except (InputError, ImportError) as exc:
        message = f"{exc}; install it with: pip install 'crfdepth[ros]'" if isinstance(exc, ImportError) else exc
        print(f"error: {message}", file=sys.stderr)
        return 2
    topics = ", ".join([*EXAMPLE_TOPICS.values(), "/tf_static"])
    print(f"wrote {path}: {args.frames} frame(s) on {topics}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
