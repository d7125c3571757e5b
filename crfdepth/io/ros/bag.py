"""Reading a ROS 1 / ROS 2 recording: topics, time stamps, pairing by time (docs/design.md section 11).

:class:`Recording` opens a ROS 1 ``.bag`` or a ROS 2 bag (a folder with ``metadata.yaml``,
or its ``.db3`` / ``.mcap`` file) with ``rosbags.highlevel.AnyReader``, the pure-Python
reader of the ``rosbags`` package (the optional extra ``crfdepth[ros]``; no ROS
installation). It checks topics and their message types, scans a topic's time stamps
(:meth:`Recording.scan`), reads the transform tree (:meth:`Recording.transforms`) and
streams deserialised messages (:meth:`Recording.messages`).

:func:`pair_nearest` pairs every image with the cloud nearest in time, within a largest
gap. Times are the messages' ``header.stamp`` (the sensor's time), not the time the
recorder received them; a topic whose stamps are all zero (a driver that does not stamp)
falls back to the record time, with a warning.

Every failure is an :class:`~crfdepth.errors.InputError` whose message starts with the
``name`` the caller gives (the command line passes ``--bag <path>``), in one line.
"""

from __future__ import annotations

import logging
import os
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from crfdepth.errors import InputError
from crfdepth.io.ros.messages import stamp_ns
from crfdepth.io.ros.tf import TransformTree

__all__ = ["CLOUD_TYPE", "IMAGE_TYPES", "INFO_TYPE", "TF_TOPICS", "Pairing", "Recording", "Stream",
           "camera_info_topic", "pair_nearest"]

logger = logging.getLogger(__name__)

IMAGE_TYPES = ("sensor_msgs/msg/Image", "sensor_msgs/msg/CompressedImage")
CLOUD_TYPE = "sensor_msgs/msg/PointCloud2"
INFO_TYPE = "sensor_msgs/msg/CameraInfo"
TF_TYPE = "tf2_msgs/msg/TFMessage"
TF_TOPICS = {"/tf_static": True, "/tf": False}  # topic -> static
ROS_EXTRA = "pip install 'crfdepth[ros]'"
_MAX_LISTED = 12  # topics named in a message before "... and N more"


def camera_info_topic(image_topic: str) -> str:
    """The ``camera_info`` topic beside an image topic, as ``image_transport`` names it:
    ``/cam/image_raw`` and ``/cam/image_raw/compressed`` -> ``/cam/camera_info``."""
    base = image_topic.rstrip("/")
    if base.endswith("/compressed"):
        base = base[: -len("/compressed")]
    return f"{base.rsplit('/', 1)[0]}/camera_info"


def _listed(names: Iterable[str]) -> str:
    names = sorted(names)
    if not names:
        return "none"
    more = f" ... and {len(names) - _MAX_LISTED} more" if len(names) > _MAX_LISTED else ""
    return ", ".join(names[:_MAX_LISTED]) + more


@dataclass(frozen=True)
class Stream:
    """The messages of one topic, in record order.

    Attributes:
        topic: the topic name.
        stamps_ns: (N,) int64 ``header.stamp`` of each message, nanoseconds (the record time
            when the topic never stamps its headers).
        log_ns: (N,) int64 time the recorder received each message, nanoseconds.
        frame_ids: ``header.frame_id`` of each message.
    """

    topic: str
    stamps_ns: np.ndarray
    log_ns: np.ndarray
    frame_ids: tuple[str, ...]

    def __len__(self) -> int:
        return len(self.stamps_ns)


@dataclass(frozen=True)
class Pairing:
    """Images paired with clouds by time (:func:`pair_nearest`).

    Attributes:
        cloud: (N_images,) int64 index of each image's cloud in the cloud stream, -1 when
            no cloud is within the largest gap.
        gap_ns: (N_images,) int64 absolute time from each image to its nearest cloud,
            nanoseconds (also for unpaired images).
    """

    cloud: np.ndarray
    gap_ns: np.ndarray

    @property
    def paired(self) -> int:
        return int(np.sum(self.cloud >= 0))


