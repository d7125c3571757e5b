"""``crfdepth complete --bag``: ROS 1 and ROS 2 recordings written here with rosbags' writers."""

from __future__ import annotations

import csv
import sys
from pathlib import Path

import numpy as np
import pytest

from crfdepth import cli
from crfdepth.api import complete_depth
from crfdepth.io.kitti import read_depth_png
from crfdepth.model import CRFDepth

pytest.importorskip("rosbags")

from tests.io.ros.bags import (  # noqa: E402
    IMAGE_TOPIC,
    INFO_TOPIC,
    KINDS,
    PERIOD_NS,
    POINTS_TOPIC,
    START_NS,
    BagBuilder,
    rig_edges,
    synthetic_frames,
    write_bag,
)

FAST = ["--potentials", "colour", "--quiet"]
TOPICS = ["--image-topic", IMAGE_TOPIC, "--points-topic", POINTS_TOPIC]
MS = 1_000_000


@pytest.fixture
def main(monkeypatch):
    monkeypatch.setattr(cli, "_COMMANDS", ("crfdepth.cli.complete",))
    return cli.main


@pytest.fixture(scope="module")
def model():
    return CRFDepth.from_pretrained(potentials=["colour"])  # what the CLI builds from FAST


def _bag_path(tmp_path: Path, kind: str, name: str = "in") -> Path:
    return tmp_path / (f"{name}.bag" if kind == "ros1" else name)


def _quantised(depth: np.ndarray) -> np.ndarray:
    """What write_depth_png + read_depth_png make of a completed depth (or std) map: 1/256 m steps, clipped to
    [1/256, 65535/256] m."""
    return np.round(np.clip(depth.astype(np.float64), 1 / 256, 65535 / 256) * 256).astype(np.float32) / 256


def _expected(recorded, k: int, model, cloud: int | None = None):
    points = recorded.clouds[k if cloud is None else cloud]
    return complete_depth(recorded.images[k], points=points, K=recorded.K, T_cam_lidar=recorded.T_cam_lidar,
                          model=model)


def _index(folder: Path) -> list[dict]:
    with open(folder / "index.csv", newline="") as handle:
        return list(csv.DictReader(handle))


def _read_bag(path: Path) -> dict[str, list]:
    from rosbags.highlevel import AnyReader

    messages = {}
    with AnyReader([path]) as reader:
        for connection, _, raw in reader.messages():
            messages.setdefault(connection.topic, []).append(reader.deserialize(raw, connection.msgtype))
    return messages


@pytest.mark.parametrize("kind", KINDS)
def test_bag_equals_complete_depth(main, model, tmp_path, kind):
    """Every frame equals complete_depth on the same image, cloud, K and T (composed here over three
    /tf_static hops); the output bag carries the same depth and std with the images' headers."""
    recorded = write_bag(_bag_path(tmp_path, kind), kind)
    out_bag = _bag_path(tmp_path, kind, "out")
    assert main(["complete", "--bag", str(recorded.path), *TOPICS, "--out-dir", str(tmp_path / "d"),
                 "--out-std-dir", str(tmp_path / "s"), "--out-bag", str(out_bag), *FAST]) == 0
    rows = _index(tmp_path / "d")
    assert [int(r["timestamp_ns"]) for r in rows] == recorded.image_ns
    written = _read_bag(out_bag)
    assert sorted(written) == ["/camera/crfdepth/camera_info", "/camera/crfdepth/depth", "/camera/crfdepth/std"]
    for k, row in enumerate(rows):
        depth, std = _expected(recorded, k, model)
        png = read_depth_png(tmp_path / "d" / f"{recorded.image_ns[k]}.png")
        assert np.abs(png - _quantised(depth)).max() <= 1 / 256 + 1e-6  # measured: 0
        assert np.abs(read_depth_png(tmp_path / "s" / row["std_png"]) - _quantised(std)).max() <= 1 / 256 + 1e-6
        image = written["/camera/crfdepth/depth"][k]
        assert image.encoding == "32FC1" and (image.height, image.width) == depth.shape
        assert image.header.frame_id == "camera_optical"
        assert image.header.stamp.sec * 10**9 + image.header.stamp.nanosec == recorded.image_ns[k]
        values = np.frombuffer(image.data.tobytes(), dtype="<f4").reshape(depth.shape)
        np.testing.assert_allclose(values, depth, rtol=1e-5, atol=1e-5)
        std_values = np.frombuffer(written["/camera/crfdepth/std"][k].data.tobytes(), dtype="<f4")
        np.testing.assert_allclose(std_values.reshape(depth.shape), std, rtol=1e-4, atol=1e-5)
        info = written["/camera/crfdepth/camera_info"][k]
        K = getattr(info, "k", getattr(info, "K", None))
        np.testing.assert_allclose(np.asarray(K).reshape(3, 3), recorded.K)
        assert int(row["points"]) == len(recorded.clouds[k]) and 0 < int(row["points_in_view"]) < int(row["points"])
        assert row["image_topic"] == IMAGE_TOPIC and row["points_topic"] == POINTS_TOPIC


