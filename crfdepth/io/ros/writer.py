"""Writing ROS 1 / ROS 2 bags: ``complete --bag ... --out-bag`` and the example recording (docs/design.md section 11).

:class:`BagWriter` writes a new bag with ``rosbags``' writers: a name ending in ``.bag``
gives a ROS 1 bag, any other name a ROS 2 bag folder (``storage`` mcap or sqlite3). It
builds the messages crfdepth writes, the inverse of :mod:`crfdepth.io.ros.images` and
:mod:`crfdepth.io.ros.messages`:

- :meth:`~BagWriter.image`: ``sensor_msgs/Image`` of an RGB picture (``rgb8``) or of a
  depth map in metres (``32FC1``, :func:`~crfdepth.io.ros.messages.depth_image_fields`);
- :meth:`~BagWriter.camera_info`: ``sensor_msgs/CameraInfo`` of a pinhole camera;
- :meth:`~BagWriter.point_cloud`: ``sensor_msgs/PointCloud2`` with float32 x y z
  [intensity];
- :meth:`~BagWriter.transforms`: ``tf2_msgs/TFMessage`` of rigid transforms.

The bag is written into a hidden folder beside the output and moved into place by
:meth:`~BagWriter.commit` (also on leaving a ``with`` block normally); an exception
inside the block, or :meth:`~BagWriter.abort`, removes it, so a failed run leaves no
partial bag.
"""

from __future__ import annotations

import os
import shutil
import tempfile
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from crfdepth.io.ros.messages import depth_image_fields

__all__ = ["BagWriter"]

_TF_MSG = "geometry_msgs/TransformStamped[] transforms"  # tf2_msgs/TFMessage, missing from rosbags' ROS 1 store
_FLOAT32 = 7  # sensor_msgs/PointField datatype


def _fields(cls, **values) -> dict:
    """``values`` under the field names of message class ``cls`` (ROS 1 spells CameraInfo's K, D, R, P in
    capitals, ROS 2 in lower case; only ROS 1 headers have ``seq``)."""
    names = {name.lower(): name for name in cls.__dataclass_fields__}
    return {names[key.lower()]: value for key, value in values.items() if key.lower() in names}


