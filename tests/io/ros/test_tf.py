"""Tests of crfdepth.io.ros.tf: the /tf_static + /tf transform tree.

Oracle: 4x4 matrices built here with NumPy from the quaternion formula (no scipy), composed
by hand; known answers (the optical-frame rotation, a yaw ramp); real rosbags messages.
"""

import math

import numpy as np
import pytest

from crfdepth.errors import InputError
from crfdepth.io.ros.tf import TransformError, TransformTree

OPTICAL_Q = (-0.5, 0.5, -0.5, 0.5)  # camera body (x fwd, y left, z up) -> optical (x right, y down, z fwd)


def quat_matrix(q):
    """Rotation matrix of a unit quaternion (x, y, z, w), the textbook formula."""
    x, y, z, w = np.asarray(q, dtype=np.float64) / np.linalg.norm(q)
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
        [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
        [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
    ])


def rigid(t, q):
    T = np.eye(4)
    T[:3, :3] = quat_matrix(q)
    T[:3, 3] = t
    return T


def yaw_q(angle):
    return (0.0, 0.0, math.sin(angle / 2), math.cos(angle / 2))


# A rig: base_link -> lidar, base_link -> camera -> camera_optical.
LIDAR = ((1.2, 0.0, 1.7), (0.0, 0.0, 0.0087265, 0.9999619))          # 1 degree yaw
CAMERA = ((1.5, 0.1, 1.3), (0.0, 0.0436194, 0.0, 0.9990482))         # 5 degree pitch
OPTICAL = ((0.0, 0.0, 0.0), OPTICAL_Q)


@pytest.fixture
def rig():
    tree = TransformTree()
    tree.add("base_link", "lidar", *LIDAR, 0, static=True)
    tree.add("base_link", "camera", *CAMERA, 0, static=True)
    tree.add("camera", "camera_optical", *OPTICAL, 0, static=True)
    return tree


def test_optical_quaternion_oracle():
    # Optical z (forward) is body x, optical x (right) is body -y, optical y (down) is body -z.
    np.testing.assert_allclose(quat_matrix(OPTICAL_Q), [[0, 0, 1], [-1, 0, 0], [0, -1, 0]], atol=1e-15)


def test_two_hops(rig):
    expected = np.linalg.inv(rigid(*CAMERA)) @ rigid(*LIDAR)
    T = rig.lookup("camera", "lidar")
    assert T.shape == (4, 4) and T.dtype == np.float64
    np.testing.assert_allclose(T, expected, atol=1e-12)
    assert rig.path("camera", "lidar") == ["lidar", "base_link", "camera"]


def test_three_hops(rig):
    expected = np.linalg.inv(rigid(*CAMERA) @ rigid(*OPTICAL)) @ rigid(*LIDAR)
    np.testing.assert_allclose(rig.lookup("camera_optical", "lidar"), expected, atol=1e-12)
    assert rig.path("camera_optical", "lidar") == ["lidar", "base_link", "camera", "camera_optical"]
    assert rig.path("lidar", "camera_optical") == ["camera_optical", "camera", "base_link", "lidar"]


def test_inverse_direction(rig):
    for a, b in [("camera_optical", "lidar"), ("camera", "lidar"), ("base_link", "camera_optical")]:
        np.testing.assert_allclose(rig.lookup(a, b), np.linalg.inv(rig.lookup(b, a)), atol=1e-12)


def test_ancestor_either_way(rig):
    T_base_optical = rigid(*CAMERA) @ rigid(*OPTICAL)
    np.testing.assert_allclose(rig.lookup("base_link", "camera_optical"), T_base_optical, atol=1e-12)
    np.testing.assert_allclose(rig.lookup("camera_optical", "base_link"), np.linalg.inv(T_base_optical), atol=1e-12)
    assert rig.path("base_link", "camera_optical") == ["camera_optical", "camera", "base_link"]
    assert rig.path("camera_optical", "base_link") == ["base_link", "camera", "camera_optical"]