def test_compressed_images_and_pairing_with_jitter(main, model, tmp_path, capsys):
    """JPEG images; stamps jittered by up to +-20 ms, one cloud 70 ms late: each image takes the nearest
    cloud, and the image whose nearest cloud is beyond --max-dt (0.05 s) is counted as unpaired."""
    jitter = np.array([12, -18, 20, 5]) * MS
    offsets = np.array([-15, 9, 70, 0]) * MS  # image 2 (at +220 ms) is 50 ms from cloud 2 (+270 ms)
    recorded = write_bag(tmp_path / "in", "mcap", count=4, encoding="jpeg", image_jitter_ns=jitter,
                         cloud_offsets_ns=offsets)
    args = ["complete", "--bag", str(recorded.path), "--image-topic", IMAGE_TOPIC + "/compressed",
            "--points-topic", POINTS_TOPIC, "--out-dir", str(tmp_path / "d"), "--potentials", "colour", "--vis"]
    assert main([*args, "--max-dt", "0.045"]) == 0
    pictures = sorted(p.name for p in (tmp_path / "d_vis").iterdir())
    assert pictures == sorted(f"{recorded.image_ns[k]}_vis_{kind}.png" for k in (0, 1, 3) for kind in ("depth", "std"))
    out = capsys.readouterr().out
    assert "1 of 4 image(s) unpaired: no cloud within --max-dt 0.045 s (their gaps 0.05-0.05 s)" in out
    rows = _index(tmp_path / "d")
    assert [int(r["timestamp_ns"]) for r in rows] == [recorded.image_ns[k] for k in (0, 1, 3)]
    assert [float(r["dt_ms"]) for r in rows] == [-27.0, 27.0, -5.0]
    for k in (0, 1, 3):  # the JPEG decoded as the CLI decodes it
        from crfdepth.io.ros.images import decode_image

        builder = BagBuilder(tmp_path / f"scratch{k}", "mcap")
        rgb = decode_image(builder.image(recorded.images[k], 0, "jpeg"), "test")
        builder.close()
        depth, _ = complete_depth(rgb, points=recorded.clouds[k], K=recorded.K, T_cam_lidar=recorded.T_cam_lidar,
                                  model=model, return_std=False)
        png = read_depth_png(tmp_path / "d" / f"{recorded.image_ns[k]}.png")
        assert np.abs(png - _quantised(depth)).max() <= 1 / 256 + 1e-6