class BagWriter:
    """A new ROS 1 or ROS 2 bag, written atomically.

    Args:
        path: ``*.bag`` (ROS 1) or a ROS 2 bag folder; must not exist, its folder must.
        storage: for ROS 2, ``"mcap"`` (default) or ``"sqlite3"``.
    """

    def __init__(self, path: str | os.PathLike, *, storage: str = "mcap") -> None:
        from rosbags.typesys import Stores, get_types_from_msg, get_typestore

        self.path = Path(path)
        self.ros1 = self.path.suffix == ".bag"
        self._store = get_typestore(Stores.ROS1_NOETIC if self.ros1 else Stores.ROS2_HUMBLE)
        if "tf2_msgs/msg/TFMessage" not in self._store.types:
            self._store.register(get_types_from_msg(_TF_MSG, "tf2_msgs/msg/TFMessage"))
        self.types = self._store.types
        self._scratch = Path(tempfile.mkdtemp(prefix=f".{self.path.name}.", dir=self.path.parent))
        try:
            self._writer = self._open(self._scratch / self.path.name, storage)
        except BaseException:
            shutil.rmtree(self._scratch, ignore_errors=True)
            raise
        self._connections = {}

    def _open(self, target: Path, storage: str):
        if self.ros1:
            from rosbags.rosbag1 import Writer

            writer = Writer(target)
        else:
            from rosbags.rosbag2 import StoragePlugin, Writer

            plugin = StoragePlugin.MCAP if storage == "mcap" else StoragePlugin.SQLITE3
            writer = Writer(target, version=8, storage_plugin=plugin)
        writer.open()
        return writer

    def __enter__(self) -> BagWriter:
        return self

    def __exit__(self, kind, *exc) -> None:
        if kind is None:
            self.commit()
        else:
            self.abort()

    # ----------------------------------------------------------------------- writing

    def write(self, topic: str, log_ns: int, msg) -> None:
        """Serialise ``msg`` onto ``topic`` at record time ``log_ns`` (the topic is added on first use)."""
        msgtype = msg.__msgtype__
        if topic not in self._connections:
            self._connections[topic] = self._writer.add_connection(topic, msgtype, typestore=self._store)
        raw = self._store.serialize_ros1(msg, msgtype) if self.ros1 else self._store.serialize_cdr(msg, msgtype)
        self._writer.write(self._connections[topic], int(log_ns), raw)

    def commit(self) -> Path:
        """Close the bag and move it to ``path``; returns ``path``."""
        self._writer.close()
        os.replace(self._scratch / self.path.name, self.path)
        shutil.rmtree(self._scratch, ignore_errors=True)
        return self.path

    def abort(self) -> None:
        """Drop the partial bag."""
        try:
            self._writer.close()
        except Exception:  # a writer that failed half-way may not close cleanly; its files go anyway
            pass
        finally:
            shutil.rmtree(self._scratch, ignore_errors=True)

    # ----------------------------------------------------------------------- messages

    def header(self, stamp_ns: int, frame_id: str):
        """``std_msgs/Header`` with ``stamp_ns`` (integer nanoseconds) and ``frame_id``."""
        stamp = self.types["builtin_interfaces/msg/Time"](sec=int(stamp_ns) // 1_000_000_000,
                                                          nanosec=int(stamp_ns) % 1_000_000_000)
        cls = self.types["std_msgs/msg/Header"]
        return cls(**_fields(cls, seq=0, stamp=stamp, frame_id=frame_id))

    def image(self, values: np.ndarray, stamp_ns: int, frame_id: str, encoding: str = "rgb8"):
        """``sensor_msgs/Image``: ``values`` (H, W, 3) uint8 RGB as ``rgb8``, or (H, W) metres as ``32FC1``."""
        header = self.header(stamp_ns, frame_id)
        if encoding == "32FC1":
            return self.types["sensor_msgs/msg/Image"](header=header, **depth_image_fields(values))
        rgb = np.ascontiguousarray(values, dtype=np.uint8)
        height, width = rgb.shape[:2]
        return self.types["sensor_msgs/msg/Image"](header=header, height=height, width=width, encoding="rgb8",
                                                   is_bigendian=0, step=3 * width, data=rgb.reshape(-1))

    def camera_info(self, K: np.ndarray, image_size: tuple[int, int], stamp_ns: int, frame_id: str,
                    distortion: np.ndarray | None = None):
        """``sensor_msgs/CameraInfo``: intrinsics ``K`` (3, 3) of an (height, width) image, ``distortion``
        OpenCV k1 k2 p1 p2 k3 (plumb_bob; None: no distortion), identity rectification."""
        K = np.asarray(K, dtype=np.float64)
        P = np.zeros((3, 4))
        P[:, :3] = K
        d = np.zeros(5) if distortion is None else np.asarray(distortion, dtype=np.float64)
        roi = self.types["sensor_msgs/msg/RegionOfInterest"](x_offset=0, y_offset=0, height=0, width=0,
                                                             do_rectify=False)
        cls = self.types["sensor_msgs/msg/CameraInfo"]
        return cls(**_fields(cls, header=self.header(stamp_ns, frame_id), height=image_size[0], width=image_size[1],
                             distortion_model="plumb_bob" if len(d) == 5 else "rational_polynomial", d=d,
                             k=K.ravel(), r=np.eye(3).ravel(), p=P.ravel(), binning_x=0, binning_y=0, roi=roi))

    def point_cloud(self, points: np.ndarray, stamp_ns: int, frame_id: str):
        """``sensor_msgs/PointCloud2``, unorganised: (N, 3) or (N, 4) x y z [intensity] as float32 fields."""
        table = np.ascontiguousarray(points, dtype="<f4")
        names = ("x", "y", "z", "intensity")[: table.shape[1]]
        field = self.types["sensor_msgs/msg/PointField"]
        fields = [field(name=name, offset=4 * i, datatype=_FLOAT32, count=1) for i, name in enumerate(names)]
        step = 4 * len(names)
        return self.types["sensor_msgs/msg/PointCloud2"](
            header=self.header(stamp_ns, frame_id), height=1, width=len(table), fields=fields, is_bigendian=False,
            point_step=step, row_step=step * len(table), data=table.view(np.uint8).reshape(-1),
            is_dense=bool(np.isfinite(table[:, :3]).all()))

    def transforms(self, edges: list[tuple[str, str, np.ndarray]], stamp_ns: int):
        """``tf2_msgs/TFMessage`` of ``(parent, child, T_parent_child)`` edges (4x4 rigid, metres)."""
        t = self.types
        transforms = []
        for parent, child, T in edges:
            q = Rotation.from_matrix(T[:3, :3]).as_quat()  # x y z w
            transforms.append(t["geometry_msgs/msg/TransformStamped"](
                header=self.header(stamp_ns, parent), child_frame_id=child,
                transform=t["geometry_msgs/msg/Transform"](
                    translation=t["geometry_msgs/msg/Vector3"](x=T[0, 3], y=T[1, 3], z=T[2, 3]),
                    rotation=t["geometry_msgs/msg/Quaternion"](x=q[0], y=q[1], z=q[2], w=q[3]))))
        return t["tf2_msgs/msg/TFMessage"](transforms=transforms)