def test_same_frame_identity(rig):
    np.testing.assert_array_equal(rig.lookup("camera", "camera"), np.eye(4))
    np.testing.assert_array_equal(rig.lookup("/camera", "camera"), np.eye(4))
    assert rig.path("camera", "camera") == ["camera"]
    assert not rig.has_dynamic("camera", "camera")


def test_frames_sorted(rig):
    assert rig.frames == ["base_link", "camera", "camera_optical", "lidar"]


def test_point_ahead_of_lidar_lands_on_optical_axis():
    tree = TransformTree()
    tree.add("base_link", "velodyne", (0.0, 0.0, 1.8), (0, 0, 0, 1), 0, static=True)
    tree.add("base_link", "camera", (0.0, 0.0, 1.8), (0, 0, 0, 1), 0, static=True)
    tree.add("camera", "camera_optical", (0, 0, 0), OPTICAL_Q, 0, static=True)
    point = tree.lookup("camera_optical", "velodyne") @ np.array([10.0, 0.0, 0.0, 1.0])
    np.testing.assert_allclose(point[:3], [0.0, 0.0, 10.0], atol=1e-12)
    # 1 m to the left (+y body) is 1 m to the left in the image (-x optical); 1 m up is -y.
    point = tree.lookup("camera_optical", "velodyne") @ np.array([10.0, 1.0, 1.0, 1.0])
    np.testing.assert_allclose(point[:3], [-1.0, -1.0, 10.0], atol=1e-12)


def test_leading_slashes_equivalent():
    plain, slashed = TransformTree(), TransformTree()
    plain.add("base_link", "velodyne", *LIDAR, 0, static=True)
    plain.add("base_link", "camera", *CAMERA, 0, static=True)
    slashed.add("/base_link", "/velodyne", *LIDAR, 0, static=True)
    slashed.add("base_link", "//camera", *CAMERA, 0, static=True)  # same parent, written two ways
    assert slashed.frames == ["base_link", "camera", "velodyne"]
    expected = plain.lookup("camera", "velodyne")
    for target, source in [("camera", "velodyne"), ("/camera", "/velodyne"), ("camera", "/velodyne")]:
        np.testing.assert_allclose(slashed.lookup(target, source), expected, atol=1e-15)
    assert slashed.path("/camera", "velodyne") == ["velodyne", "base_link", "camera"]


def test_quaternion_normalised():
    tree = TransformTree()
    tree.add("a", "b", (1, 2, 3), (0, 0, 0, 2.0), 0, static=True)
    tree.add("a", "c", (0, 0, 0), np.array(yaw_q(0.3)) * 3, 0, static=True)
    np.testing.assert_allclose(tree.lookup("a", "b"), rigid((1, 2, 3), (0, 0, 0, 1)), atol=1e-15)
    np.testing.assert_allclose(tree.lookup("a", "c")[:3, :3], quat_matrix(yaw_q(0.3)), atol=1e-12)


def test_static_replaced_by_later_static():
    tree = TransformTree()
    tree.add("base_link", "lidar", (1, 0, 0), (0, 0, 0, 1), 5, static=True)
    tree.add("base_link", "lidar", (2, 0, 0), (0, 0, 0, 1), 1, static=True)
    np.testing.assert_allclose(tree.lookup("base_link", "lidar")[:3, 3], [2, 0, 0])
    np.testing.assert_allclose(tree.lookup("base_link", "lidar", 0)[:3, 3], [2, 0, 0])
    assert not tree.has_dynamic("base_link", "lidar")


@pytest.fixture
def moving():
    """odom -> base_link on /tf: at 1 s (0, 0, 0) yaw 0; at 3 s (2, 4, 0) yaw 90 deg; base_link -> lidar static."""
    tree = TransformTree()
    tree.add("odom", "base_link", (2.0, 4.0, 0.0), yaw_q(math.pi / 2), 3_000_000_000, static=False)  # out of order
    tree.add("odom", "base_link", (0.0, 0.0, 0.0), yaw_q(0.0), 1_000_000_000, static=False)
    tree.add("base_link", "lidar", (1.0, 0.0, 0.0), (0, 0, 0, 1), 0, static=True)
    return tree