def pair_nearest(image_ns: np.ndarray, cloud_ns: np.ndarray, max_gap_ns: int) -> Pairing:
    """Pair each image with the cloud nearest in time, when at most ``max_gap_ns`` away.

    Args:
        image_ns: (N,) int64 image times, nanoseconds, any order.
        cloud_ns: (M,) int64 cloud times, nanoseconds, any order; M >= 1.
        max_gap_ns: the largest accepted ``|t_image - t_cloud|``, nanoseconds. Of two clouds
            equally near, the earlier wins.

    Returns:
        :class:`Pairing` with indices into ``cloud_ns``.
    """
    image_ns = np.asarray(image_ns, dtype=np.int64)
    cloud_ns = np.asarray(cloud_ns, dtype=np.int64)
    order = np.argsort(cloud_ns, kind="stable")
    sorted_ns = cloud_ns[order]
    right = np.clip(np.searchsorted(sorted_ns, image_ns), 0, len(sorted_ns) - 1)
    left = np.clip(right - 1, 0, len(sorted_ns) - 1)
    gap_left = np.abs(image_ns - sorted_ns[left])
    gap_right = np.abs(sorted_ns[right] - image_ns)
    nearest = np.where(gap_left <= gap_right, left, right)
    gap = np.minimum(gap_left, gap_right)
    cloud = np.where(gap <= max_gap_ns, order[nearest], -1)
    return Pairing(cloud=cloud.astype(np.int64), gap_ns=gap.astype(np.int64))


def _bag_errors() -> tuple[type[BaseException], ...]:
    """What rosbags and its storage back ends raise for a damaged recording."""
    import sqlite3
    import struct

    from rosbags.highlevel import AnyReaderError
    from rosbags.rosbag1 import ReaderError as Ros1Error
    from rosbags.rosbag2 import ReaderError as Ros2Error

    return AnyReaderError, Ros1Error, Ros2Error, sqlite3.Error, struct.error, EOFError, OSError, KeyError, ValueError