@pytest.mark.parametrize("kind", ["ros1", "sqlite3"])
def test_dynamic_tf_distortion_and_calib_override(main, model, tmp_path, kind):
    """The rig's transform on /tf (one message per frame, looked up at each image's time), a CameraInfo with
    lens distortion (the image is undistorted by complete_depth), and --calib replacing both."""
    distortion = np.array([-0.05, 0.01, 0.001, -0.001, 0.0])
    recorded = write_bag(_bag_path(tmp_path, kind), kind, count=2, tf="/tf", distortion=distortion)
    assert main(["complete", "--bag", str(recorded.path), *TOPICS, "--out-dir", str(tmp_path / "d"), *FAST]) == 0
    for k in range(2):
        depth, _ = complete_depth(recorded.images[k], points=recorded.clouds[k], K=recorded.K,
                                  T_cam_lidar=recorded.T_cam_lidar, distortion=distortion, model=model,
                                  return_std=False)
        png = read_depth_png(tmp_path / "d" / f"{recorded.image_ns[k]}.png")
        assert np.abs(png - _quantised(depth)).max() <= 1 / 256 + 1e-6
    bare = write_bag(_bag_path(tmp_path, kind, "bare"), kind, count=2, tf=None, camera_info=False)
    (tmp_path / "rig.yaml").write_text(f"K: {recorded.K.tolist()}\nT_cam_lidar: {recorded.T_cam_lidar.tolist()}\n")
    assert main(["complete", "--bag", str(bare.path), *TOPICS, "--calib", str(tmp_path / "rig.yaml"), "--out-dir",
                 str(tmp_path / "c"), *FAST]) == 0
    for k in range(2):
        depth, _ = _expected(bare, k, model)
        png = read_depth_png(tmp_path / "c" / f"{bare.image_ns[k]}.png")
        assert np.abs(png - _quantised(depth)).max() <= 1 / 256 + 1e-6


def test_pair_nearest_against_brute_force():
    from crfdepth.io.ros.bag import pair_nearest

    rng = np.random.default_rng(0)
    clouds = START_NS + np.arange(50) * PERIOD_NS + rng.integers(-5, 5, 50) * MS
    images = START_NS + rng.integers(-200, 5200, 300) * MS
    pairing = pair_nearest(images, rng.permutation(clouds), 30 * MS)
    shuffled = rng.permutation(clouds)
    pairing = pair_nearest(images, shuffled, 30 * MS)
    gaps = np.abs(images[:, None] - shuffled[None, :])
    np.testing.assert_array_equal(pairing.gap_ns, gaps.min(axis=1))
    best = gaps.argmin(axis=1)
    np.testing.assert_array_equal(pairing.cloud, np.where(gaps.min(axis=1) <= 30 * MS, best, -1))
    assert 0 < pairing.paired < len(images)


@pytest.mark.kitti
def test_kitti_frame_from_a_bag_equals_complete_depth(main, tmp_path, kitti_root):
    """A real KITTI raw frame (image, Velodyne scan, calibration) recorded into a ROS 2 bag."""
    from crfdepth.io.calibration import load_any_calibration
    from crfdepth.io.kitti import read_rgb, read_velodyne

    drive = kitti_root / "raw/2011_09_26/2011_09_26_drive_0001_sync"
    rgb = read_rgb(drive / "image_02/data/0000000005.png")
    scan = read_velodyne(drive / "velodyne_points/data/0000000005.bin")
    calibration = load_any_calibration(kitti_root / "raw/2011_09_26")
    recorded = write_bag(tmp_path / "kitti", "mcap", frames=([rgb], [scan], calibration.K, calibration.T_cam_lidar))
    assert main(["complete", "--bag", str(recorded.path), *TOPICS, "--out-dir", str(tmp_path / "d"), *FAST]) == 0
    depth, _ = complete_depth(rgb, points=scan, K=calibration.K, T_cam_lidar=calibration.T_cam_lidar,
                              model=CRFDepth.from_pretrained(potentials=["colour"]), return_std=False)
    png = read_depth_png(tmp_path / "d" / f"{START_NS}.png")
    assert png.shape == (375, 1242)
    assert np.abs(png - _quantised(depth)).max() <= 1 / 256 + 1e-6  # measured: 0