def test_dynamic_interpolated_halfway(moving):
    T = moving.lookup("odom", "base_link", 2_000_000_000)
    np.testing.assert_allclose(T[:3, 3], [1.0, 2.0, 0.0], atol=1e-12)
    np.testing.assert_allclose(T[:3, :3], quat_matrix(yaw_q(math.pi / 4)), atol=1e-12)
    angle = math.degrees(math.acos((np.trace(T[:3, :3]) - 1) / 2))
    assert angle == pytest.approx(45.0, abs=1e-9)
    # A quarter of the way: translation a quarter, angle a quarter (Slerp is constant speed).
    T = moving.lookup("odom", "base_link", 1_500_000_000)
    np.testing.assert_allclose(T[:3, 3], [0.5, 1.0, 0.0], atol=1e-12)
    np.testing.assert_allclose(T[:3, :3], quat_matrix(yaw_q(math.pi / 8)), atol=1e-12)


def test_dynamic_composed_with_static(moving):
    T = moving.lookup("odom", "lidar", 2_000_000_000)
    expected = rigid((1.0, 2.0, 0.0), yaw_q(math.pi / 4)) @ rigid((1.0, 0.0, 0.0), (0, 0, 0, 1))
    np.testing.assert_allclose(T, expected, atol=1e-12)
    np.testing.assert_allclose(moving.lookup("lidar", "odom", 2_000_000_000), np.linalg.inv(expected), atol=1e-12)
    assert moving.has_dynamic("lidar", "odom") and moving.has_dynamic("odom", "base_link")
    assert not moving.has_dynamic("base_link", "lidar")


def test_dynamic_held_outside_range_and_latest(moving):
    first = rigid((0.0, 0.0, 0.0), yaw_q(0.0))
    last = rigid((2.0, 4.0, 0.0), yaw_q(math.pi / 2))
    np.testing.assert_allclose(moving.lookup("odom", "base_link", 0), first, atol=1e-12)
    np.testing.assert_allclose(moving.lookup("odom", "base_link", 1_000_000_000), first, atol=1e-12)
    np.testing.assert_allclose(moving.lookup("odom", "base_link", 3_000_000_000), last, atol=1e-12)
    np.testing.assert_allclose(moving.lookup("odom", "base_link", 10**12), last, atol=1e-12)
    np.testing.assert_allclose(moving.lookup("odom", "base_link"), last, atol=1e-12)


def test_dynamic_sample_added_later_is_used(moving):
    moving.add("odom", "base_link", (5.0, 0.0, 0.0), (0, 0, 0, 1), 4_000_000_000, static=False)
    np.testing.assert_allclose(moving.lookup("odom", "base_link")[:3, 3], [5.0, 0.0, 0.0])
    # Same stamp again: the later sample replaces the earlier.
    moving.add("odom", "base_link", (6.0, 0.0, 0.0), (0, 0, 0, 1), 4_000_000_000, static=False)
    np.testing.assert_allclose(moving.lookup("odom", "base_link")[:3, 3], [6.0, 0.0, 0.0])


def test_two_parents_refused(rig):
    with pytest.raises(TransformError, match=r"'lidar'.*'base_link'.*'camera'"):
        rig.add("camera", "lidar", (0, 0, 0), (0, 0, 0, 1), 0, static=True)
    with pytest.raises(TransformError, match="two parents"):
        rig.add("/camera", "/lidar", (0, 0, 0), (0, 0, 0, 1), 0, static=False)
    rig.add("/base_link", "lidar", (0, 0, 0), (0, 0, 0, 1), 0, static=True)  # the same parent is fine


def test_cycle_refused(rig):
    with pytest.raises(TransformError, match="cycle"):
        rig.add("camera_optical", "base_link", (0, 0, 0), (0, 0, 0, 1), 0, static=True)
    assert rig.path("lidar", "camera_optical")[-1] == "lidar"  # the tree is unchanged


