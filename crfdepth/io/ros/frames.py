"""A ROS bag's camera images paired with LiDAR clouds, as ``complete --bag`` and ``targets --bag`` read them.

Pass 1 (:func:`plan_frames`) checks the topics and their types, every image encoding and
cloud layout, the CameraInfo and the LiDAR -> camera transform of every pair (or takes
``--calib``), and pairs each image with the cloud nearest in ``header.stamp`` within
``--max-dt``; :func:`paired_frames` then reads the pairs in image order and
:func:`decode_frame` decodes one (docs/design.md section 11). What to read is a
:class:`FrameTopics` (or any object with its attributes, such as the command line's options); errors
name the options as the commands spell them (``--image-topic``, ``--calib`` ...).
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from crfdepth.errors import InputError
from crfdepth.io.calibration import RigCalibration, load_any_calibration
from crfdepth.io.decoder_noise import quiet_decoders
from crfdepth.io.file_errors import flagged
from crfdepth.io.ros.bag import (
    CLOUD_TYPE,
    IMAGE_TYPES,
    INFO_TYPE,
    Pairing,
    Recording,
    Stream,
    camera_info_topic,
    pair_nearest,
)
from crfdepth.io.ros.images import decode_image
from crfdepth.io.ros.messages import camera_from_info, points_from_cloud
from crfdepth.io.ros.tf import TransformTree

__all__ = ["DEFAULT_MAX_DT_S", "FrameTopics", "Plan", "decode_frame", "paired_frames", "plan_frames"]

# A 10 Hz LiDAR (the common rate) sweeps in 0.1 s: within half a sweep, every image of a
# continuous recording has a cloud, and a cloud is never paired across a whole sweep.
DEFAULT_MAX_DT_S = 0.05


@dataclass(frozen=True)
class FrameTopics:
    """What to read of a bag: the camera image and point-cloud topics, the CameraInfo topic (None: the
    ``camera_info`` topic beside the images), or a calibration file ``calib`` (a rig YAML/JSON or KITTI
    calibration, :func:`crfdepth.io.calibration.load_any_calibration`, with its KITTI ``camera``) that replaces
    the CameraInfo and the /tf transform; ``rectified``: the images are rectified already (also assumed for an
    image topic whose last name holds ``rect``)."""

    image_topic: str
    points_topic: str
    camera_info_topic: str | None = None
    calib: str | Path | None = None
    camera: int = 2
    rectified: bool = False


def _decode_quietly(msg, where: str) -> np.ndarray:
    """:func:`crfdepth.io.ros.images.decode_image` with the decoders' C warnings held back
    (:func:`~crfdepth.io.decoder_noise.quiet_decoders`): a CompressedImage that does not decode is told by
    its message alone."""
    with quiet_decoders():
        return decode_image(msg, where)


# --------------------------------------------------------------------------- the plan (pass 1)


@dataclass
class Plan:
    """What pass 1 found: streams, pairing and each paired frame's calibration."""

    images: Stream
    clouds: Stream
    pairing: Pairing
    calibrations: dict[int, RigCalibration] = field(default_factory=dict)  # image index -> calibration
    duplicates: int = 0
    tree: TransformTree | None = None  # /tf_static + /tf (None with --calib)


def _check_each_layout(decode, key, sizes: list | None = None):
    """A ``scan`` check decoding the first message of each distinct layout ``key(msg)`` (encoding, size ...);
    appends each message's (height, width) to ``sizes`` when given (that of its layout's first message)."""
    seen = {}

    def check(msg, where):
        if key(msg) not in seen:
            seen[key(msg)] = decode(msg, where).shape[:2]
        if sizes is not None:
            sizes.append(seen[key(msg)])
    return check


def _image_key(msg):
    """Raw images: encoding and size; compressed ones: the format (their size is known only by decoding)."""
    return getattr(msg, "encoding", None), getattr(msg, "format", None), getattr(msg, "height", 0), \
        getattr(msg, "width", 0), getattr(msg, "step", 0)


def _cloud_key(msg):
    return tuple((f.name, f.offset, f.datatype, f.count) for f in msg.fields), msg.point_step, msg.is_bigendian


