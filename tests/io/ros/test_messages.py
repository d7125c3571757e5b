"""Tests of crfdepth.io.ros.images and crfdepth.io.ros.messages: images (raw encodings with padded rows, JPEG/PNG),
CameraInfo (ROS 1 and ROS 2 field names, distortion models, refusals), PointCloud2 layouts
(float32/float64, big-endian, organised with padded rows) and the 32FC1 depth image fields.

Messages are plain ``types.SimpleNamespace`` objects or real rosbags messages round-tripped
through ROS 1 / CDR serialisation, so their data arrays are exactly what a bag reader yields.
"""

from __future__ import annotations

import dataclasses
import sys
import warnings
from types import SimpleNamespace

import cv2
import numpy as np
import pytest

from crfdepth.errors import InputError
from crfdepth.io.ros.images import IMAGE_ENCODINGS, decode_image
from crfdepth.io.ros.messages import CameraModel, camera_from_info, depth_image_fields, points_from_cloud, stamp_ns

WHERE = "--image-topic /cam/image_raw (image at 1700000000123456789 ns)"
STORES = ["ROS1_NOETIC", "ROS2_HUMBLE"]
K = [500.0, 0.0, 320.0, 0.0, 510.0, 240.0, 0.0, 0.0, 1.0]
P = [480.0, 0.0, 318.0, 0.0, 0.0, 481.0, 242.0, 0.0, 0.0, 0.0, 1.0, 0.0]
R = [1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0]
PLUMB_BOB = [-0.28, 0.07, 0.001, -0.002, 0.01]
RATIONAL = [0.5, -0.1, 0.001, -0.002, 0.02, 0.8, -0.05, 0.03]
FLOAT32, FLOAT64, INT16, UINT16 = 7, 8, 3, 4


def raises(match_parts, call, *args, **kwargs) -> str:
    """Run ``call``, expect an InputError whose single line starts with its ``where`` and holds ``match_parts``."""
    with pytest.raises(InputError) as info:
        call(*args, **kwargs)
    message = str(info.value)
    assert "\n" not in message
    if any(arg is WHERE for arg in args):
        assert message.startswith(WHERE + ": "), message
    for part in match_parts:
        assert part in message, (part, message)
    return message


# --------------------------------------------------------------------------- rosbags helpers


@pytest.fixture(params=STORES)
def store(request):
    """(typestore, is_ros1) for ROS 1 Noetic and ROS 2 Humble."""
    typesys = pytest.importorskip("rosbags.typesys")
    name = request.param
    return typesys.get_typestore(getattr(typesys.Stores, name)), name.startswith("ROS1")


def make_header(typestore, sec=1_700_000_000, nanosec=123_456_789, frame_id="camera"):
    """A std_msgs/Header of the store (ROS 1 has ``seq``)."""
    Header = typestore.types["std_msgs/msg/Header"]
    stamp = typestore.types["builtin_interfaces/msg/Time"](sec=sec, nanosec=nanosec)
    if "seq" in Header.__dataclass_fields__:
        return Header(seq=7, stamp=stamp, frame_id=frame_id)
    return Header(stamp=stamp, frame_id=frame_id)


def roundtrip(typestore, is_ros1, msg):
    """``msg`` serialised and deserialised as a bag reader would give it."""
    msgtype = msg.__msgtype__
    if is_ros1:
        return typestore.deserialize_ros1(typestore.serialize_ros1(msg, msgtype), msgtype)
    return typestore.deserialize_cdr(typestore.serialize_cdr(msg, msgtype), msgtype)


# --------------------------------------------------------------------------- stamps


def test_stamp_ns_is_exact_for_large_seconds():
    header = SimpleNamespace(stamp=SimpleNamespace(sec=1_700_000_000, nanosec=123_456_789))
    assert stamp_ns(header) == 1_700_000_000_123_456_789
    assert int(1_700_000_000 * 1e9 + 123_456_789) != 1_700_000_000_123_456_789  # float would round
    big = SimpleNamespace(stamp=SimpleNamespace(sec=np.uint32(2**32 - 1), nanosec=np.uint32(999_999_999)))
    assert stamp_ns(big) == (2**32 - 1) * 1_000_000_000 + 999_999_999
    assert type(stamp_ns(big)) is int