def test_bad_values_refused():
    tree = TransformTree()
    with pytest.raises(TransformError, match="different from its parent"):
        tree.add("/a", "a", (0, 0, 0), (0, 0, 0, 1), 0, static=True)
    with pytest.raises(TransformError, match="non-zero quaternion"):
        tree.add("a", "b", (0, 0, 0), (0, 0, 0, 0), 0, static=True)
    with pytest.raises(TransformError, match="quaternion.*finite"):
        tree.add("a", "b", (0, 0, 0), (0, 0, math.nan, 1), 0, static=True)
    with pytest.raises(TransformError, match="translation.*finite"):
        tree.add("a", "b", (0, math.inf, 0), (0, 0, 0, 1), 0, static=False)
    with pytest.raises(TransformError, match="translation.*3 numbers"):
        tree.add("a", "b", (0, 0), (0, 0, 0, 1), 0, static=True)
    with pytest.raises(TransformError, match="non-empty frame name"):
        tree.add("/", "b", (0, 0, 0), (0, 0, 0, 1), 0, static=True)
    with pytest.raises(TransformError, match="stamp_ns"):
        tree.add("a", "b", (0, 0, 0), (0, 0, 0, 1), 1.5, static=False)
    assert tree.frames == []  # nothing stored by a refused edge
    assert issubclass(TransformError, InputError) and issubclass(TransformError, ValueError)


def test_unconnected_frames_message(rig):
    rig.add("velodyne", "os_sensor", (0, 0, 0), (0, 0, 0, 1), 0, static=True)
    with pytest.raises(TransformError) as info:
        rig.lookup("camera_optical", "velodyne")
    message = str(info.value)
    assert "\n" not in message
    assert "'velodyne'" in message and "'camera_optical'" in message
    assert "not connected" in message and "unknown" not in message
    assert "{base_link, camera, camera_optical, lidar}" in message
    assert "{velodyne, os_sensor}" in message
    for call in (rig.path, rig.has_dynamic):
        with pytest.raises(TransformError, match="not connected"):
            call("camera_optical", "os_sensor")


def test_unknown_frame_message(rig):
    with pytest.raises(TransformError) as info:
        rig.lookup("camera_optical", "/velodyne")
    message = str(info.value)
    assert "frame 'velodyne' is unknown" in message and "'camera_optical'" in message
    assert "{base_link, camera, camera_optical, lidar}" in message
    with pytest.raises(TransformError, match="frames 'nope' and 'velodyne' are unknown"):
        rig.lookup("velodyne", "nope")
    with pytest.raises(TransformError, match="none"):
        TransformTree().lookup("camera", "velodyne")


def test_unconnected_message_kept_short():
    tree = TransformTree()
    for i in range(30):
        tree.add("root", f"f{i:02d}", (0, 0, 0), (0, 0, 0, 1), 0, static=True)
    for i in range(15):
        tree.add(f"island{i:02d}", f"leaf{i:02d}", (0, 0, 0), (0, 0, 0, 1), 0, static=True)
    with pytest.raises(TransformError) as info:
        tree.lookup("f00", "leaf03")
    message = str(info.value)
    assert "{root, f00, f01" in message and "... and 21 more}" in message
    assert "more groups" in message
    assert len(message) < 400


def test_dynamic_and_static_for_one_child_refused_at_lookup():
    tree = TransformTree()
    tree.add("base_link", "lidar", (0, 0, 0), (0, 0, 0, 1), 0, static=True)
    tree.add("base_link", "lidar", (1, 0, 0), (0, 0, 0, 1), 5, static=False)
    tree.add("base_link", "camera", (0, 0, 0), (0, 0, 0, 1), 0, static=True)
    np.testing.assert_array_equal(tree.lookup("base_link", "camera"), np.eye(4))  # other chains unaffected
    with pytest.raises(TransformError, match="'lidar' is published on both /tf_static and /tf"):
        tree.lookup("camera", "lidar")


def test_add_message_rejects_other_objects():
    with pytest.raises(TransformError, match="TFMessage"):
        TransformTree().add_message(object(), static=True)
    with pytest.raises(TransformError, match="TransformStamped"):
        TransformTree().add_message(type("M", (), {"transforms": [object()]})(), static=True)


# -- real rosbags messages -------------------------------------------------------------


