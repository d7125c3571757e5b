"""``--rerun FILE.rrd`` of ``crfdepth demo``, ``complete`` and ``targets``: the recording read back
(tests/recordings.py) against what the command wrote (the depth PNGs within 1/256 m, K, the LiDAR points, one time
step per frame, the poses of a targets run), and its bad input (exit status 2, one line naming --rerun, nothing
computed, no .rrd left after an error)."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest

import crfdepth.cli.demo as demo
from crfdepth.data.kitti import KittiDrive
from crfdepth.data.synthetic import make_scene, make_sequence
from crfdepth.io.kitti import read_depth_png, read_intrinsics, read_velodyne
from crfdepth.pictures import rerun_recording as rec
from tests.cli.frames import FAST, SIZE, png, run_main, stem, write_folder
from tests.recordings import depth_image, pinhole_K, pose, read_recording
from tests.sequence_drive import DRIVE, poses_file, write_drive
from tests.sequence_drive import stem as drive_stem

pytest.importorskip("rerun")

PNG_CODE = 1 / 256  # metres: one code of a KITTI depth PNG
COMPLETE_ENTITIES = {rec.WORLD, rec.CAMERA, rec.IMAGE, rec.LIDAR_2D, rec.LIDAR_3D, rec.DEPTH}


def _frame(folder: Path, index: int = 0) -> list:
    """``--image``, ``--sparse`` and ``--intrinsics`` of frame ``index`` of :func:`tests.cli.frames.write_folder`."""
    return ["--image", folder / "image" / f"{stem('image', index)}.png", "--sparse", folder / "velodyne_raw" /
            png(index), "--intrinsics", folder / "intrinsics" / f"{stem('image', index)}.txt"]


def _step(found: dict, frame: int) -> dict:
    """``{entity: components}`` at time step ``frame``."""
    return {entity: steps[frame] for entity, steps in found.items() if frame in steps}


def _files(folder: Path) -> list[str]:
    return sorted(p.name for p in folder.iterdir())


# --------------------------------------------------------------------------- what the recordings hold


def test_demo_records_the_scene(tmp_path, capsys):
    out, rrd = tmp_path / "demo", tmp_path / "demo.rrd"
    code, printed, err = run_main(["demo", "--out-dir", out, "--rerun", rrd], capsys)
    assert code == 0, err
    assert printed.splitlines()[-1] == f"wrote {rrd}: a Rerun recording of 1 frame(s); open it with: rerun {rrd}"
    scene = make_scene(0, beams=64)
    found = read_recording(rrd)
    assert COMPLETE_ENTITIES | {rec.STD} <= set(found) and rec.TARGETS not in found
    assert sorted(found[rec.DEPTH]) == [0]
    step = _step(found, 0)
    np.testing.assert_allclose(pinhole_K(step[rec.IMAGE]), scene.K, rtol=1e-6)
    np.testing.assert_array_equal(pose(step[rec.CAMERA]), np.eye(4))
    depth = depth_image(step[rec.DEPTH])
    written = read_depth_png(out / "data" / f"{scene.name}_depth16.png")
    assert depth.shape == written.shape == scene.sparse.shape
    assert np.abs(depth - written).max() <= PNG_CODE
    std = depth_image(step[rec.STD])
    assert std.shape == depth.shape and std.min() > 0
    lidar = int(np.count_nonzero(scene.sparse))
    assert len(step[rec.LIDAR_3D]["Points3D:positions"]) == len(step[rec.LIDAR_2D]["Points2D:positions"]) == lidar


def test_complete_one_frame_records_depth_std_and_lidar(tmp_path, capsys):
    folder = write_folder(tmp_path / "in", 1)
    out, out_std, rrd = tmp_path / "depth.png", tmp_path / "std.png", tmp_path / "frame.rrd"
    code, _, err = run_main(["complete", *_frame(folder), "--out", out, "--out-std", out_std, "--rerun", rrd, *FAST],
                            capsys)
    assert code == 0, err
    assert _files(tmp_path) == ["depth.png", "frame.rrd", "in", "std.png"]  # no temporary file left
    found = read_recording(rrd)
    assert COMPLETE_ENTITIES | {rec.STD} <= set(found) and sorted(found[rec.DEPTH]) == [0]
    step = _step(found, 0)
    np.testing.assert_allclose(pinhole_K(step[rec.IMAGE]), read_intrinsics(_frame(folder)[5]), rtol=1e-6)
    np.testing.assert_array_equal(step[rec.IMAGE]["Pinhole:resolution"][0], [SIZE[1], SIZE[0]])
    assert np.abs(depth_image(step[rec.DEPTH]) - read_depth_png(out)).max() <= PNG_CODE
    assert np.abs(depth_image(step[rec.STD]) - read_depth_png(out_std)).max() <= PNG_CODE
    sparse = read_depth_png(_frame(folder)[3])
    assert len(step[rec.LIDAR_3D]["Points3D:positions"]) == int(np.count_nonzero(sparse))
    np.testing.assert_allclose(step[rec.LIDAR_3D]["Points3D:positions"][:, 2], sparse[sparse > 0], rtol=1e-6)


def test_complete_folder_records_one_step_per_frame_and_no_std_unless_asked(tmp_path, capsys):
    folder = write_folder(tmp_path / "in", 2)
    out, rrd = tmp_path / "out", tmp_path / "folder.rrd"
    code, printed, err = run_main(["complete", "--input-dir", folder, "--out-dir", out, "--rerun", rrd, *FAST],
                                  capsys)
    assert code == 0, err
    assert printed == ""  # --quiet: not even the recording's line
    found = read_recording(rrd)
    assert COMPLETE_ENTITIES <= set(found) and rec.STD not in found
    assert sorted(found[rec.DEPTH]) == sorted(found[rec.IMAGE]) == sorted(found[rec.LIDAR_3D]) == [0, 1]
    for index in range(2):
        step = _step(found, index)
        assert np.abs(depth_image(step[rec.DEPTH]) - read_depth_png(out / png(index))).max() <= PNG_CODE
        lidar = int(np.count_nonzero(read_depth_png(folder / "velodyne_raw" / png(index))))
        assert len(step[rec.LIDAR_3D]["Points3D:positions"]) == lidar


def test_complete_drive_and_point_cloud_record_the_lidar(tmp_path, capsys):
    drive = write_drive(tmp_path / "raw", make_sequence(2, 0, height=SIZE[0], width=SIZE[1], beams=16))
    out, rrd = tmp_path / "out", tmp_path / "drive.rrd"
    code, _, err = run_main(["complete", "--input-dir", drive, "--out-dir", out, "--rerun", rrd, *FAST], capsys)
    assert code == 0, err
    found = read_recording(rrd)
    frames = KittiDrive(drive)
    assert sorted(found[rec.DEPTH]) == [0, 1]
    for index in range(2):
        step = _step(found, index)
        assert np.abs(depth_image(step[rec.DEPTH]) - read_depth_png(out / f"{drive_stem(index)}.png")).max() \
            <= PNG_CODE
        lidar = int(np.count_nonzero(frames[index].sparse))  # the scan's pixels, as the model saw them
        assert len(step[rec.LIDAR_3D]["Points3D:positions"]) == lidar
    # one frame from its raw scan: every point of the cloud in 3D
    scan = drive / "velodyne_points" / "data" / f"{drive_stem(1)}.bin"
    code, _, err = run_main(["complete", "--image", drive / "image_02" / "data" / f"{drive_stem(1)}.png", "--points",
                             scan, "--calib", drive.parent, "--out", tmp_path / "one.png", "--rerun",
                             tmp_path / "one.rrd", *FAST], capsys)
    assert code == 0, err
    step = _step(read_recording(tmp_path / "one.rrd"), 0)
    assert len(step[rec.LIDAR_3D]["Points3D:positions"]) == len(read_velodyne(scan))
    assert np.abs(depth_image(step[rec.DEPTH]) - read_depth_png(tmp_path / "one.png")).max() <= PNG_CODE


def test_targets_record_poses_trajectory_scans_and_targets(tmp_path, capsys):
    count = 4
    sequence = make_sequence(count, 0, height=SIZE[0], width=SIZE[1], beams=16)
    drive = write_drive(tmp_path / "raw", sequence)
    out, rrd = tmp_path / "out", tmp_path / "targets.rrd"
    code, _, err = run_main(["targets", "--drive", drive, "--poses", poses_file(drive), "-k", 1, "--out-dir", out,
                             "--quiet", "--rerun", rrd], capsys)
    assert code == 0, err
    found = read_recording(rrd)
    assert {rec.CAMERA, rec.IMAGE, rec.LIDAR_2D, rec.LIDAR_3D, rec.TARGETS, rec.TRAJECTORY} <= set(found)
    assert rec.DEPTH not in found and rec.STD not in found
    assert sorted(found[rec.TARGETS]) == sorted(found[rec.CAMERA]) == list(range(count))
    world = np.linalg.inv(sequence[0].T_w_cam)  # the world: the camera of the first scan
    for index in range(count):
        step = _step(found, index)
        np.testing.assert_allclose(pinhole_K(step[rec.IMAGE]), sequence[0].K, rtol=1e-6)
        np.testing.assert_allclose(pose(step[rec.CAMERA]), world @ sequence[index].T_w_cam, atol=1e-4)
        written = read_depth_png(out / DRIVE / "proj_depth" / "groundtruth" / "image_02" / f"{drive_stem(index)}.png")
        assert np.abs(depth_image(step[rec.TARGETS]) - written).max() <= PNG_CODE
        scan = read_velodyne(drive / "velodyne_points" / "data" / f"{drive_stem(index)}.bin")
        assert len(step[rec.LIDAR_3D]["Points3D:positions"]) == len(scan)
    positions = [(world @ frame.T_w_cam)[:3, 3] for frame in sequence]
    np.testing.assert_allclose(found[rec.TRAJECTORY][count - 1]["LineStrips3D:strips"], positions, atol=1e-4)


def test_complete_and_targets_on_a_bag_record_each_frame(tmp_path, capsys):
    pytest.importorskip("rosbags")
    from tests.cli.test_targets_bag import write_bag as write_sequence_bag
    from tests.io.ros.bags import IMAGE_TOPIC, POINTS_TOPIC, write_bag

    recorded = write_bag(tmp_path / "in.bag", "ros1", count=3)
    out, rrd = tmp_path / "out", tmp_path / "bag.rrd"
    code, _, err = run_main(["complete", "--bag", recorded.path, "--image-topic", IMAGE_TOPIC, "--points-topic",
                             POINTS_TOPIC, "--out-dir", out, "--out-std-dir", tmp_path / "std", "--rerun", rrd, *FAST],
                            capsys)
    assert code == 0, err
    found = read_recording(rrd)
    assert COMPLETE_ENTITIES | {rec.STD} <= set(found) and sorted(found[rec.DEPTH]) == [0, 1, 2]
    assert sorted(read_recording(rrd, "stamp")[rec.DEPTH]) == recorded.image_ns  # the images' header stamps
    for index, stamp in enumerate(recorded.image_ns):
        step = _step(found, index)
        np.testing.assert_allclose(pinhole_K(step[rec.IMAGE]), recorded.K, rtol=1e-6)
        assert np.abs(depth_image(step[rec.DEPTH]) - read_depth_png(out / f"{stamp}.png")).max() <= PNG_CODE
        assert len(step[rec.LIDAR_3D]["Points3D:positions"]) == len(recorded.clouds[index])
    # targets --bag: the bag's frames as a drive, recorded by the drive's code path
    sequence = make_sequence(3, 0, height=SIZE[0], width=SIZE[1], beams=16)
    bag = write_sequence_bag(tmp_path / "rig.bag", sequence)
    code, _, err = run_main(["targets", "--bag", bag, "-k", 1, "--out-dir", tmp_path / "targets", "--quiet",
                             "--rerun", tmp_path / "targets.rrd"], capsys)
    assert code == 0, err
    found = read_recording(tmp_path / "targets.rrd")
    assert sorted(found[rec.TARGETS]) == [0, 1, 2] and rec.DEPTH not in found
    world = np.linalg.inv(sequence[0].T_w_cam)
    np.testing.assert_allclose(pose(found[rec.CAMERA][2]), world @ sequence[2].T_w_cam, atol=1e-3)
    assert [len(found[rec.LIDAR_3D][i]["Points3D:positions"]) for i in range(3)] == \
        [len(frame.points) for frame in sequence]


# --------------------------------------------------------------------------- bad input


@pytest.fixture
def no_computation(monkeypatch):
    """Fail the test if a command gets as far as building its model."""

    def refuse(*args, **kwargs):
        raise AssertionError("the command started computing before refusing its input")

    monkeypatch.setattr(demo, "load_pretrained", refuse)
    monkeypatch.setattr("crfdepth.cli.complete_one.build_model", refuse)


@pytest.mark.parametrize("path, message", [
    ("depth.png", "--rerun: expected a file name ending in .rrd, got {tmp}/depth.png"),
    ("nowhere/run.rrd", "--rerun: the folder of {tmp}/nowhere/run.rrd does not exist"),
    ("/proc/run.rrd", "--rerun: cannot create /proc/run.rrd: the folder /proc does not accept new files"),
])
def test_a_bad_recording_path_is_refused_before_any_computation(tmp_path, capsys, no_computation, path, message):
    folder = write_folder(tmp_path / "in", 1)
    target = path if path.startswith("/") else tmp_path / path
    expected = message.format(tmp=tmp_path)
    for argv in (["demo", "--out-dir", tmp_path / "demo"],
                 ["complete", *_frame(folder), "--out", tmp_path / "d.png", *FAST],
                 ["targets", "--drive", tmp_path / "drive", "--out-dir", tmp_path / "t"]):
        code, _, err = run_main([*argv, "--rerun", target], capsys)
        assert code == 2 and len(err.splitlines()) == 1, err
        assert err.startswith(f"crfdepth {argv[0]}: error: {expected}"), err
    assert _files(tmp_path) == ["in"]  # nothing created


def test_a_failed_run_leaves_no_recording(tmp_path, capsys):
    folder = write_folder(tmp_path / "in", 2, bad={1: "zero sparse"})
    out = tmp_path / "records"
    out.mkdir()
    code, _, err = run_main(["complete", "--input-dir", folder, "--out-dir", tmp_path / "out", "--rerun",
                             out / "run.rrd", *FAST], capsys)
    assert code == 2 and "frame 2/2" in err.splitlines()[0], err
    code, _, err = run_main(["complete", *_frame(folder, 1), "--out", tmp_path / "d.png", "--rerun", out / "one.rrd",
                             *FAST], capsys)
    assert code == 2 and len(err.splitlines()) == 1, err
    assert _files(out) == []  # neither recording, nor a temporary file


def test_rerun_is_refused_with_many_processes_or_an_input_list(tmp_path, capsys):
    folder = write_folder(tmp_path / "in", 1)
    listing = tmp_path / "list.txt"
    listing.write_text(f"{folder}\n")
    for extra, named in ((["--input-dir", folder, "--devices", 2], "--devices 2"),
                         (["--input-list", listing], "--input-list")):
        code, _, err = run_main(["complete", *extra, "--out-dir", tmp_path / "out", "--rerun", tmp_path / "r.rrd",
                                 *FAST], capsys)
        assert code == 2 and err == (f"crfdepth complete: error: --rerun: records the frames of one process (one "
                                     f"frame, --input-dir or --bag), got {named}\n")
    assert _files(tmp_path) == ["in", "list.txt"]


def test_without_rerun_sdk_the_command_names_the_extra(tmp_path, capsys, monkeypatch, no_computation):
    monkeypatch.setitem(sys.modules, "rerun", None)  # import rerun raises ImportError
    code, _, err = run_main(["demo", "--out-dir", tmp_path / "demo", "--rerun", tmp_path / "demo.rrd"], capsys)
    assert code == 2 and err == ("crfdepth demo: error: --rerun: needs the viewer extra: pip install "
                                 "'crfdepth[viewer]' (rerun-sdk), got no module rerun\n")
    assert list(tmp_path.iterdir()) == []


# --------------------------------------------------------------------------- a real frame


@pytest.mark.kitti
def test_a_real_kitti_frame_records_its_lidar_and_depth(kitti_root, tmp_path, capsys):
    val = kitti_root / "depth_selection" / "val_selection_cropped"
    name = "2011_09_26_drive_0001_sync_{kind}_0000000005_image_02"  # as tests/cli/test_complete.py reads it
    image = val / "image" / f"{name.format(kind='image')}.png"
    sparse = val / "velodyne_raw" / f"{name.format(kind='velodyne_raw')}.png"
    intrinsics = val / "intrinsics" / f"{name.format(kind='image')}.txt"
    out, out_std, rrd = tmp_path / "depth.png", tmp_path / "std.png", tmp_path / "kitti.rrd"
    code, _, err = run_main(["complete", "--image", image, "--sparse", sparse, "--intrinsics", intrinsics, "--out",
                             out, "--out-std", out_std, "--rerun", rrd, "--quiet"], capsys)
    assert code == 0, err
    step = _step(read_recording(rrd), 0)
    np.testing.assert_allclose(pinhole_K(step[rec.IMAGE]), read_intrinsics(intrinsics), rtol=1e-6)
    assert np.abs(depth_image(step[rec.DEPTH]) - read_depth_png(out)).max() <= PNG_CODE
    # the PNG clips the std at its largest code (the sky's std reaches kilometres); the recording keeps it
    std, written = depth_image(step[rec.STD]), read_depth_png(out_std)
    below = written < 65535 / 256
    assert np.abs(std - written)[below].max() <= PNG_CODE and np.all(std[~below] >= 65535 / 256 - PNG_CODE)
    lidar = read_depth_png(sparse)
    assert len(step[rec.LIDAR_3D]["Points3D:positions"]) == int(np.count_nonzero(lidar)) > 10000
    assert len(step[rec.LIDAR_2D]["Points2D:positions"]) == int(np.count_nonzero(lidar))