def test_stamp_ns_of_rosbags_headers(store):
    typestore, is_ros1 = store
    Image = typestore.types["sensor_msgs/msg/Image"]
    msg = Image(header=make_header(typestore, sec=2_000_000_001, nanosec=999_999_999), height=0, width=0,
                encoding="rgb8", is_bigendian=0, step=0, data=np.zeros(0, np.uint8))
    assert stamp_ns(roundtrip(typestore, is_ros1, msg).header) == 2_000_000_001_999_999_999


def test_stamp_ns_refuses_bad_nanoseconds():
    raises(["header.stamp.nanosec", "1000000000"], stamp_ns,
           SimpleNamespace(stamp=SimpleNamespace(sec=1, nanosec=1_000_000_000)))
    raises(["header:"], stamp_ns, SimpleNamespace())


# --------------------------------------------------------------------------- raw images


RGB = np.random.default_rng(0).integers(0, 256, size=(3, 4, 3), dtype=np.uint8)
GREY = RGB[:, :, 1]


def raw_pixels(encoding: str) -> tuple[np.ndarray, np.ndarray]:
    """(pixels as stored in the message (H, W, C), the expected RGB decoding (H, W, 3))."""
    alpha = np.full(RGB.shape[:2] + (1,), 77, np.uint8)
    return {
        "rgb8": (RGB, RGB),
        "bgr8": (RGB[:, :, ::-1], RGB),
        "rgba8": (np.concatenate([RGB, alpha], axis=2), RGB),
        "bgra8": (np.concatenate([RGB[:, :, ::-1], alpha], axis=2), RGB),
        "mono8": (GREY[:, :, None], np.repeat(GREY[:, :, None], 3, axis=2)),
    }[encoding]


def image_msg(encoding: str, pixels: np.ndarray, padding: int = 0, **overrides) -> SimpleNamespace:
    """A sensor_msgs/Image namespace with ``padding`` junk bytes (0xEE) after every row."""
    height, width, channels = pixels.shape
    step = width * channels + padding
    rows = np.full((height, step), 0xEE, np.uint8)
    rows[:, :width * channels] = pixels.reshape(height, -1)
    fields = dict(height=height, width=width, encoding=encoding, is_bigendian=0, step=step, data=rows.tobytes())
    return SimpleNamespace(**{**fields, **overrides})


@pytest.mark.parametrize("encoding", ["rgb8", "bgr8", "mono8", "rgba8", "bgra8"])
@pytest.mark.parametrize("padding", [0, 5])
def test_every_encoding_decodes_to_rgb(encoding, padding):
    stored, expected = raw_pixels(encoding)
    image = decode_image(image_msg(encoding, stored, padding), WHERE)
    assert image.shape == (3, 4, 3) and image.dtype == np.uint8
    assert image.flags.c_contiguous and image.flags.writeable
    np.testing.assert_array_equal(image, expected)


def test_decoded_image_is_a_copy_of_the_message_data():
    data = np.ascontiguousarray(RGB).reshape(-1).copy()
    msg = SimpleNamespace(height=3, width=4, encoding="rgb8", is_bigendian=0, step=12, data=data)
    image = decode_image(msg, WHERE)
    image[:] = 0
    np.testing.assert_array_equal(data, RGB.reshape(-1))


@pytest.mark.parametrize("encoding", ["rgb8", "bgr8", "mono8"])
def test_rosbags_image_roundtrip(store, encoding):
    typestore, is_ros1 = store
    stored, expected = raw_pixels(encoding)
    ns = image_msg(encoding, stored, padding=3)
    Image = typestore.types["sensor_msgs/msg/Image"]
    msg = Image(header=make_header(typestore), height=ns.height, width=ns.width, encoding=encoding,
                is_bigendian=0, step=ns.step, data=np.frombuffer(ns.data, np.uint8).copy())
    np.testing.assert_array_equal(decode_image(roundtrip(typestore, is_ros1, msg), WHERE), expected)


@pytest.mark.parametrize("encoding", ["16UC1", "32FC1"])
def test_depth_encodings_are_named_as_depth_images(encoding):
    msg = image_msg(encoding, np.zeros((2, 2, 4), np.uint8))
    raises([WHERE + ": ", encoding, "depth image, not a camera image", "rgb8, bgr8, mono8, rgba8, bgra8"],
           decode_image, msg, WHERE)


