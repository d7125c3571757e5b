"""``crfdepth targets --bag`` on a synthetic recording (crfdepth.data.synthetic.make_sequence written as a ROS
bag with /tf_static camera <-> LiDAR and /tf odometry odom -> LiDAR carrying the true poses): the targets match
those of the same sequence written as a KITTI drive, poses.txt the true poses, SequenceFrames reads the output;
its bad input (exit status 2, one line, nothing written)."""

from __future__ import annotations

import csv
from pathlib import Path

import numpy as np
import pytest

from crfdepth.cli import main
from crfdepth.data.sequences import SequenceFrames
from crfdepth.data.synthetic import make_sequence
from crfdepth.io.calibration import read_raw_calibration
from crfdepth.io.kitti import read_depth_png, read_velodyne
from crfdepth.sequences import pose_source
from crfdepth.sequences.poses import read_kitti_poses
from tests.cli.frames import run_main as run
from tests.sequence_drive import DRIVE, poses_file, write_drive
from tests.sequence_drive import stem as _stem

pytest.importorskip("rosbags")

N_FRAMES = 6
K_WINDOW = 2
START_NS = 1_700_000_000_000_000_000  # 2023-11-14 UTC
PERIOD_NS = 100_000_000
CLOUD_DELAY_NS = 7_000_000
DATE = "2023_11_14"
IMAGE, CLOUDS, INFO = "/cam/image_raw", "/lidar/points", "/cam/camera_info"


@pytest.fixture(scope="module")
def sequence():
    return make_sequence(N_FRAMES, 0, height=128, width=416, movers=1, yaw_rate=3.0)


def write_bag(path: Path, seq, *, frames=None, tf: bool = True, stamp_of=None, images: bool = True,
              info: bool = True) -> Path:
    """The sequence as a recording: images (rgb8) and CameraInfo at ``stamp_of(k)``, clouds (x y z, frame
    ``velodyne``) 7 ms later, /tf_static ``velodyne -> camera_optical`` (the inverse of T_cam_lidar), and with
    ``tf`` the true LiDAR poses on /tf as ``odom -> velodyne`` at the clouds' stamps."""
    from crfdepth.io.ros.writer import BagWriter

    stamp_of = stamp_of or (lambda k: START_NS + k * PERIOD_NS)
    T = seq.T_cam_lidar
    lidar = seq.lidar_poses()
    with BagWriter(path) as bag:
        bag.write("/tf_static", START_NS - PERIOD_NS,
                  bag.transforms([("velodyne", "camera_optical", np.linalg.inv(T))], START_NS - PERIOD_NS))
        for k in (range(len(seq)) if frames is None else frames):
            f, stamp = seq[k], stamp_of(k)
            rgb = np.round(np.clip(f.image, 0, 1) * 255).astype(np.uint8)
            if images:
                bag.write(IMAGE, stamp + 1_000_000, bag.image(rgb, stamp, "camera_optical"))
            if info:
                bag.write(INFO, stamp + 1_000_000, bag.camera_info(f.K, rgb.shape[:2], stamp, "camera_optical"))
            cloud = stamp + CLOUD_DELAY_NS
            bag.write(CLOUDS, cloud + 2_000_000, bag.point_cloud(f.points[:, :3], cloud, "velodyne"))
            if tf:
                bag.write("/tf", cloud + 2_000_000, bag.transforms([("odom", "velodyne", lidar[k])], cloud))
    return path


@pytest.fixture(scope="module")
def recording(tmp_path_factory, sequence) -> Path:
    return write_bag(tmp_path_factory.mktemp("bag") / "rig.bag", sequence)


@pytest.fixture(scope="module")
def from_bag(tmp_path_factory, recording) -> Path:
    """``targets --bag`` (auto poses: /tf) into a fresh OUT; returns OUT."""
    out = tmp_path_factory.mktemp("bag_out") / "out"
    assert main(["targets", "--bag", str(recording), "-k", str(K_WINDOW), "--out-dir", str(out), "--quiet"]) == 0
    return out


@pytest.fixture(scope="module")
def from_drive(tmp_path_factory, sequence) -> Path:
    """The same sequence written as a KITTI drive, targets with the true poses."""
    root = tmp_path_factory.mktemp("drive")
    drive = write_drive(root / "raw", sequence)
    out = root / "out"
    assert main(["targets", "--drive", str(drive), "--poses", str(poses_file(drive)), "-k", str(K_WINDOW),
                 "--out-dir", str(out), "--quiet"]) == 0
    return out / DRIVE


