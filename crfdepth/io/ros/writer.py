"""Writing completed depth back into a recording: ``complete --bag ... --out-bag`` (docs/design.md section 11).

:class:`DepthBagWriter` writes the depth (and std) of each frame as ``sensor_msgs/Image``
``32FC1`` (metres, float32; :func:`~crfdepth.io.ros.messages.depth_image_fields`) with
the camera image's own header (stamp and ``frame_id``), and a ``sensor_msgs/CameraInfo``
of the depth image (its ``K``, no distortion: the depth belongs to the undistorted
image), so that it plays back beside the input in RViz or Foxglove (RViz's DepthCloud
display needs both). A name ending in ``.bag`` gives a ROS 1 bag; any other name a ROS 2
bag folder, in the input's storage format (mcap for a ROS 1 input).

The bag is written into a hidden folder beside the output and moved into place by
:meth:`DepthBagWriter.commit`; :meth:`~DepthBagWriter.abort` (or an exception inside a
``with`` block) removes it, so a failed run leaves no partial bag.
"""

from __future__ import annotations

import os
import shutil
import tempfile
from pathlib import Path

import numpy as np

from crfdepth.io.ros.messages import depth_image_fields

__all__ = ["DepthBagWriter"]

_IMAGE = "sensor_msgs/msg/Image"
_INFO = "sensor_msgs/msg/CameraInfo"


def _fields(cls, **values) -> dict:
    """``values`` under the field names of message class ``cls`` (ROS 1 spells CameraInfo's K, D, R, P in
    capitals, ROS 2 in lower case)."""
    names = {name.lower(): name for name in cls.__dataclass_fields__}
    return {names[key.lower()]: value for key, value in values.items() if key.lower() in names}


class DepthBagWriter:
    """Depth images into a new ROS 1 or ROS 2 bag.

    Args:
        path: the output: ``*.bag`` (ROS 1) or a ROS 2 bag folder; must not exist.
        storage: for ROS 2, ``"mcap"`` or ``"sqlite3"``.
        topics: message type of each output topic, e.g. ``{"/cam/crfdepth/depth":
            "sensor_msgs/msg/Image", "/cam/crfdepth/camera_info": "sensor_msgs/msg/CameraInfo"}``.
    """

    def __init__(self, path: str | os.PathLike, *, storage: str, topics: dict[str, str]) -> None:
        from rosbags.typesys import Stores, get_typestore

        self.path = Path(path)
        self.ros1 = self.path.suffix == ".bag"
        self._store = get_typestore(Stores.ROS1_NOETIC if self.ros1 else Stores.ROS2_HUMBLE)
        self._scratch = Path(tempfile.mkdtemp(prefix=f".{self.path.name}.", dir=self.path.parent))
        self._writer = self._open(self._scratch / self.path.name, storage)
        self._connections = {topic: self._writer.add_connection(topic, msgtype, typestore=self._store)
                             for topic, msgtype in topics.items()}
        self._seq = 0

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

    def __enter__(self) -> DepthBagWriter:
        return self

    def __exit__(self, kind, *exc) -> None:
        if kind is not None:
            self.abort()

    def _header(self, stamp_ns: int, frame_id: str):
        types = self._store.types
        stamp = types["builtin_interfaces/msg/Time"](sec=stamp_ns // 1_000_000_000, nanosec=stamp_ns % 1_000_000_000)
        return types["std_msgs/msg/Header"](**_fields(types["std_msgs/msg/Header"], seq=self._seq, stamp=stamp,
                                                      frame_id=frame_id))

    def _write(self, topic: str, log_ns: int, msg) -> None:
        msgtype = msg.__msgtype__
        raw = self._store.serialize_ros1(msg, msgtype) if self.ros1 else self._store.serialize_cdr(msg, msgtype)
        self._writer.write(self._connections[topic], log_ns, raw)

    def write_image(self, topic: str, log_ns: int, stamp_ns: int, frame_id: str, values: np.ndarray) -> None:
        """``values`` (H, W) float32 metres as a 32FC1 image with the given header, at record time ``log_ns``."""
        image = self._store.types[_IMAGE](header=self._header(stamp_ns, frame_id), **depth_image_fields(values))
        self._write(topic, log_ns, image)

    def write_camera_info(self, topic: str, log_ns: int, stamp_ns: int, frame_id: str, K: np.ndarray,
                          image_size: tuple[int, int]) -> None:
        """The pinhole camera of the depth images: ``K``, no distortion, identity rectification."""
        types = self._store.types
        P = np.zeros((3, 4))
        P[:, :3] = K
        roi_cls = types["sensor_msgs/msg/RegionOfInterest"]
        roi = roi_cls(x_offset=0, y_offset=0, height=0, width=0, do_rectify=False)
        info_cls = types[_INFO]
        info = info_cls(**_fields(info_cls, header=self._header(stamp_ns, frame_id), height=image_size[0],
                                  width=image_size[1], distortion_model="plumb_bob", d=np.zeros(5),
                                  k=np.asarray(K, dtype=np.float64).ravel(), r=np.eye(3).ravel(), p=P.ravel(),
                                  binning_x=0, binning_y=0, roi=roi))
        self._write(topic, log_ns, info)
        self._seq += 1

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
        finally:
            shutil.rmtree(self._scratch, ignore_errors=True)
