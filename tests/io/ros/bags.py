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
from scipy.spatial.transform import Rotation

from crfdepth.data.synthetic import make_scene

IMAGE_TOPIC = "/camera/image_raw"
INFO_TOPIC = "/camera/camera_info"
POINTS_TOPIC = "/velodyne_points"
KINDS = ("ros1", "sqlite3", "mcap")
START_NS = 1_700_000_000_000_000_000  # a 2023 wall-clock time, as real recordings carry
PERIOD_NS = 100_000_000  # 10 Hz camera and LiDAR
_TF_MSG = "geometry_msgs/TransformStamped[] transforms"


def _rigid(rotvec, translation) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = Rotation.from_rotvec(rotvec).as_matrix()
    T[:3, 3] = translation
    return T


# The rig: T_base_lidar and T_base_camlink are arbitrary mounts; camera_link -> camera_optical is
# whatever makes the chain equal the scene's T_cam_lidar.
T_BASE_LIDAR = _rigid([0.0, 0.02, 0.05], [1.1, 0.0, 1.7])
T_BASE_CAMLINK = _rigid([0.01, -0.03, 0.0], [1.5, 0.1, 1.4])


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


def typestore(kind: str):
    from rosbags.typesys import Stores, get_types_from_msg, get_typestore

    store = get_typestore(Stores.ROS1_NOETIC if kind == "ros1" else Stores.ROS2_HUMBLE)
    if "tf2_msgs/msg/TFMessage" not in store.types:  # rosbags' ROS 1 store lacks it
        store.register(get_types_from_msg(_TF_MSG, "tf2_msgs/msg/TFMessage"))
    return store


class BagBuilder:
    """Messages of one type store, serialised and written to a rosbags writer."""

    def __init__(self, path: Path, kind: str) -> None:
        from rosbags.rosbag1 import Writer as Writer1
        from rosbags.rosbag2 import StoragePlugin
        from rosbags.rosbag2 import Writer as Writer2

        self.kind, self.store = kind, typestore(kind)
        self.types = self.store.types
        if kind == "ros1":
            self.writer = Writer1(path)
        else:
            plugin = StoragePlugin.MCAP if kind == "mcap" else StoragePlugin.SQLITE3
            self.writer = Writer2(path, version=9, storage_plugin=plugin)
        self.writer.open()
        self.connections = {}

    def header(self, stamp_ns: int, frame_id: str):
        stamp = self.types["builtin_interfaces/msg/Time"](sec=stamp_ns // 10**9, nanosec=stamp_ns % 10**9)
        cls = self.types["std_msgs/msg/Header"]
        extra = {"seq": 0} if "seq" in cls.__dataclass_fields__ else {}
        return cls(stamp=stamp, frame_id=frame_id, **extra)

    def write(self, topic: str, log_ns: int, msg) -> None:
        msgtype = msg.__msgtype__
        if topic not in self.connections:
            self.connections[topic] = self.writer.add_connection(topic, msgtype, typestore=self.store)
        raw = self.store.serialize_ros1(msg, msgtype) if self.kind == "ros1" else self.store.serialize_cdr(msg, msgtype)
        self.writer.write(self.connections[topic], log_ns, raw)

    def image(self, rgb: np.ndarray, stamp_ns: int, encoding: str = "rgb8", frame_id: str = "camera_optical"):
        if encoding == "jpeg":
            ok, data = cv2.imencode(".jpg", cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR), [cv2.IMWRITE_JPEG_QUALITY, 95])
            return self.types["sensor_msgs/msg/CompressedImage"](
                header=self.header(stamp_ns, frame_id), format="rgb8; jpeg compressed bgr8", data=data.ravel())
        pixels = {"rgb8": rgb, "bgr8": rgb[..., ::-1], "mono8": rgb[..., :1], "bayer_rggb8": rgb[..., :1]}[encoding]
        pixels = np.ascontiguousarray(pixels)
        h, w, c = pixels.shape
        return self.types["sensor_msgs/msg/Image"](header=self.header(stamp_ns, frame_id), height=h, width=w,
                                                   encoding=encoding, is_bigendian=0, step=w * c,
                                                   data=pixels.ravel())

    def camera_info(self, K: np.ndarray, size: tuple[int, int], stamp_ns: int, distortion=None,
                    frame_id: str = "camera_optical"):
        cls = self.types["sensor_msgs/msg/CameraInfo"]
        names = {n.lower(): n for n in cls.__dataclass_fields__}
        P = np.zeros((3, 4))
        P[:, :3] = K
        roi = self.types["sensor_msgs/msg/RegionOfInterest"](x_offset=0, y_offset=0, height=0, width=0,
                                                             do_rectify=False)
        values = dict(header=self.header(stamp_ns, frame_id), height=size[0], width=size[1],
                      distortion_model="plumb_bob", d=np.zeros(5) if distortion is None else np.asarray(distortion),
                      k=np.asarray(K, float).ravel(), r=np.eye(3).ravel(), p=P.ravel(), binning_x=0, binning_y=0,
                      roi=roi)
        return cls(**{names[k]: v for k, v in values.items()})

    def cloud(self, points: np.ndarray, stamp_ns: int, frame_id: str = "velodyne", xyz_type: int = 7):
        """x y z intensity (float32, or ``xyz_type``) and a uint16 ring field, point_step 24."""
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

    def tf(self, edges: list[tuple[str, str, np.ndarray]], stamp_ns: int):
        """A TFMessage of ``(parent, child, T_parent_child)`` edges."""
        t = self.types
        transforms = []
        for parent, child, T in edges:
            q = Rotation.from_matrix(T[:3, :3]).as_quat()
            transforms.append(t["geometry_msgs/msg/TransformStamped"](
                header=self.header(stamp_ns, parent), child_frame_id=child,
                transform=t["geometry_msgs/msg/Transform"](
                    translation=t["geometry_msgs/msg/Vector3"](x=T[0, 3], y=T[1, 3], z=T[2, 3]),
                    rotation=t["geometry_msgs/msg/Quaternion"](x=q[0], y=q[1], z=q[2], w=q[3]))))
        return t["tf2_msgs/msg/TFMessage"](transforms=transforms)

    def close(self) -> None:
        self.writer.close()