def files(folder: Path) -> list[str]:
    return sorted(str(p.relative_to(folder)) for p in folder.rglob("*") if p.is_file()) if folder.exists() else []


def _refused(argv, capsys, out: Path, expected: str) -> None:
    code, _, err = run(argv, capsys)
    assert code == 2, err
    assert (err.splitlines() or [""])[0] == expected
    assert files(out) == [] and not out.exists()


# --------------------------------------------------------------------------- the output


def test_writes_a_kitti_raw_drive_and_its_targets(from_bag, sequence):
    drive = from_bag / DATE / "rig_sync"
    stems = [_stem(i) for i in range(N_FRAMES)]
    assert files(from_bag) == sorted(
        [f"{DATE}/calib_cam_to_cam.txt", f"{DATE}/calib_velo_to_cam.txt"]
        + [f"{DATE}/rig_sync/image_02/data/{s}.png" for s in stems]
        + [f"{DATE}/rig_sync/velodyne_points/data/{s}.bin" for s in stems]
        + ["rig_sync/index_image_02.csv", "rig_sync/poses.txt"]
        + [f"rig_sync/proj_depth/{kind}/image_02/{s}.png" for kind in ("groundtruth", "support") for s in stems])
    # the day calibration reads back as the bag's camera and transform
    calib = read_raw_calibration(from_bag / DATE)
    np.testing.assert_allclose(calib.K, sequence[0].K, atol=1e-9)
    np.testing.assert_allclose(calib.velo_to_rect_cam(), sequence.T_cam_lidar, atol=1e-9)
    assert calib.image_size == sequence[0].image.shape[:2]
    # the scans: float32 x y z of the bag's clouds, intensity 0
    scan = read_velodyne(drive / "velodyne_points" / "data" / f"{_stem(3)}.bin")
    np.testing.assert_allclose(scan[:, :3], sequence[3].points[:, :3], atol=1e-6)
    assert np.all(scan[:, 3] == 0)


def test_targets_match_those_of_the_same_sequence_as_a_drive(from_bag, from_drive):
    for i in range(N_FRAMES):
        name = f"{_stem(i)}.png"
        bag = read_depth_png(from_bag / "rig_sync" / "proj_depth" / "groundtruth" / "image_02" / name)
        drive = read_depth_png(from_drive / "proj_depth" / "groundtruth" / "image_02" / name)
        density_bag, density_drive = (bag > 0).mean(), (drive > 0).mean()
        # measured: identical (0 pixels differ, depth difference 0: the poses differ by the /tf quaternions'
        # rounding, 5e-10, far below the PNG's 1/256 m); tolerances: density 2%, common pixels 98%, depth 1 cm
        assert abs(density_bag - density_drive) <= 0.02 * density_drive, (i, density_bag, density_drive)
        common = (bag > 0) & (drive > 0)
        assert common.sum() >= 0.98 * (drive > 0).sum()
        assert np.abs(bag[common] - drive[common]).max() <= 0.01, i
    rows_bag = list(csv.DictReader((from_bag / "rig_sync" / "index_image_02.csv").open()))
    rows_drive = list(csv.DictReader((from_drive / "index_image_02.csv").open()))
    assert [r["frame"] for r in rows_bag] == [r["frame"] for r in rows_drive]
    for a, b in zip(rows_bag, rows_drive):
        assert abs(float(a["density"]) - float(b["density"])) <= 0.02 * float(b["density"])


def test_poses_are_the_true_poses(from_bag, sequence):
    written = read_kitti_poses(from_bag / "rig_sync" / "poses.txt")
    # the camera poses relative to the first (R_rect = I, so rectified camera 0 is the camera); measured 4.7e-10
    np.testing.assert_allclose(written, sequence.camera_poses(), atol=1e-6)


