"""Small ROS 1 / ROS 2 recordings written with rosbags' writers, for the bag tests.

:func:`write_bag` records a few frames of the synthetic street (a different scene per
frame, so that a wrong pairing changes the depth) or given frames: camera images,
CameraInfo, PointCloud2 and the LiDAR -> camera transform as three ``/tf_static`` hops
(velodyne -> base_link -> camera_link -> camera_optical). It returns what it wrote, so
that tests can call :func:`crfdepth.api.complete_depth` on the same arrays.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

from crfdepth.data.example_bag import rig_edges
from crfdepth.data.synthetic import make_scene
from crfdepth.io.ros.writer import BagWriter

IMAGE_TOPIC = "/camera/image_raw"
INFO_TOPIC = "/camera/camera_info"
POINTS_TOPIC = "/velodyne_points"
KINDS = ("ros1", "sqlite3", "mcap")
START_NS = 1_700_000_000_000_000_000  # a 2023 wall-clock time, as real recordings carry
PERIOD_NS = 100_000_000  # 10 Hz camera and LiDAR
__all__ = ["BagBuilder", "rig_edges", "synthetic_frames", "write_bag"]


@dataclass
class Recorded:
    """What :func:`write_bag` wrote: per frame the RGB image (H, W, 3) uint8 and the cloud (N, 4) float32."""

    path: Path
    images: list[np.ndarray] = field(default_factory=list)
    clouds: list[np.ndarray] = field(default_factory=list)
    image_ns: list[int] = field(default_factory=list)
    cloud_ns: list[int] = field(default_factory=list)
    K: np.ndarray | None = None
    T_cam_lidar: np.ndarray | None = None


def synthetic_frames(count: int, height: int = 64, width: int = 96, seed: int = 0):
    """``count`` synthetic frames: (RGB uint8 list, cloud list, K, T_cam_lidar)."""
    scenes = [make_scene(seed + k, height=height, width=width, beams=16) for k in range(count)]
    images = [np.round(s.image * 255).astype(np.uint8) for s in scenes]
    return images, [s.points for s in scenes], scenes[0].K, scenes[0].T_cam_lidar


def _mosaic(rgb: np.ndarray) -> np.ndarray:
    """What an RGGB colour-filter camera records of ``rgb``: (H, W, 1), red at even rows and columns."""
    mosaic = rgb[..., 1].copy()
    mosaic[0::2, 0::2] = rgb[0::2, 0::2, 0]
    mosaic[1::2, 1::2] = rgb[1::2, 1::2, 2]
    return mosaic[..., None]


class BagBuilder(BagWriter):
    """crfdepth's bag writer plus what the tests need beyond it: other image encodings (bgr8, mono8, a
    Bayer pattern, JPEG) and clouds with a ring field and x y z of another type. ``kind`` is
    "ros1" (``path`` ends in .bag), "sqlite3" or "mcap"."""

    def __init__(self, path: Path, kind: str) -> None:
        super().__init__(path, storage=kind)

    def image(self, rgb: np.ndarray, stamp_ns: int, encoding: str = "rgb8", frame_id: str = "camera_optical"):
        if encoding == "rgb8":
            return super().image(rgb, stamp_ns, frame_id)
        if encoding == "jpeg":
            ok, data = cv2.imencode(".jpg", cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR), [cv2.IMWRITE_JPEG_QUALITY, 95])
            return self.types["sensor_msgs/msg/CompressedImage"](
                header=self.header(stamp_ns, frame_id), format="rgb8; jpeg compressed bgr8", data=data.ravel())
        pixels = {"bgr8": rgb[..., ::-1], "mono8": rgb[..., :1], "mono16": np.repeat(rgb[..., :1], 2, axis=2),
                  "bayer_rggb8": _mosaic(rgb)}[encoding]
        pixels = np.ascontiguousarray(pixels)
        h, w, c = pixels.shape
        return self.types["sensor_msgs/msg/Image"](header=self.header(stamp_ns, frame_id), height=h, width=w,
                                                   encoding=encoding, is_bigendian=0, step=w * c,
                                                   data=pixels.ravel())

    def cloud(self, points: np.ndarray, stamp_ns: int, frame_id: str = "velodyne", xyz_type: int = 7):
        """x y z (float32, or PointField type ``xyz_type``), intensity float32 and a uint16 ring field."""
        field_cls = self.types["sensor_msgs/msg/PointField"]
        xyz_dtype = {7: "<f4", 8: "<f8", 3: "<i2"}[xyz_type]
        size = np.dtype(xyz_dtype).itemsize
        dtype = np.dtype({"names": ["x", "y", "z", "intensity", "ring"],
                          "formats": [xyz_dtype] * 3 + ["<f4", "<u2"],
                          "offsets": [0, size, 2 * size, 3 * size, 3 * size + 4], "itemsize": 3 * size + 8})
        table = np.zeros(len(points), dtype=dtype)
        for i, name in enumerate("xyz"):
            table[name] = points[:, i]
        table["intensity"] = points[:, 3] if points.shape[1] > 3 else 0
        table["ring"] = np.arange(len(points)) % 16
        fields = [field_cls(name=n, offset=dtype.fields[n][1], datatype=t, count=1)
                  for n, t in (("x", xyz_type), ("y", xyz_type), ("z", xyz_type), ("intensity", 7), ("ring", 4))]
        return self.types["sensor_msgs/msg/PointCloud2"](
            header=self.header(stamp_ns, frame_id), height=1, width=len(points), fields=fields, is_bigendian=False,
            point_step=dtype.itemsize, row_step=dtype.itemsize * len(points),
            data=np.frombuffer(table.tobytes(), dtype=np.uint8), is_dense=False)

    def close(self) -> None:
        self.commit()


def write_bag(path: Path, kind: str = "mcap", *, count: int = 3, frames=None, encoding: str = "rgb8",
              cloud_offsets_ns=None, image_jitter_ns=None, camera_info: bool = True, tf: str | None = "/tf_static",
              distortion=None, info_size=None, xyz_type: int = 7, size: tuple[int, int] = (64, 96)) -> Recorded:
    """Record ``count`` frames (or ``frames = (images, clouds, K, T_cam_lidar)``) at 10 Hz.

    Cloud k is stamped ``START_NS + k * PERIOD_NS + cloud_offsets_ns[k]`` (default 0), image k
    ``START_NS + k * PERIOD_NS + image_jitter_ns[k]`` (default 0); record times are the stamps plus
    2 ms. The rig's transform goes on ``tf`` (None: nowhere): once on /tf_static, or with every frame on /tf.
    A ROS 1 bag is one file (``path`` should end in .bag); a ROS 2 bag a folder.
    """
    images, clouds, K, T = frames if frames is not None else synthetic_frames(count, *size)
    count = len(images)
    cloud_offsets = np.zeros(count, np.int64) if cloud_offsets_ns is None else np.asarray(cloud_offsets_ns)
    jitter = np.zeros(count, np.int64) if image_jitter_ns is None else np.asarray(image_jitter_ns)
    builder = BagBuilder(path, kind)
    recorded = Recorded(path=path, K=K, T_cam_lidar=T)
    if tf == "/tf_static":
        builder.write(tf, START_NS - PERIOD_NS, builder.transforms(rig_edges(T), START_NS - PERIOD_NS))
    messages = []
    image_topic = IMAGE_TOPIC + "/compressed" if encoding == "jpeg" else IMAGE_TOPIC
    for k in range(count):
        image_ns = START_NS + k * PERIOD_NS + int(jitter[k])
        cloud_ns = START_NS + k * PERIOD_NS + int(cloud_offsets[k])
        messages.append((cloud_ns + 2_000_000, POINTS_TOPIC, builder.cloud(clouds[k], cloud_ns, xyz_type=xyz_type)))
        messages.append((image_ns + 2_000_000, image_topic, builder.image(images[k], image_ns, encoding)))
        if camera_info:
            info = builder.camera_info(K, info_size or images[k].shape[:2], image_ns, "camera_optical", distortion)
            messages.append((image_ns + 2_000_000, INFO_TOPIC, info))
        if tf == "/tf":
            messages.append((image_ns - 1_000_000, tf, builder.transforms(rig_edges(T), image_ns - 3_000_000)))
        recorded.images.append(images[k])
        recorded.clouds.append(clouds[k])
        recorded.image_ns.append(image_ns)
        recorded.cloud_ns.append(cloud_ns)
    for log_ns, topic, msg in sorted(messages, key=lambda m: m[0]):
        builder.write(topic, log_ns, msg)
    builder.close()
    return recorded