class Recording:
    """An open ROS 1 or ROS 2 recording; use as a context manager.

    Args:
        path: a ROS 1 ``.bag`` file, a ROS 2 bag folder (with ``metadata.yaml``), or the
            ``.db3`` / ``.mcap`` file of one.
        name: how messages name the recording (the command line: ``--bag <path>``).

    Raises:
        FileNotFoundError: ``path`` does not exist.
        InputError: ``rosbags`` is not installed, or the file is not a readable bag
            (truncated, damaged, another format).
    """

    def __init__(self, path: str | os.PathLike, name: str = "bag") -> None:
        self.path = Path(path)
        self.name = name
        if not self.path.exists():
            raise FileNotFoundError(f"{name}: no such file or folder: {self.path}")
        try:
            from rosbags.highlevel import AnyReader
        except ImportError:
            raise InputError(f"{name}: reading ROS bags needs the rosbags package, which is not installed; "
                             f"install it with: {ROS_EXTRA}") from None
        self._errors = _bag_errors()
        try:
            self._reader = AnyReader([self.path])
            self._reader.open()
        except self._errors as exc:
            raise self._unreadable(exc) from None
        self.is_ros1 = not self._reader.is2
        self.topics = {topic: info.msgtype for topic, info in self._reader.topics.items()}

    def _unreadable(self, exc: BaseException) -> InputError:
        reason = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
        return InputError(f"{self.name}: expected a readable ROS 1 .bag or ROS 2 bag (sqlite3 or mcap), got one "
                          f"that cannot be read ({reason}): truncated, damaged or not a bag")

    @property
    def storage(self) -> str:
        """``"ros1"``, ``"sqlite3"`` or ``"mcap"``."""
        if self.is_ros1:
            return "ros1"
        files = [self.path] if self.path.is_file() else list(self.path.iterdir())
        return "mcap" if any(f.suffix == ".mcap" for f in files) else "sqlite3"

    def __enter__(self) -> Recording:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def close(self) -> None:
        self._reader.close()

    def topics_of(self, msgtypes: Iterable[str]) -> list[str]:
        """The recording's topics carrying any of ``msgtypes``, sorted."""
        wanted = set(msgtypes)
        return sorted(topic for topic, msgtype in self.topics.items() if msgtype in wanted)

    def listing(self, *msgtypes: str) -> str:
        """The recording's image and point-cloud topics (and those of ``msgtypes``), for messages."""
        groups = [("image", IMAGE_TYPES), ("point-cloud", (CLOUD_TYPE,))]
        groups += [(t.rsplit("/", 1)[-1], (t,)) for t in msgtypes if t not in (*IMAGE_TYPES, CLOUD_TYPE)]
        return "; ".join(f"{what} topics: {_listed(self.topics_of(types))}" for what, types in groups)

    def check_topic(self, topic: str, flag: str, msgtypes: tuple[str, ...], what: str) -> str:
        """``topic``'s message type, refused (naming ``flag``) when the topic is missing or of another type;
        the message lists the recording's image and point-cloud topics (and those of ``msgtypes``)."""
        short = " or ".join(t.replace("/msg/", "/") for t in msgtypes)
        if topic not in self.topics:
            raise InputError(f"{flag}: expected a {what} topic of {self.name}, got {topic!r}, which is not in it; "
                             f"{self.listing(*msgtypes)}")
        if self.topics[topic] not in msgtypes:
            raise InputError(f"{flag}: expected a topic of {short}, got {topic!r} of "
                             f"{self.topics[topic].replace('/msg/', '/')}; {self.listing(*msgtypes)}")
        return self.topics[topic]

    def messages(self, topics: Iterable[str]) -> Iterator[tuple[str, int, object]]:
        """``(topic, record time ns, deserialised message)`` of ``topics``, in record order."""
        topics = set(topics)
        connections = [c for c in self._reader.connections if c.topic in topics]
        if not connections:  # (rosbags reads every connection for an empty list)
            return
        try:
            for connection, log_ns, raw in self._reader.messages(connections=connections):
                yield connection.topic, int(log_ns), self._reader.deserialize(raw, connection.msgtype)
        except self._errors as exc:
            raise self._unreadable(exc) from None

    def scan(self, topic: str, check: Callable[[object, str], None] | None = None, flag: str = "topic") -> Stream:
        """Time stamps and frame ids of every message of ``topic``; ``check(msg, where)`` on each
        (``where``: ``"<flag> <topic> (message at <stamp> ns)"``)."""
        stamps, logs, frames = [], [], []
        for _, log_ns, msg in self.messages([topic]):
            stamps.append(stamp_ns(msg.header))
            logs.append(log_ns)
            frames.append(msg.header.frame_id.lstrip("/"))
            if check is not None:
                check(msg, f"{flag} {topic} (message at {stamps[-1]} ns)")
        stamps_ns = np.asarray(stamps, dtype=np.int64)
        if len(stamps_ns) and not stamps_ns.any():
            logger.warning("%s: every header.stamp is 0; pairing by the time the recorder received the messages",
                           topic)
            stamps_ns = np.asarray(logs, dtype=np.int64)
        return Stream(topic, stamps_ns, np.asarray(logs, dtype=np.int64), tuple(frames))

    def transforms(self) -> TransformTree:
        """The transform tree of ``/tf_static`` and ``/tf`` (empty when the recording has neither)."""
        tree = TransformTree()
        topics = [t for t in TF_TOPICS if self.topics.get(t) == TF_TYPE]
        for topic, _, msg in self.messages(topics):
            tree.add_message(msg, static=TF_TOPICS[topic])
        return tree