def _camera_infos(bag: Recording, topics: FrameTopics) -> tuple[str, np.ndarray, list]:
    """Record times and :class:`~crfdepth.io.ros.messages.CameraModel` s of the CameraInfo topic."""
    default = topics.camera_info_topic is None
    topic = camera_info_topic(topics.image_topic) if default else topics.camera_info_topic
    flag = "--camera-info-topic" + (f" (default: {topic}, beside --image-topic)" if default else "")
    if topic not in bag.topics and default:
        raise InputError(f"{flag}: no CameraInfo for the images: {bag.name} has no topic {topic}; "
                         f"{bag.listing(INFO_TYPE)}; name one with --camera-info-topic, or give the camera and "
                         f"the transform with --calib FILE")
    bag.check_topic(topic, flag, (INFO_TYPE,), "CameraInfo")
    rectified = topics.rectified or "rect" in topics.image_topic.rstrip("/").split("/")[-1]
    times, cameras = [], []
    for _, log_ns, msg in bag.messages([topic]):
        times.append(log_ns)
        cameras.append(camera_from_info(msg, f"--camera-info-topic {topic} (CameraInfo recorded at {log_ns} ns)",
                                        rectified=rectified))
    if not cameras:
        raise InputError(f"{flag}: no CameraInfo message on {topic} in {bag.name}; give the camera with --calib FILE")
    return topic, np.asarray(times, dtype=np.int64), cameras


def _drop_duplicates(images: Stream, pairing: Pairing) -> int:
    """Unpair later images whose stamp repeats an earlier paired one (their PNG names would collide)."""
    seen, dropped = set(), 0
    for i in np.flatnonzero(pairing.cloud >= 0):
        if int(images.stamps_ns[i]) in seen:
            pairing.cloud[i] = -1
            dropped += 1
        seen.add(int(images.stamps_ns[i]))
    return dropped


def _no_pairs(topics: FrameTopics, images: Stream, clouds: Stream, pairing: Pairing, max_dt: float) -> InputError:
    closest = pairing.gap_ns.min() / 1e9
    return InputError(
        f"--max-dt {max_dt:g}: no image of {topics.image_topic} has a cloud of {topics.points_topic} within "
        f"{max_dt:g} s; "
        f"the closest gap is {closest:.6g} s (image stamps {images.stamps_ns.min() / 1e9:.3f}-"
        f"{images.stamps_ns.max() / 1e9:.3f} s, cloud stamps {clouds.stamps_ns.min() / 1e9:.3f}-"
        f"{clouds.stamps_ns.max() / 1e9:.3f} s): do the two sensors stamp with different clocks?")