def rig_edges(T_cam_lidar: np.ndarray) -> list[tuple[str, str, np.ndarray]]:
    """Three tf edges whose chain velodyne -> camera_optical is ``T_cam_lidar``."""
    T_base_optical = T_BASE_LIDAR @ np.linalg.inv(T_cam_lidar)
    return [("base_link", "velodyne", T_BASE_LIDAR), ("base_link", "camera_link", T_BASE_CAMLINK),
            ("camera_link", "camera_optical", np.linalg.inv(T_BASE_CAMLINK) @ T_base_optical)]


def write_bag(path: Path, kind: str = "mcap", *, count: int = 3, frames=None, encoding: str = "rgb8",
              cloud_offsets_ns=None, image_jitter_ns=None, camera_info: bool = True, tf: bool = True,
              xyz_type: int = 7, size: tuple[int, int] = (64, 96)) -> Recorded:
    """Record ``count`` frames (or ``frames = (images, clouds, K, T_cam_lidar)``) at 10 Hz.

    Cloud k is stamped ``START_NS + k * PERIOD_NS + cloud_offsets_ns[k]`` (default 0), image k
    ``START_NS + k * PERIOD_NS + image_jitter_ns[k]`` (default 0); record times are the stamps plus
    2 ms. A ROS 1 bag is one file (``path`` should end in .bag); a ROS 2 bag a folder.
    """
    images, clouds, K, T = frames if frames is not None else synthetic_frames(count, *size)
    count = len(images)
    cloud_offsets = np.zeros(count, np.int64) if cloud_offsets_ns is None else np.asarray(cloud_offsets_ns)
    jitter = np.zeros(count, np.int64) if image_jitter_ns is None else np.asarray(image_jitter_ns)
    builder = BagBuilder(path, kind)
    recorded = Recorded(path=path, K=K, T_cam_lidar=T)
    if tf:
        builder.write("/tf_static", START_NS - PERIOD_NS, builder.tf(rig_edges(T), START_NS - PERIOD_NS))
    messages = []
    image_topic = IMAGE_TOPIC + "/compressed" if encoding == "jpeg" else IMAGE_TOPIC
    for k in range(count):
        image_ns = START_NS + k * PERIOD_NS + int(jitter[k])
        cloud_ns = START_NS + k * PERIOD_NS + int(cloud_offsets[k])
        messages.append((cloud_ns + 2_000_000, POINTS_TOPIC, builder.cloud(clouds[k], cloud_ns, xyz_type=xyz_type)))
        messages.append((image_ns + 2_000_000, image_topic, builder.image(images[k], image_ns, encoding)))
        if camera_info:
            messages.append((image_ns + 2_000_000, INFO_TOPIC, builder.camera_info(K, images[k].shape[:2], image_ns)))
        recorded.images.append(images[k])
        recorded.clouds.append(clouds[k])
        recorded.image_ns.append(image_ns)
        recorded.cloud_ns.append(cloud_ns)
    for log_ns, topic, msg in sorted(messages, key=lambda m: m[0]):
        builder.write(topic, log_ns, msg)
    builder.close()
    return recorded