# ROS names a Bayer pattern by its first row, OpenCV by the second pixel of the second row: ROS's
# rggb is OpenCV's BayerBG (as cv_bridge converts it).
BAYER = {"bayer_rggb8": cv2.COLOR_BayerBG2RGB, "bayer_bggr8": cv2.COLOR_BayerRG2RGB,
         "bayer_gbrg8": cv2.COLOR_BayerGR2RGB, "bayer_grbg8": cv2.COLOR_BayerGB2RGB}


@pytest.mark.parametrize("encoding", list(BAYER))
def test_bayer_images_are_demosaiced(encoding):
    pytest.importorskip("rosbags.image")
    rng = np.random.default_rng(1)
    mosaic = rng.integers(0, 256, (6, 8), dtype=np.uint8)
    padded = np.zeros((6, 10), np.uint8)
    padded[:, :8] = mosaic  # two bytes of row padding
    msg = SimpleNamespace(encoding=encoding, height=6, width=8, step=10, is_bigendian=0, data=padded.ravel())
    np.testing.assert_array_equal(decode_image(msg, WHERE), cv2.cvtColor(mosaic, BAYER[encoding]))


def test_rggb_pattern_is_red_first():
    """A red scene seen through an RGGB filter (red on even rows and columns) decodes red."""
    pytest.importorskip("rosbags.image")
    mosaic = np.zeros((8, 8), np.uint8)
    mosaic[0::2, 0::2] = 200
    msg = SimpleNamespace(encoding="bayer_rggb8", height=8, width=8, step=8, is_bigendian=0, data=mosaic.ravel())
    rgb = decode_image(msg, WHERE)
    assert rgb[2:6, 2:6, 0].min() > 150 and rgb[2:6, 2:6, 1:].max() < 60


def test_yuv422_is_converted():
    pytest.importorskip("rosbags.image")
    grey = np.full((4, 6, 2), 128, np.uint8)  # U = V = 128: no colour
    grey[:, :, 1] = 90  # uyvy: the second byte of each pixel is its luma
    msg = SimpleNamespace(encoding="uyvy", height=4, width=6, step=12, is_bigendian=0, data=grey.ravel())
    rgb = decode_image(msg, WHERE)
    np.testing.assert_array_equal(rgb, cv2.cvtColor(grey, cv2.COLOR_YUV2RGB_UYVY))
    assert (rgb == rgb[0, 0, 0]).all()  # grey stays grey (86: OpenCV's video-range luma)


def test_bayer_without_rosbags_image_names_the_extra(monkeypatch):
    monkeypatch.setitem(sys.modules, "rosbags.image", None)
    msg = SimpleNamespace(encoding="bayer_rggb8", height=2, width=2, step=2, is_bigendian=0,
                          data=np.zeros(4, np.uint8))
    raises([WHERE + ": ", "bayer_rggb8", "rosbags-image", "pip install 'crfdepth[ros]'"], decode_image, msg, WHERE)


@pytest.mark.parametrize("encoding", ["bayer_rggb16", "mono16", "rgb16", "8UC3", "nv12"])
def test_unsupported_encodings_list_the_supported_ones(encoding):
    msg = image_msg(encoding, np.zeros((2, 2, 2), np.uint8))
    message = raises([WHERE + ": ", f"unsupported encoding '{encoding}'", "rgb8, bgr8, mono8, rgba8, bgra8"],
                     decode_image, msg, WHERE)
    assert "depth" not in message


def test_raw_image_size_errors():
    stored, _ = raw_pixels("rgb8")
    msg = image_msg("rgb8", stored, padding=2)
    msg.data = msg.data[:-1]
    raises([WHERE + ": ", "truncated", "3 * 14 = 42", "got 41"], decode_image, msg, WHERE)
    raises(["step >= width * channels = 4 * 3 = 12", "got step 10"], decode_image,
           image_msg("rgb8", stored, step=10), WHERE)
    raises(["height", ">= 1", "got 0"], decode_image, image_msg("rgb8", stored, height=0), WHERE)
    raises(["width", "got -4"], decode_image, image_msg("rgb8", stored, width=-4), WHERE)
    raises(["data as bytes or a 1-D uint8 array", "int64"], decode_image,
           image_msg("rgb8", stored, data=np.zeros(36, np.int64)), WHERE)
    raises(["sensor_msgs/Image", "sensor_msgs/CompressedImage"], decode_image, SimpleNamespace(data=b""), WHERE)