def _tf_message(store, transforms):
    """A TFMessage of ``store`` from (parent, child, sec, nanosec, translation, quaternion) rows."""
    types = store.types
    Time, Header = types["builtin_interfaces/msg/Time"], types["std_msgs/msg/Header"]
    Vector3, Quaternion = types["geometry_msgs/msg/Vector3"], types["geometry_msgs/msg/Quaternion"]
    Transform, TransformStamped = types["geometry_msgs/msg/Transform"], types["geometry_msgs/msg/TransformStamped"]
    entries = []
    for parent, child, sec, nanosec, t, q in transforms:
        stamp = Time(sec=sec, nanosec=nanosec)
        header = Header(seq=0, stamp=stamp, frame_id=parent) if "seq" in Header.__dataclass_fields__ else \
            Header(stamp=stamp, frame_id=parent)
        transform = Transform(translation=Vector3(x=t[0], y=t[1], z=t[2]),
                              rotation=Quaternion(x=q[0], y=q[1], z=q[2], w=q[3]))
        entries.append(TransformStamped(header=header, child_frame_id=child, transform=transform))
    return types["tf2_msgs/msg/TFMessage"](transforms=entries)


def _store(name):
    typesys = pytest.importorskip("rosbags.typesys")
    store = typesys.get_typestore(getattr(typesys.Stores, name))
    if "tf2_msgs/msg/TFMessage" not in store.types:  # ROS 1 bags carry the definition; the store lacks it
        store.register(typesys.get_types_from_msg("geometry_msgs/TransformStamped[] transforms",
                                                  "tf2_msgs/msg/TFMessage"))
    return store


def _roundtrip(store, name, msg):
    """Serialise and deserialise ``msg`` as a recording would hold it."""
    if name.startswith("ROS1"):
        return store.deserialize_ros1(store.serialize_ros1(msg, msg.__msgtype__), msg.__msgtype__)
    return store.deserialize_cdr(store.serialize_cdr(msg, msg.__msgtype__), msg.__msgtype__)


@pytest.mark.parametrize("name", ["ROS2_HUMBLE", "ROS1_NOETIC"])
def test_add_message_rosbags(name):
    store = _store(name)
    slash = "/" if name.startswith("ROS1") else ""  # ROS 1 tf often wrote "/base_link"
    static = _tf_message(store, [
        (f"{slash}base_link", f"{slash}velodyne", 0, 0, LIDAR[0], LIDAR[1]),
        (f"{slash}base_link", f"{slash}camera", 0, 0, CAMERA[0], CAMERA[1]),
        (f"{slash}camera", f"{slash}camera_optical", 0, 0, OPTICAL[0], OPTICAL[1]),
    ])
    dynamic = [
        _tf_message(store, [("odom", "base_link", 100, 0, (0.0, 0.0, 0.0), yaw_q(0.0))]),
        _tf_message(store, [("odom", "base_link", 100, 500_000_000, (3.0, 0.0, 0.0), yaw_q(math.pi / 3))]),
    ]
    tree = TransformTree()
    tree.add_message(_roundtrip(store, name, static), static=True)
    for msg in dynamic:
        tree.add_message(_roundtrip(store, name, msg), static=False)
    assert tree.frames == ["base_link", "camera", "camera_optical", "odom", "velodyne"]
    expected = np.linalg.inv(rigid(*CAMERA) @ rigid(*OPTICAL)) @ rigid(*LIDAR)
    np.testing.assert_allclose(tree.lookup("camera_optical", "velodyne"), expected, atol=1e-12)
    assert not tree.has_dynamic("camera_optical", "velodyne")
    T = tree.lookup("odom", "base_link", 100_250_000_000)  # halfway: stamp = sec * 1e9 + nanosec
    np.testing.assert_allclose(T[:3, 3], [1.5, 0.0, 0.0], atol=1e-12)
    np.testing.assert_allclose(T[:3, :3], quat_matrix(yaw_q(math.pi / 6)), atol=1e-12)
    assert tree.has_dynamic("camera_optical", "odom")
    assert tree.path("camera_optical", "odom") == ["odom", "base_link", "camera", "camera_optical"]