# --------------------------------------------------------------------------- bad input


def _bag_with(tmp_path: Path, kind: str = "mcap", **options) -> Path:
    return write_bag(_bag_path(tmp_path, kind), kind, count=2, **options).path


def _disconnected(tmp_path: Path) -> Path:
    """The camera's half of the tree only: velodyne is in no /tf_static edge."""
    images, clouds, K, T = synthetic_frames(1)
    builder = BagBuilder(tmp_path / "in", "mcap")
    builder.write("/tf_static", START_NS, builder.transforms(rig_edges(T)[1:], START_NS))
    builder.write(POINTS_TOPIC, START_NS, builder.cloud(clouds[0], START_NS))
    builder.write(IMAGE_TOPIC, START_NS, builder.image(images[0], START_NS))
    builder.write(INFO_TOPIC, START_NS, builder.camera_info(K, images[0].shape[:2], START_NS, "camera_optical"))
    builder.close()
    return tmp_path / "in"


def _small_rig(tmp_path: Path) -> Path:
    """A rig calibration for 96x48 images."""
    _, _, K, T = synthetic_frames(1)
    (tmp_path / "rig.yaml").write_text(f"K: {K.tolist()}\nT_cam_lidar: {T.tolist()}\nimage_size: [48, 96]\n")
    return tmp_path / "rig.yaml"