# --------------------------------------------------------------------------- compressed images


def smooth_rgb(height: int = 48, width: int = 64) -> np.ndarray:
    """A smooth colour image JPEG keeps within a few grey levels."""
    v, u = np.mgrid[0:height, 0:width]
    return np.stack([4 * u, 5 * v, 255 - 2 * u - 2 * v], axis=2).clip(0, 255).astype(np.uint8)


def compressed_msg(fmt: str, data) -> SimpleNamespace:
    return SimpleNamespace(format=fmt, data=np.frombuffer(bytes(data), np.uint8))


@pytest.mark.parametrize("fmt", ["jpeg", "rgb8; jpeg compressed bgr8"])
def test_compressed_jpeg(fmt):
    rgb = smooth_rgb()
    ok, jpeg = cv2.imencode(".jpg", rgb[:, :, ::-1], [cv2.IMWRITE_JPEG_QUALITY, 95])
    assert ok
    image = decode_image(compressed_msg(fmt, jpeg), WHERE)
    assert image.shape == rgb.shape and image.dtype == np.uint8 and image.flags.c_contiguous
    np.testing.assert_array_equal(image, cv2.imdecode(jpeg, cv2.IMREAD_COLOR)[:, :, ::-1])
    assert np.abs(image.astype(int) - rgb).mean() < 2.0


@pytest.mark.parametrize("fmt", ["png", "bgr8; png compressed bgr8"])
def test_compressed_png_is_exact(fmt):
    ok, png = cv2.imencode(".png", RGB[:, :, ::-1].copy())
    assert ok
    np.testing.assert_array_equal(decode_image(compressed_msg(fmt, png), WHERE), RGB)


def test_compressed_grey_png_is_replicated():
    ok, png = cv2.imencode(".png", GREY.copy())
    assert ok
    np.testing.assert_array_equal(decode_image(compressed_msg("mono8; png compressed mono8", png), WHERE),
                                  np.repeat(GREY[:, :, None], 3, axis=2))


def test_rosbags_compressed_image_roundtrip(store):
    typestore, is_ros1 = store
    ok, png = cv2.imencode(".png", RGB[:, :, ::-1].copy())
    CompressedImage = typestore.types["sensor_msgs/msg/CompressedImage"]
    msg = CompressedImage(header=make_header(typestore), format="bgr8; png compressed bgr8", data=png.reshape(-1))
    np.testing.assert_array_equal(decode_image(roundtrip(typestore, is_ros1, msg), WHERE), RGB)


def test_compressed_refusals():
    ok, png16 = cv2.imencode(".png", np.full((4, 5), 4000, np.uint16))
    assert ok
    raises([WHERE + ": ", "16-bit PNG", "not an 8-bit camera image"], decode_image,
           compressed_msg("png", png16), WHERE)
    raises([WHERE + ": ", "compressedDepth", "depth image, not a camera image"], decode_image,
           compressed_msg("16UC1; compressedDepth png", png16), WHERE)
    garbage = np.random.default_rng(1).integers(0, 256, 200, dtype=np.uint8).tobytes()
    raises([WHERE + ": ", "could not be decoded as JPEG/PNG", "200 bytes"], decode_image,
           compressed_msg("jpeg", garbage), WHERE)
    ok, jpeg = cv2.imencode(".jpg", smooth_rgb())
    raises(["could not be decoded as JPEG/PNG"], decode_image, compressed_msg("jpeg", jpeg[:40]), WHERE)
    raises([WHERE + ": ", "got 0 bytes"], decode_image, compressed_msg("jpeg", b""), WHERE)


# --------------------------------------------------------------------------- camera info