def plan_frames(bag: Recording, topics: FrameTopics, max_dt: float) -> Plan:
    """Pass 1 over ``bag``: the topics checked, each image paired with the cloud nearest in stamp
    within ``max_dt`` seconds, and each paired frame's calibration; bad input raises ``InputError`` naming the
    option."""
    bag.check_topic(topics.image_topic, "--image-topic", IMAGE_TYPES, "camera image")
    bag.check_topic(topics.points_topic, "--points-topic", (CLOUD_TYPE,), "point cloud")
    calibration = None
    if topics.calib is not None:
        with flagged("--calib", topics.calib, labels=("calibration",)):
            calibration = load_any_calibration(topics.calib, camera=topics.camera)
    else:
        info_topic, info_times, cameras = _camera_infos(bag, topics)
    sizes = []
    images = bag.scan(topics.image_topic, _check_each_layout(_decode_quietly, _image_key, sizes), "--image-topic")
    clouds = bag.scan(topics.points_topic, _check_each_layout(points_from_cloud, _cloud_key), "--points-topic")
    for flag, stream in (("--image-topic", images), ("--points-topic", clouds)):
        if len(stream) == 0:
            raise InputError(f"{flag} {stream.topic}: no message in {bag.name}")
    pairing = pair_nearest(images.stamps_ns, clouds.stamps_ns, round(max_dt * 1e9))
    if pairing.paired == 0:
        raise _no_pairs(topics, images, clouds, pairing, max_dt)
    plan = Plan(images, clouds, pairing, duplicates=_drop_duplicates(images, pairing))
    tree = plan.tree = bag.transforms() if calibration is None else None
    for i in np.flatnonzero(pairing.cloud >= 0):
        if calibration is not None:
            if calibration.image_size not in (None, sizes[i]):
                (h, w), (hc, wc) = sizes[i], calibration.image_size
                raise InputError(f"--calib {topics.calib}: expected the calibration of the {w}x{h} (WxH) images of "
                                 f"--image-topic, got one of {wc}x{hc}")
            plan.calibrations[int(i)] = calibration
            continue
        camera_frame, lidar_frame = images.frame_ids[i], clouds.frame_ids[pairing.cloud[i]]
        for flag, frame in (("--image-topic", camera_frame), ("--points-topic", lidar_frame)):
            if not frame:
                raise InputError(f"{flag}: header.frame_id is empty, so the LiDAR -> camera transform cannot be "
                                 f"looked up in /tf_static or /tf; give it with --calib FILE")
        try:
            T = tree.lookup(camera_frame, lidar_frame, int(images.stamps_ns[i]))
        except InputError as exc:
            raise InputError(f"--points-topic / --image-topic: {exc}; or give the transform with --calib FILE") \
                from None
        camera = cameras[int(np.argmin(np.abs(info_times - images.log_ns[i])))]
        if camera.image_size != sizes[i]:
            (h, w), (hc, wc) = sizes[i], camera.image_size
            raise InputError(f"--camera-info-topic {info_topic}: expected the camera of the {w}x{h} (WxH) images of "
                             f"--image-topic, got a CameraInfo of {wc}x{hc}")
        plan.calibrations[int(i)] = RigCalibration(
            K=camera.K, T_cam_lidar=T, distortion=camera.distortion, image_size=camera.image_size,
            source=f"CameraInfo {info_topic}, tf {lidar_frame} -> {camera_frame}")
    return plan


# --------------------------------------------------------------------------- pass 2


def paired_frames(bag: Recording, topics: FrameTopics, plan: Plan, skip=frozenset()):
    """``(image index, image message, cloud message, cloud index)`` of every paired frame not in ``skip``, in
    image order, holding only the clouds that a waiting image still needs."""
    cloud_of = plan.pairing.cloud.copy()
    cloud_of[list(skip)] = -1
    users = np.bincount(cloud_of[cloud_of >= 0], minlength=len(plan.clouds))
    clouds, waiting = {}, deque()
    counters = {topics.image_topic: 0, topics.points_topic: 0}
    for topic, _, msg in bag.messages([topics.image_topic, topics.points_topic]):
        index = counters[topic]
        counters[topic] += 1
        if topic == topics.image_topic and cloud_of[index] >= 0:
            waiting.append((index, msg))
        elif topic == topics.points_topic and users[index]:
            clouds[index] = msg
        while waiting and cloud_of[waiting[0][0]] in clouds:
            image_index, image = waiting.popleft()
            c = int(cloud_of[image_index])
            yield image_index, image, clouds[c], c
            users[c] -= 1
            if not users[c]:
                del clouds[c]


def decode_frame(topics: FrameTopics, plan: Plan, i: int, image_msg, cloud_msg, c: int):
    """A paired frame's RGB image, finite (N, 3) points and the names of its parts for error messages."""
    stamp = int(plan.images.stamps_ns[i])
    where_image = f"--image-topic {topics.image_topic} (image at {stamp} ns)"
    where_cloud = f"--points-topic {topics.points_topic} (cloud at {int(plan.clouds.stamps_ns[c])} ns)"
    rgb = _decode_quietly(image_msg, where_image)
    xyz = points_from_cloud(cloud_msg, where_cloud)
    xyz = xyz[np.isfinite(xyz).all(axis=1)]
    if xyz.shape[0] == 0:
        raise InputError(f"{where_cloud}: no point with finite coordinates")
    flags = {"image": where_image, "points": where_cloud, "*": f"{where_cloud} with {where_image}",
             "K": f"camera of {where_image}", "T_cam_lidar": f"transform of {where_cloud}"}
    return rgb, xyz, flags