def _truncated(tmp_path: Path, kind: str) -> Path:
    path = _bag_with(tmp_path, kind)
    data = path if kind == "ros1" else next(path.glob("*.mcap"))
    data.write_bytes(data.read_bytes()[: data.stat().st_size // 2])
    return path


BAD = {
    "image topic missing": (lambda t: _bag_with(t), ["--image-topic", "/cam/image"],
                            ["--image-topic", "'/cam/image', which is not in it", f"image topics: {IMAGE_TOPIC}",
                             f"point-cloud topics: {POINTS_TOPIC}"]),
    "points topic missing": (lambda t: _bag_with(t), ["--points-topic", "/points"],
                             ["--points-topic", "'/points', which is not in it",
                              f"point-cloud topics: {POINTS_TOPIC}"]),
    "points topic of images": (lambda t: _bag_with(t), ["--points-topic", IMAGE_TOPIC],
                               ["--points-topic", "sensor_msgs/PointCloud2", "sensor_msgs/Image"]),
    "no transform": (lambda t: _bag_with(t, tf=None), [],
                     ["no transform from frame 'velodyne' to frame 'camera_optical'", "--calib FILE"]),
    "disconnected frames": (_disconnected, [],
                            ["'velodyne'", "'camera_optical'", "base_link", "camera_link"]),
    "no CameraInfo": (lambda t: _bag_with(t, camera_info=False), [],
                      ["--camera-info-topic", f"no topic {INFO_TOPIC}", "--calib FILE"]),
    "CameraInfo topic of images": (lambda t: _bag_with(t), ["--camera-info-topic", IMAGE_TOPIC],
                                   ["--camera-info-topic", "sensor_msgs/CameraInfo", "got '/camera/image_raw' of"]),
    "CameraInfo of another size": (lambda t: _bag_with(t, info_size=(48, 96)), [],
                                   ["--camera-info-topic", "96x48", "96x64"]),
    "clocks never pair": (lambda t: _bag_with(t, cloud_offsets_ns=[1000 * 10**9] * 2), [],
                          ["--max-dt 0.05", "the closest gap is 999.9 s", "different clocks"]),
    "unsupported encoding": (lambda t: _bag_with(t, encoding="mono16"), [],
                             ["--image-topic", "mono16", "rgb8"]),
    "unsupported cloud layout": (lambda t: _bag_with(t, xyz_type=3), [],
                                 ["--points-topic", POINTS_TOPIC, "INT16", "FLOAT32"]),
    "truncated ROS 1 bag": (lambda t: _truncated(t, "ros1"), [], ["--bag", "cannot be read", "truncated"]),
    "truncated mcap bag": (lambda t: _truncated(t, "mcap"), [], ["--bag", "cannot be read", "truncated"]),
    "not a bag": (lambda t: (t / "notes.bag").write_text("not a bag") and t / "notes.bag", [],
                  ["--bag", "cannot be read"]),
    "out-bag exists": (lambda t: (t / "existing").mkdir() or _bag_with(t), ["--out-bag", "{t}/existing"],
                       ["--out-bag", "exists"]),
    "calib of another size": (lambda t: _small_rig(t) and _bag_with(t), ["--calib", "{t}/rig.yaml"],
                              ["--calib", "rig.yaml", "96x64", "96x48"]),
    "out-dir is the bag": (lambda t: _bag_with(t), ["--out-dir", "{t}/in"], ["--out-dir", "is the --bag input"]),
    "with --image": (lambda t: _bag_with(t), ["--image", "x.png"], ["--image", "cannot be combined with --bag"]),
}


@pytest.mark.parametrize("case", list(BAD))
def test_bad_input(main, tmp_path, capsys, case):
    """Exit status 2, one line naming the flag, and nothing written: no --out-dir, no --out-bag."""
    make, extra, expected = BAD[case]
    bag = make(tmp_path)
    extra = [a.format(t=tmp_path) for a in extra]
    args = {**dict(zip(TOPICS[::2], TOPICS[1::2])), "--out-dir": str(tmp_path / "d")}
    args.update(dict(zip(extra[::2], extra[1::2])))
    argv = ["complete", "--bag", str(bag), *[a for kv in args.items() for a in kv]]
    if "--out-bag" not in args:
        argv += ["--out-bag", str(tmp_path / "out")]
    assert main([*argv, *FAST]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and err.startswith("crfdepth complete: error: "), err
    for text in expected:
        assert text in err, (text, err)
    assert not (tmp_path / "d").exists()
    assert not (tmp_path / "out").exists()
    assert sorted(p.name for p in tmp_path.iterdir() if p.name.startswith(".")) == []  # no scratch bag left


def test_rosbags_missing(main, tmp_path, capsys, monkeypatch):
    bag = _bag_with(tmp_path)
    monkeypatch.setitem(sys.modules, "rosbags.highlevel", None)
    assert main(["complete", "--bag", str(bag), *TOPICS, "--out-dir", str(tmp_path / "d"), *FAST]) == 2
    assert "pip install 'crfdepth[ros]'" in capsys.readouterr().err


def test_bag_options_need_bag(main, tmp_path, capsys):
    assert main(["complete", "--image-topic", IMAGE_TOPIC, "--input-dir", str(tmp_path), "--out-dir",
                 str(tmp_path / "d")]) == 2
    assert "--image-topic: bag options need --bag" in capsys.readouterr().err


def _bag_with_bad_jpeg(tmp_path: Path) -> Path:
    """Three frames of compressed images whose second JPEG does not decode."""
    images, clouds, K, T = synthetic_frames(3)
    builder = BagBuilder(tmp_path / "in", "mcap")
    builder.write("/tf_static", START_NS, builder.transforms(rig_edges(T), START_NS))
    for k in range(3):
        stamp = START_NS + k * PERIOD_NS
        image = builder.image(images[k], stamp, "jpeg")
        if k == 1:
            image.data[len(image.data) // 3:] = 0
            image.data[:4] = 0  # not a JPEG any more
        builder.write(POINTS_TOPIC, stamp, builder.cloud(clouds[k], stamp))
        builder.write(IMAGE_TOPIC + "/compressed", stamp + 1, image)
        builder.write(INFO_TOPIC, stamp + 1, builder.camera_info(K, images[k].shape[:2], stamp, "camera_optical"))
    builder.close()
    return tmp_path / "in"


def test_bad_frame_midway_writes_nothing(main, tmp_path, capsys):
    """A JPEG that does not decode in frame 2 of 3 is found before anything is written: exit 2, no file."""
    bag = _bag_with_bad_jpeg(tmp_path)
    assert main(["complete", "--bag", str(bag), "--image-topic", IMAGE_TOPIC + "/compressed",
                 "--points-topic", POINTS_TOPIC, "--out-dir", str(tmp_path / "d"), "--out-bag", str(tmp_path / "out"),
                 *FAST]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1
    assert err.startswith(f"crfdepth complete: error: --image-topic {IMAGE_TOPIC}/compressed (image at "
                          f"{START_NS + PERIOD_NS} ns): "), err
    assert "could not be decoded" in err and f"[1 of 3 frame(s) of --bag {bag} bad; nothing written" in err
    assert not (tmp_path / "d").exists() and not (tmp_path / "out").exists() and not list(tmp_path.glob(".out.*"))


def test_skip_bad_completes_the_other_frames(main, tmp_path, capsys):
    """--skip-bad: frames 1 and 3 written and indexed, frame 2 in skipped.csv with its reason, exit 0."""
    bag = _bag_with_bad_jpeg(tmp_path)
    assert main(["complete", "--bag", str(bag), "--image-topic", IMAGE_TOPIC + "/compressed",
                 "--points-topic", POINTS_TOPIC, "--out-dir", str(tmp_path / "d"), "--out-bag", str(tmp_path / "out"),
                 "--skip-bad", "--potentials", "colour"]) == 0
    out = capsys.readouterr().out
    stamps = [str(START_NS), str(START_NS + 2 * PERIOD_NS)]
    assert [r["timestamp_ns"] for r in _index(tmp_path / "d")] == stamps
    assert sorted(p.name for p in (tmp_path / "d").iterdir()) == [f"{s}.png" for s in stamps] + ["index.csv",
                                                                                                   "skipped.csv"]
    with open(tmp_path / "d" / "skipped.csv", newline="") as handle:
        skipped = list(csv.DictReader(handle))
    assert [r["frame"] for r in skipped] == [str(START_NS + PERIOD_NS)] and "could not be decoded" in skipped[0]["reason"]
    assert "skipped 1 bad frame(s) of 3 (--skip-bad)" in out
    assert len(_read_bag(tmp_path / "out")["/camera/crfdepth/depth"]) == 2


@pytest.mark.parametrize("value", ["0", "-0.1", "nan", "soon"])
def test_max_dt_must_be_positive_seconds(main, tmp_path, capsys, value):
    with pytest.raises(SystemExit) as info:
        main(["complete", "--bag", str(tmp_path / "x.bag"), *TOPICS, "--out-dir", str(tmp_path / "d"),
              "--max-dt", value])
    assert info.value.code == 2
    assert f"--max-dt: expected a finite number of seconds > 0, got {value!r}" in capsys.readouterr().err


def test_bayer_images_are_demosaiced_then_completed(main, model, tmp_path):
    """A colour-filter camera's raw topic (bayer_rggb8): the depth is that of OpenCV's demosaiced image."""
    import cv2

    pytest.importorskip("rosbags.image")
    from tests.io.ros.bags import _mosaic

    recorded = write_bag(tmp_path / "in", "sqlite3", count=1, encoding="bayer_rggb8")
    assert main(["complete", "--bag", str(recorded.path), *TOPICS, "--out-dir", str(tmp_path / "d"), *FAST]) == 0
    rgb = cv2.cvtColor(_mosaic(recorded.images[0])[..., 0], cv2.COLOR_BayerBG2RGB)
    depth, _ = complete_depth(rgb, points=recorded.clouds[0], K=recorded.K, T_cam_lidar=recorded.T_cam_lidar,
                              model=model, return_std=False)
    png = read_depth_png(tmp_path / "d" / f"{recorded.image_ns[0]}.png")
    assert np.abs(png - _quantised(depth)).max() <= 1 / 256 + 1e-6