def info_msg(**overrides) -> SimpleNamespace:
    """A ROS 2 style CameraInfo namespace (lower-case matrices) for a 640x480 camera."""
    fields = dict(height=480, width=640, distortion_model="plumb_bob", d=list(PLUMB_BOB), k=list(K), r=list(R),
                  p=list(P), binning_x=0, binning_y=0,
                  roi=SimpleNamespace(x_offset=0, y_offset=0, height=0, width=0, do_rectify=False))
    return SimpleNamespace(**{**fields, **overrides})


def rosbags_info(typestore, is_ros1, **overrides):
    """A real CameraInfo of the store, round-tripped; ``overrides`` use ROS 2 (lower-case) names."""
    ns = info_msg(**overrides)
    Roi = typestore.types["sensor_msgs/msg/RegionOfInterest"]
    CameraInfo = typestore.types["sensor_msgs/msg/CameraInfo"]
    matrices = {(key.upper() if is_ros1 else key): np.array(getattr(ns, key), np.float64) for key in "dkrp"}
    msg = CameraInfo(header=make_header(typestore), height=ns.height, width=ns.width,
                     distortion_model=ns.distortion_model, binning_x=ns.binning_x, binning_y=ns.binning_y,
                     roi=Roi(**vars(ns.roi)), **matrices)
    return roundtrip(typestore, is_ros1, msg)


def test_rosbags_camera_info_field_names(store):
    typestore, is_ros1 = store
    names = set(typestore.types["sensor_msgs/msg/CameraInfo"].__dataclass_fields__)
    assert names >= ({"D", "K", "R", "P"} if is_ros1 else {"d", "k", "r", "p"})


def test_plumb_bob(store):
    camera = camera_from_info(rosbags_info(*store), WHERE)
    assert isinstance(camera, CameraModel) and camera.image_size == (480, 640)
    assert camera.K.shape == (3, 3) and camera.K.dtype == np.float64
    np.testing.assert_array_equal(camera.K, np.reshape(K, (3, 3)))
    np.testing.assert_array_equal(camera.distortion, PLUMB_BOB)


def test_rational_polynomial(store):
    camera = camera_from_info(rosbags_info(*store, distortion_model="rational_polynomial", d=RATIONAL), WHERE)
    np.testing.assert_array_equal(camera.distortion, RATIONAL)
    assert camera.distortion.dtype == np.float64


@pytest.mark.parametrize("model, d", [("plumb_bob", [0.0] * 5), ("rational_polynomial", [0.0] * 8),
                                      ("", []), ("none", [0.0] * 5)])
def test_zero_or_absent_distortion_is_none(store, model, d):
    camera = camera_from_info(rosbags_info(*store, distortion_model=model, d=d), WHERE)
    assert camera.distortion is None
    np.testing.assert_array_equal(camera.K, np.reshape(K, (3, 3)))


@pytest.mark.parametrize("model", ["plumb_bob", "equidistant"])
def test_rectified_uses_p(store, model):
    camera = camera_from_info(rosbags_info(*store, distortion_model=model), WHERE, rectified=True)
    np.testing.assert_array_equal(camera.K, np.reshape(P, (3, 4))[:, :3])
    assert camera.distortion is None


@pytest.mark.parametrize("model", ["equidistant", "fisheye", "kannala_brandt"])
def test_unsupported_distortion_models_are_refused(store, model):
    raises([WHERE + ": ", f"'{model}'", "plumb_bob or rational_polynomial", "rectified"],
           camera_from_info, rosbags_info(*store, distortion_model=model, d=[0.1, 0.01, 0.0, 0.0]), WHERE)


def test_uncalibrated_camera_is_refused(store):
    raises([WHERE + ": ", "not calibrated", "--calib FILE"], camera_from_info,
           rosbags_info(*store, k=[0.0] * 9, d=[]), WHERE)
    raises(["P[:3, :3] all zero", "not calibrated"], camera_from_info,
           rosbags_info(*store, p=[0.0] * 12), WHERE, rectified=True)


def test_binning_and_roi(store):
    raises([WHERE + ": ", "binning", "got 2 and 1", "not supported"], camera_from_info,
           rosbags_info(*store, binning_x=2, binning_y=1), WHERE)
    roi = SimpleNamespace(x_offset=10, y_offset=0, height=240, width=320, do_rectify=False)
    raises([WHERE + ": ", "roi", "x_offset=10", "not supported"], camera_from_info,
           rosbags_info(*store, roi=roi), WHERE)
    full = SimpleNamespace(x_offset=0, y_offset=0, height=480, width=640, do_rectify=False)
    assert camera_from_info(rosbags_info(*store, roi=full, binning_x=1, binning_y=1), WHERE).image_size == (480, 640)