def test_sequence_frames_reads_the_output(from_bag, sequence):
    data = SequenceFrames(from_bag, targets_root=from_bag, transform=None)
    assert len(data) == N_FRAMES - 2 and data.names[0] == f"rig_sync_{_stem(1)}_image_02"
    sample = data[1]  # frame 2
    assert tuple(sample.neighbours.shape) == (2, 3, *sequence[0].image.shape[:2])
    true = [np.linalg.inv(sequence[s].T_w_cam) @ sequence[2].T_w_cam for s in (1, 3)]
    np.testing.assert_allclose(sample.poses.numpy(), np.stack(true), atol=1e-5)
    target = read_depth_png(from_bag / "rig_sync" / "proj_depth" / "groundtruth" / "image_02" / f"{_stem(2)}.png")
    np.testing.assert_allclose(sample.target.numpy().squeeze(), target, atol=1e-6)
    assert float((sample.sparse > 0).float().mean()) > 0.01


def test_summary_line_and_vis(recording, tmp_path, capsys):
    out = tmp_path / "out"
    code, stdout, err = run(["targets", "--bag", recording, "-k", 1, "--frames", "2:3", "--out-dir", out,
                             "--vis"], capsys)
    assert code == 0, err
    assert stdout.startswith(f"wrote 2 frame(s) of {recording} as the drive {out / DATE / 'rig_sync'} and their "
                             f"targets to {out / 'rig_sync'} (image_02, k=1, poses: /tf odometry odom -> velodyne): ")
    assert files(out / DATE / "rig_sync" / "image_02") == [f"data/{_stem(i)}.png" for i in range(1, 5)]
    assert files(Path(f"{out}_vis")) == [f"rig_sync_image_02_{_stem(i)}.png" for i in (2, 3)]
    assert len(read_kitti_poses(out / "rig_sync" / "poses.txt")) == 4
    assert not list(out.glob(".crfdepth*"))


def test_a_ros2_bag_folder(sequence, tmp_path, capsys):
    """A ROS 2 (mcap) bag folder: the drive is named after the folder; the topics given with --cloud-topic."""
    bag = write_bag(tmp_path / "run2", sequence, frames=[0, 1, 2])
    out = tmp_path / "out"
    code, _, err = run(["targets", "--bag", bag, "--image-topic", IMAGE, "--cloud-topic", CLOUDS, "-k", 1,
                        "--out-dir", out, "--quiet"], capsys)
    assert code == 0, err
    assert files(out / "run2_sync" / "proj_depth" / "groundtruth") == [f"image_02/{_stem(i)}.png" for i in range(3)]
    assert len(files(out / DATE / "run2_sync" / "velodyne_points")) == 3


def test_kiss_icp_odometry_on_the_bag(recording, sequence, tmp_path, capsys):
    """--poses odometry runs the drive path's KISS-ICP on the bag's scans, every step checked. On this
    synthetic street (perfectly flat ground, a gentle turn, start from standstill) KISS-ICP with all
    points stays near zero motion (about 1 m short per 1 m step, smooth enough for the speed and jump
    checks), and so does the retry without the ground: the registration check
    (crfdepth.sequences.registration.step_alignment) names the frames that slid, for a bag as for a drive, and
    nothing is written."""
    pytest.importorskip("kiss_icp")
    from crfdepth.sequences.odometry import lidar_odometry_with_fallback

    out = tmp_path / "out"
    code, _, err = run(["targets", "--bag", recording, "--poses", "odometry", "-k", 1, "--out-dir", out], capsys)
    assert code == 2
    line = (err.splitlines() or [""])[0]
    odo, _ = lidar_odometry_with_fallback([f.points[:, :3] for f in sequence])
    assert odo.failures and line.startswith(
        f"crfdepth targets: error: --poses odometry: expected LiDAR odometry without failures, got "
        f"{len(odo.failures)} failed step(s) (frame {_stem(odo.failures[0][0])}: the registration slid: ")
    assert files(out) == [] and not out.exists()


# --------------------------------------------------------------------------- bad input


def test_refuses_both_or_neither_input(recording, tmp_path, capsys):
    out = tmp_path / "out"
    _refused(["targets", "--out-dir", out], capsys, out,
             "crfdepth targets: error: --drive / --bag: expected one of them (a KITTI raw drive folder or a ROS "
             "bag), got neither")
    _refused(["targets", "--drive", tmp_path, "--bag", recording, "--out-dir", out], capsys, out,
             "crfdepth targets: error: --drive / --bag: expected one of them (a KITTI raw drive folder or a ROS "
             "bag), got both")
    _refused(["targets", "--drive", tmp_path, "--image-topic", IMAGE, "--out-dir", out], capsys, out,
             "crfdepth targets: error: --image-topic: cannot be combined with --drive (options of --bag)")