def test_camera_info_refusals():
    raises([WHERE + ": ", "width", "got 0"], camera_from_info, info_msg(width=0), WHERE)
    raises([WHERE + ": ", "finite", "k"], camera_from_info, info_msg(k=[500.0, 0, 320, 0, np.nan, 240, 0, 0, 1]), WHERE)
    raises([WHERE + ": ", "k with 9 numbers", "got 6"], camera_from_info, info_msg(k=K[:6]), WHERE)
    raises([WHERE + ": ", "non-zero distortion", "''"], camera_from_info, info_msg(distortion_model=""), WHERE)
    raises([WHERE + ": ", "6"], camera_from_info, info_msg(d=[0.1] * 6), WHERE)
    raises([WHERE + ": K: ", "principal point"], camera_from_info,
           info_msg(k=[500.0, 0, 3200, 0, 500, 240, 0, 0, 1]), WHERE)
    raises([WHERE + ": ", "field 'k' (ROS 2) or 'K' (ROS 1)"], camera_from_info,
           SimpleNamespace(height=480, width=640), WHERE)


def test_camera_model_is_frozen_and_read_only():
    camera = camera_from_info(info_msg(), WHERE)
    with pytest.raises(dataclasses.FrozenInstanceError):
        camera.K = np.eye(3)
    with pytest.raises(ValueError):
        camera.K[0, 0] = 1.0
    with pytest.raises(ValueError):
        camera.distortion[0] = 1.0


# --------------------------------------------------------------------------- point clouds


def field(name, offset, datatype, count=1):
    return SimpleNamespace(name=name, offset=offset, datatype=datatype, count=count)


def cloud_msg(records: np.ndarray, fields, *, bigendian=False, row_padding=0, **overrides) -> SimpleNamespace:
    """A PointCloud2 namespace from (H, W) structured ``records`` (itemsize = point_step)."""
    height, width = records.shape
    point_step = records.dtype.itemsize
    row_step = width * point_step + row_padding
    rows = np.full((height, row_step), 0xAB, np.uint8)
    rows[:, :width * point_step] = records.view(np.uint8).reshape(height, -1)
    msg = dict(height=height, width=width, fields=fields, is_bigendian=bigendian, point_step=point_step,
               row_step=row_step, data=rows.reshape(-1), is_dense=False)
    return SimpleNamespace(**{**msg, **overrides})


LIDAR_DTYPE = np.dtype({"names": ["x", "y", "z", "intensity", "ring"], "formats": ["<f4", "<f4", "<f4", "<f4", "<u2"],
                        "offsets": [0, 4, 8, 16, 20], "itemsize": 32})
LIDAR_FIELDS = [field("x", 0, FLOAT32), field("y", 4, FLOAT32), field("z", 8, FLOAT32),
                field("intensity", 16, FLOAT32), field("ring", 20, UINT16)]


def lidar_records(n: int = 7, seed: int = 2) -> np.ndarray:
    rng = np.random.default_rng(seed)
    records = np.zeros((1, n), LIDAR_DTYPE)
    for axis in "xyz":
        records[axis] = rng.uniform(-50, 50, (1, n))
    records["intensity"] = rng.uniform(0, 255, (1, n))
    records["ring"] = np.arange(n) % 32
    return records


def xyz_of(records: np.ndarray) -> np.ndarray:
    return np.stack([records[a].reshape(-1).astype(np.float32) for a in "xyz"], axis=1)


def test_rosbags_lidar_cloud(store):
    typestore, is_ros1 = store
    records = lidar_records()
    ns = cloud_msg(records, LIDAR_FIELDS)
    PointField = typestore.types["sensor_msgs/msg/PointField"]
    PointCloud2 = typestore.types["sensor_msgs/msg/PointCloud2"]
    msg = PointCloud2(header=make_header(typestore, frame_id="velodyne"), height=1, width=records.shape[1],
                      fields=[PointField(name=f.name, offset=f.offset, datatype=f.datatype, count=f.count)
                              for f in LIDAR_FIELDS],
                      is_bigendian=False, point_step=32, row_step=ns.row_step, data=ns.data.copy(), is_dense=True)
    msg = roundtrip(typestore, is_ros1, msg)
    points = points_from_cloud(msg, WHERE)
    assert points.shape == (7, 3) and points.dtype == np.float32 and points.flags.c_contiguous
    np.testing.assert_array_equal(points, xyz_of(records))