def test_refuses_a_bag_of_one_paired_frame(sequence, tmp_path, capsys):
    bag = write_bag(tmp_path / "one.bag", sequence, frames=[0])
    out = tmp_path / "out"
    _refused(["targets", "--bag", bag, "--out-dir", out], capsys, out,
             f"crfdepth targets: error: --bag {bag}: expected at least 2 frames (accumulation needs neighbouring "
             f"scans), got 1 (frame 0000000000)")


def test_refuses_missing_topics(sequence, recording, tmp_path, capsys):
    bag = write_bag(tmp_path / "clouds.bag", sequence, frames=[0, 1], images=False, info=False)
    out = tmp_path / "out"
    _refused(["targets", "--bag", bag, "--out-dir", out], capsys, out,
             f"crfdepth targets: error: --image-topic: expected the camera image topic of --bag {bag} (needed when "
             f"the bag has several or none), got none; image topics: none; point-cloud topics: {CLOUDS}")
    _refused(["targets", "--bag", recording, "--points-topic", "/nope", "--out-dir", out], capsys, out,
             f"crfdepth targets: error: --points-topic: expected a point cloud topic of --bag {recording}, got "
             f"'/nope', which is not in it; image topics: {IMAGE}; point-cloud topics: {CLOUDS}")


def test_refuses_without_rosbags(recording, tmp_path, capsys, monkeypatch):
    import sys

    monkeypatch.setitem(sys.modules, "rosbags.highlevel", None)
    out = tmp_path / "out"
    _refused(["targets", "--bag", recording, "--out-dir", out], capsys, out,
             f"crfdepth targets: error: --bag {recording}: reading ROS bags needs the rosbags package, which is not "
             f"installed; install it with: pip install 'crfdepth[ros]'")


def test_refuses_a_time_gap_unless_frames_selects_a_gap_free_range(sequence, tmp_path, capsys):
    """Frame 4's clouds come 0.5 s after frame 3's (4 periods missing): numbered 7, refused without --frames."""
    bag = write_bag(tmp_path / "gap.bag", sequence,
                    stamp_of=lambda k: START_NS + (k + (4 if k >= 4 else 0)) * PERIOD_NS)
    out = tmp_path / "out"
    args = ["targets", "--bag", bag, "-k", 1, "--out-dir", out, "--quiet"]
    _refused(args, capsys, out,
             f"crfdepth targets: error: --bag {bag}: expected clouds at a steady rate, got a gap of 0.500 s after "
             f"frame 0000000003 (next: 0000000008; more than 3x the median period 0.100 s; 1 gap(s)); give --frames "
             f"A:B for a gap-free range")
    _refused([*args, "--frames", "3:8"], capsys, out,
             "crfdepth targets: error: --frames 3:8: expected a gap-free range, got frame 0000000004 missing (4 of 6)")
    code, _, err = run([*args, "--frames", "1:3"], capsys)
    assert code == 0, err
    rows = list(csv.DictReader((out / "gap_sync" / "index_image_02.csv").open()))
    # frame 3's window stops at the gap: 2-3, not 2-8
    assert [(r["first_scan"], r["last_scan"]) for r in rows] == [
        (_stem(0), _stem(2)), (_stem(1), _stem(3)), (_stem(2), _stem(3))]
    assert files(out / DATE / "gap_sync" / "velodyne_points") == [f"data/{_stem(i)}.bin" for i in range(4)]


def test_refuses_an_output_folder_holding_this_drive(recording, from_bag, capsys):
    before = files(from_bag)
    code, _, err = run(["targets", "--bag", recording, "--out-dir", from_bag], capsys)
    assert code == 2
    assert err.splitlines()[0] == (
        f"crfdepth targets: error: --out-dir: {from_bag} already holds the drive rig_sync "
        f"({from_bag / DATE / 'rig_sync'}, from an earlier run); remove it or choose another --out-dir")
    assert files(from_bag) == before