def test_float64_and_bigendian_clouds():
    rng = np.random.default_rng(3)
    fields = [field("z", 0, FLOAT64), field("y", 8, FLOAT64), field("x", 16, FLOAT64), field("t", 24, FLOAT64)]
    records = np.zeros((1, 5), np.dtype({"names": ["z", "y", "x"], "formats": ["<f8"] * 3,
                                         "offsets": [0, 8, 16], "itemsize": 32}))
    for axis in "xyz":
        records[axis] = rng.uniform(-100, 100, (1, 5))
    np.testing.assert_array_equal(points_from_cloud(cloud_msg(records, fields), WHERE), xyz_of(records))
    big = np.zeros((1, 6), np.dtype({"names": ["x", "y", "z"], "formats": [">f4"] * 3,
                                      "offsets": [0, 4, 8], "itemsize": 16}))
    for axis in "xyz":
        big[axis] = rng.uniform(-100, 100, (1, 6))
    fields = [field("x", 0, FLOAT32), field("y", 4, FLOAT32), field("z", 8, FLOAT32)]
    np.testing.assert_array_equal(points_from_cloud(cloud_msg(big, fields, bigendian=True), WHERE), xyz_of(big))
    assert not np.array_equal(points_from_cloud(cloud_msg(big, fields), WHERE), xyz_of(big))


def test_organised_cloud_with_row_padding_keeps_nan_rows():
    records = lidar_records(n=20).reshape(4, 5)
    records["x"][1, 2] = np.nan
    records["z"][3, 0] = np.inf
    records["x"][2] = np.nan
    msg = cloud_msg(records, LIDAR_FIELDS, row_padding=12)
    points = points_from_cloud(msg, WHERE)
    assert points.shape == (20, 3)
    np.testing.assert_array_equal(points, xyz_of(records))  # message order, NaN/inf rows in place
    assert int(np.sum(~np.isfinite(points).all(axis=1))) == 7


def test_float64_beyond_float32_becomes_inf_without_warning():
    records = np.zeros((1, 2), np.dtype({"names": ["x", "y", "z"], "formats": ["<f8"] * 3}))
    records["x"] = [[1e300, 1.0]]
    fields = [field("x", 0, FLOAT64), field("y", 8, FLOAT64), field("z", 16, FLOAT64)]
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        points = points_from_cloud(cloud_msg(records, fields), WHERE)
    assert np.isinf(points[0, 0]) and points[1, 0] == 1.0


def test_empty_cloud():
    msg = cloud_msg(lidar_records(), LIDAR_FIELDS, width=0, data=np.zeros(0, np.uint8))
    points = points_from_cloud(msg, WHERE)
    assert points.shape == (0, 3) and points.dtype == np.float32


def test_cloud_refusals():
    records = lidar_records()
    no_z = [f for f in LIDAR_FIELDS if f.name != "z"]
    raises([WHERE + ": ", "no 'z' field", "x FLOAT32@0", "ring UINT16@20"], points_from_cloud,
           cloud_msg(records, no_z), WHERE)
    packed = np.zeros((1, 3), np.dtype({"names": ["x", "y", "z"], "formats": ["<i2"] * 3, "itemsize": 8}))
    int_fields = [field("x", 0, INT16), field("y", 2, INT16), field("z", 4, INT16)]
    raises([WHERE + ": ", "got INT16", "FLOAT32 or FLOAT64", "x INT16@0"], points_from_cloud,
           cloud_msg(packed, int_fields), WHERE)
    msg = cloud_msg(records, LIDAR_FIELDS)
    msg.data = msg.data[:-1]
    raises([WHERE + ": ", "truncated", "1 * 224 = 224", "got 223"], points_from_cloud, msg, WHERE)
    beyond = LIDAR_FIELDS[:2] + [field("z", 30, FLOAT32)]
    raises([WHERE + ": ", "beyond", "point_step 32"], points_from_cloud, cloud_msg(records, beyond), WHERE)
    raises([WHERE + ": ", "row_step >= width * point_step = 7 * 32 = 224", "got row_step 200"],
           points_from_cloud, cloud_msg(records, LIDAR_FIELDS, row_step=200), WHERE)
    raises([WHERE + ": ", "count 3"], points_from_cloud,
           cloud_msg(records, [field("x", 0, FLOAT32, 3)] + LIDAR_FIELDS[1:]), WHERE)
    raises([WHERE + ": ", "overlap"], points_from_cloud,
           cloud_msg(records, [field("x", 0, FLOAT32), field("y", 2, FLOAT32), field("z", 8, FLOAT32)]), WHERE)


# --------------------------------------------------------------------------- depth images for writing


def test_depth_image_fields_roundtrip_bytes():
    depth = np.random.default_rng(4).uniform(0, 80, (5, 7)).astype(np.float32)
    depth[0, 0], depth[1, 1] = 0.0, np.nan
    fields = depth_image_fields(depth)
    assert {k: v for k, v in fields.items() if k != "data"} == {
        "height": 5, "width": 7, "encoding": "32FC1", "is_bigendian": 0, "step": 28}
    assert fields["data"].dtype == np.uint8 and fields["data"].shape == (140,)
    np.testing.assert_array_equal(np.frombuffer(fields["data"].tobytes(), "<f4").reshape(5, 7), depth)
    depth[2, 2] = -1.0
    assert np.frombuffer(fields["data"].tobytes(), "<f4")[2 * 7 + 2] != -1.0  # a copy, not a view
    doubles = np.arange(6, dtype=np.float64).reshape(2, 3)
    np.testing.assert_array_equal(np.frombuffer(depth_image_fields(doubles)["data"], "<f4"), np.arange(6))


def test_depth_image_fields_in_a_rosbags_image(store):
    typestore, is_ros1 = store
    depth = np.random.default_rng(5).uniform(0, 80, (3, 4)).astype(np.float32)
    Image = typestore.types["sensor_msgs/msg/Image"]
    msg = roundtrip(typestore, is_ros1, Image(header=make_header(typestore), **depth_image_fields(depth)))
    assert (msg.encoding, msg.height, msg.width, msg.step) == ("32FC1", 3, 4, 16)
    np.testing.assert_array_equal(np.frombuffer(msg.data.tobytes(), "<f4").reshape(3, 4), depth)
    raises(["expected an 8-bit camera image", "depth image"], decode_image, msg, WHERE)


@pytest.mark.parametrize("bad", [np.zeros((2, 3, 1), np.float32), np.zeros((0, 3), np.float32),
                                 np.array([["a"]]), np.zeros(4, np.float32)])
def test_depth_image_fields_refusals(bad):
    raises(["depth: expected a non-empty (H, W) real array"], depth_image_fields, bad)


# --------------------------------------------------------------------------- no stray exceptions


def test_random_bad_messages_raise_only_input_error():
    """Fuzz the sizes and data of images and clouds: a result or an InputError, nothing else."""
    rng = np.random.default_rng(6)
    for _ in range(300):
        height, width, step, points = (int(v) for v in rng.integers(-1, 9, 4))
        data = rng.integers(0, 256, int(rng.integers(0, 200)), dtype=np.uint8)
        encoding = str(rng.choice(list(IMAGE_ENCODINGS) + ["32FC1", "bogus"]))
        messages = [
            (decode_image, SimpleNamespace(height=height, width=width, step=step * 3, encoding=encoding, data=data)),
            (decode_image, SimpleNamespace(format=str(rng.choice(["jpeg", "png"])), data=data)),
            (points_from_cloud, SimpleNamespace(height=height, width=width, point_step=points * 4,
                                                row_step=step * 8, is_bigendian=bool(rng.integers(2)), data=data,
                                                fields=[field(a, int(rng.integers(0, 12)), int(rng.integers(0, 10)),
                                                              int(rng.integers(0, 3))) for a in "xyz"])),
        ]
        for call, msg in messages:
            try:
                call(msg, WHERE)
            except InputError as error:
                assert str(error).startswith(WHERE + ": ")