def test_tf_poses_demanded_without_tf(sequence, tmp_path, capsys, monkeypatch):
    bag = write_bag(tmp_path / "notf.bag", sequence, frames=[0, 1, 2], tf=False)
    out = tmp_path / "out"
    _refused(["targets", "--bag", bag, "--poses", "tf", "--out-dir", out], capsys, out,
             "crfdepth targets: error: --poses tf: expected odometry on /tf (a transform from a fixed frame such as "
             "odom or map to the LiDAR frame 'velodyne' that changes over time), got no transform above it; use "
             "--poses odometry or --poses FILE")
    monkeypatch.setattr(pose_source, "kiss_installed", lambda: False)
    _refused(["targets", "--bag", bag, "--out-dir", out], capsys, out,
             "crfdepth targets: error: --poses auto: the bag has no odometry on /tf, and LiDAR odometry needs the "
             "kiss-icp package, not installed; pip install \"crfdepth[odometry]\", or give --poses FILE")


def test_a_misspelt_poses_keyword_is_told_what_the_option_takes(recording, tmp_path, capsys):
    out = tmp_path / "out"
    _refused(["targets", "--bag", recording, "--poses", "odom", "--out-dir", out], capsys, out,
             "crfdepth targets: error: --poses odom: expected auto, tf, odometry or the path of a KITTI odometry "
             "poses.txt, got 'odom', which is neither (no such file)")


def test_tf_odometry_with_a_jump_is_reported_by_frame(sequence, tmp_path, capsys):
    """A /tf pose 3 m off at frame 3: check_poses names frames 3 (and 4, the step back)."""
    import dataclasses

    frames = list(sequence.frames)
    moved = frames[3].T_w_lidar.copy()
    moved[0, 3] += 3.0
    frames[3] = dataclasses.replace(frames[3], T_w_lidar=moved)
    bag = write_bag(tmp_path / "jump.bag", dataclasses.replace(sequence, frames=frames))
    out = tmp_path / "out"
    code, _, err = run(["targets", "--bag", bag, "--out-dir", out], capsys)
    assert code == 2
    line = err.splitlines()[0]
    assert line.startswith("crfdepth targets: error: --poses auto: expected /tf odometry 'odom' -> 'velodyne' without "
                           "failures, got ")
    assert "frame 0000000003: " in line and "(a jump)" in line
    assert not out.exists()


def test_a_poses_file_has_one_line_per_paired_frame(recording, sequence, tmp_path, capsys):
    from tests.sequence_drive import matrix_text

    poses = tmp_path / "poses.txt"
    poses.write_text("\n".join(matrix_text(f.T_w_cam[:3, :]) for f in sequence) + "\n")
    out = tmp_path / "out"
    code, _, err = run(["targets", "--bag", recording, "--poses", poses, "--frames", "2:3", "-k", 1, "--out-dir", out,
                        "--quiet"], capsys)
    assert code == 0, err
    true = sequence.camera_poses()[1:5]
    np.testing.assert_allclose(read_kitti_poses(out / "rig_sync" / "poses.txt"), np.linalg.inv(true[0]) @ true,
                               atol=1e-6)
    short = tmp_path / "short.txt"
    short.write_text("\n".join(poses.read_text().splitlines()[:4]) + "\n")
    out2 = tmp_path / "out2"
    _refused(["targets", "--bag", recording, "--poses", short, "--out-dir", out2], capsys, out2,
             f"crfdepth targets: error: --poses {short}: expected {N_FRAMES} poses (one per paired frame of the bag, "
             f"in time order), got 4")


def test_several_bags_into_one_output_folder(recording, sequence, tmp_path, capsys):
    # a folder of recordings of one rig, one run per bag into the same OUT: the sequence layout
    # reads every drive (configs/kitti_sequence.yaml, "From ROS bags")
    second = write_bag(tmp_path / "van.bag", sequence, stamp_of=lambda k: START_NS + 3_600_000_000_000
                       + k * PERIOD_NS)
    out = tmp_path / "out"
    for bag in (recording, second):
        code, _, err = run(["targets", "--bag", bag, "-k", K_WINDOW, "--out-dir", out, "--quiet"], capsys)
        assert code == 0, err
    assert sorted(p.name for p in (out / DATE).iterdir() if p.is_dir()) == ["rig_sync", "van_sync"]
    data = SequenceFrames(out, targets_root=out, transform=None)
    assert len(data) == 2 * (N_FRAMES - 2)
    assert {name.split("_sync_")[0] for name in data.names} == {"rig", "van"}
