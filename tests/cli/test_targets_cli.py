"""``crfdepth targets`` on a synthetic drive written in KITTI's raw layout (true poses given as a
poses.txt), its bad input (exit status 2, one line, nothing written), Ctrl-C, and five real frames
of KITTI drive 0060 with LiDAR odometry (marked kitti)."""

from __future__ import annotations

import csv
import re
import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest

from crfdepth.data.synthetic import make_sequence
from crfdepth.io.files import LOCK_NAME
from crfdepth.io.kitti import read_depth_png
from crfdepth.sequences import drive_targets, pose_source
from crfdepth.sequences.poses import read_kitti_poses
from tests.cli.frames import run_main as run
from tests.sequence_drive import DRIVE, poses_file, write_drive
from tests.sequence_drive import matrix_text as _matrix
from tests.sequence_drive import stem as _stem

N_FRAMES = 7
COLUMNS = ["frame", "first_scan", "last_scan", "points", "target_pixels", "density", "scan_density",
           "own_share", "occluded", "moved", "stereo_dropped"]


@pytest.fixture(scope="module")
def sequence():
    return make_sequence(N_FRAMES, 0, height=176, width=608, movers=1)


@pytest.fixture(scope="module")
def synthetic_drive(tmp_path_factory, sequence) -> Path:
    return write_drive(tmp_path_factory.mktemp("raw"), sequence)


def first_line(err: str) -> str:
    return err.splitlines()[0] if err else ""


def files(folder: Path) -> list[str]:
    return sorted(str(p.relative_to(folder)) for p in folder.rglob("*") if p.is_file()) if folder.exists() else []


def copy_drive(drive: Path, tmp_path: Path) -> Path:
    """A writable copy of the day folder (with the drive and poses.txt)."""
    shutil.copytree(drive.parent.parent, tmp_path / "raw")
    return tmp_path / "raw" / drive.parent.name / drive.name


# --------------------------------------------------------------------------- the synthetic drive


def test_targets_on_a_synthetic_drive(synthetic_drive, sequence, tmp_path, capsys):
    out = tmp_path / "out"
    code, stdout, err = run(["targets", "--drive", synthetic_drive, "--poses", poses_file(synthetic_drive),
                             "-k", 3, "--out-dir", out, "--vis"], capsys)
    assert code == 0, err
    stems = [_stem(i) for i in range(N_FRAMES)]
    base = out / DRIVE
    assert files(out) == sorted(
        [f"{DRIVE}/index_image_02.csv", f"{DRIVE}/poses.txt"]
        + [f"{DRIVE}/proj_depth/groundtruth/image_02/{s}.png" for s in stems]
        + [f"{DRIVE}/proj_depth/support/image_02/{s}.png" for s in stems])
    assert files(Path(f"{out}_vis")) == [f"{DRIVE}_image_02_{s}.png" for s in stems]
    rows = list(csv.DictReader((base / "index_image_02.csv").open()))
    assert list(rows[0]) == COLUMNS and [r["frame"] for r in rows] == stems
    assert rows[0]["first_scan"] == _stem(0) and rows[0]["last_scan"] == _stem(3)
    assert rows[3]["first_scan"] == _stem(0) and rows[3]["last_scan"] == _stem(6)

    within, ratios = [], []
    for i, s in enumerate(stems):
        depth = read_depth_png(base / "proj_depth" / "groundtruth" / "image_02" / f"{s}.png")
        support = cv2.imread(str(base / "proj_depth" / "support" / "image_02" / f"{s}.png"), cv2.IMREAD_UNCHANGED)
        has = depth > 0
        single = sequence[i].sparse > 0
        assert support.dtype == np.uint8 and support.max() <= 7
        assert np.all(support[has] >= 1) and np.all(support[~has] == 0)
        # the accumulation covers far more of the image than the frame's own scan. Measured: 2.0-3.1x (the
        # last frame 2.02x: it has only the scans behind it, which see less of what lies ahead)
        assert has.mean() > (1.8 if i == N_FRAMES - 1 else 2.0) * single.mean(), (i, has.mean(), single.mean())
        ratios.append(has.mean() / single.mean())
        assert abs(float(rows[i]["density"]) - has.mean()) < 1e-5
        assert abs(float(rows[i]["scan_density"]) - single.mean()) < 0.01
        truth = sequence[i].depth[has]
        ok = np.isfinite(truth) & (truth > 0)
        within.append(np.mean(np.abs(depth[has][ok] - truth[ok]) <= 0.03 * truth[ok]))
    assert np.mean(ratios) > 2.5, ratios  # measured: 2.71x on average
    # measured: 0.990-0.992 within 3% of the true depth on every frame (the single scan: 0.984-0.990)
    assert min(within) >= 0.95, within
    # poses.txt: the true camera poses back (relative to the first frame, which is the identity)
    written = read_kitti_poses(base / "poses.txt")
    true = np.stack([f.T_w_cam for f in sequence])
    np.testing.assert_allclose(written, true, atol=1e-6)
    # the summary line
    assert stdout.startswith(f"wrote targets of {N_FRAMES} frame(s) of {DRIVE} (image_02, k=3, poses: poses file ")
    assert "mean density" in stdout and "for the single scan" in stdout
    ratio = float(stdout.split("(")[-1].split("x)")[0])
    assert abs(ratio - np.mean(ratios)) < 0.05


def test_frames_selects_a_range_and_quiet_prints_nothing(synthetic_drive, tmp_path, capsys):
    out = tmp_path / "out"
    code, stdout, err = run(["targets", "--drive", synthetic_drive, "--poses", poses_file(synthetic_drive),
                             "--frames", "2:3", "-k", 1, "--out-dir", out, "--quiet"], capsys)
    assert code == 0 and stdout == "" and err == ""
    base = out / DRIVE
    assert files(base / "proj_depth" / "groundtruth") == ["image_02/0000000002.png", "image_02/0000000003.png"]
    rows = list(csv.DictReader((base / "index_image_02.csv").open()))
    assert [(r["first_scan"], r["last_scan"]) for r in rows] == [(_stem(1), _stem(3)), (_stem(2), _stem(4))]
    # poses.txt: the scans used, frames 1-4, relative to frame 1
    assert len(read_kitti_poses(base / "poses.txt")) == 4


# --------------------------------------------------------------------------- bad input


def _refused(argv, capsys, out: Path, expected: str) -> None:
    code, _, err = run(argv, capsys)
    assert code == 2, err
    assert first_line(err) == expected
    assert not out.exists() and files(out) == []


def test_refuses_a_folder_without_scans(tmp_path, capsys):
    drive = tmp_path / "day" / DRIVE
    (drive / "image_02" / "data").mkdir(parents=True)
    _refused(["targets", "--drive", drive, "--out-dir", tmp_path / "out"], capsys, tmp_path / "out",
             f"crfdepth targets: error: --drive {drive}: expected a KITTI raw drive folder with "
             f"velodyne_points/data/*.bin and image_02/data/*.png, got no velodyne_points/data")


def test_refuses_a_folder_without_images(synthetic_drive, tmp_path, capsys):
    drive = copy_drive(synthetic_drive, tmp_path)
    shutil.rmtree(drive / "image_02")
    _refused(["targets", "--drive", drive, "--out-dir", tmp_path / "out"], capsys, tmp_path / "out",
             f"crfdepth targets: error: --drive {drive}: expected a KITTI raw drive folder with "
             f"velodyne_points/data/*.bin and image_02/data/*.png, got no image_02/data")


def test_refuses_images_without_scans(synthetic_drive, tmp_path, capsys):
    drive = copy_drive(synthetic_drive, tmp_path)
    (drive / "velodyne_points" / "data" / f"{_stem(4)}.bin").unlink()
    _refused(["targets", "--drive", drive, "--out-dir", tmp_path / "out"], capsys, tmp_path / "out",
             f"crfdepth targets: error: --drive {drive}: expected a scan and an image for every frame, got 1 "
             f"image(s) without a scan (the first: frame 0000000004, missing in velodyne_points/data)")


def test_refuses_scans_without_images(synthetic_drive, tmp_path, capsys):
    drive = copy_drive(synthetic_drive, tmp_path)
    (drive / "image_02" / "data" / f"{_stem(2)}.png").unlink()
    (drive / "image_02" / "data" / f"{_stem(5)}.png").unlink()
    _refused(["targets", "--drive", drive, "--out-dir", tmp_path / "out"], capsys, tmp_path / "out",
             f"crfdepth targets: error: --drive {drive}: expected a scan and an image for every frame, got 2 "
             f"scan(s) without a image (the first: frame 0000000002, missing in image_02/data)")


def test_refuses_a_gap_unless_frames_selects_a_gap_free_range(synthetic_drive, sequence, tmp_path, capsys):
    drive = write_drive(tmp_path / "raw", sequence, frames=[0, 1, 2, 3, 5, 6])
    out = tmp_path / "out"
    args = ["targets", "--drive", drive, "--poses", poses_file(drive), "--out-dir", out, "--quiet"]
    _refused(args, capsys, out,
             f"crfdepth targets: error: --drive {drive}: expected consecutive frame numbers, got a gap after frame "
             f"0000000003 (next: 0000000005; 1 gap(s)); give --frames A:B for a gap-free range")
    _refused([*args, "--frames", "3:5"], capsys, out,
             "crfdepth targets: error: --frames 3:5: expected a gap-free range, got frame 0000000004 missing (1 of 3)")
    # the poses file has one line per frame of the full sequence: 7 for the 6 frames present
    _refused([*args, "--frames", "1:2"], capsys, out,
             f"crfdepth targets: error: --poses {poses_file(drive)}: expected 6 poses (one per frame of the drive, "
             f"in frame order), got 7")


def test_a_gap_free_range_beside_a_gap_runs(synthetic_drive, sequence, tmp_path, capsys):
    drive = write_drive(tmp_path / "raw", sequence, frames=[0, 1, 2, 3, 5, 6])
    poses = np.stack([f.T_w_cam for i, f in enumerate(sequence) if i != 4])
    (tmp_path / "poses6.txt").write_text("\n".join(_matrix(P[:3, :]) for P in poses) + "\n")
    out = tmp_path / "out"
    code, _, err = run(["targets", "--drive", drive, "--poses", tmp_path / "poses6.txt", "--frames", "2:3", "-k", 2,
                        "--out-dir", out, "--quiet"], capsys)
    assert code == 0, err
    rows = list(csv.DictReader((out / DRIVE / "index_image_02.csv").open()))
    # the windows stop at the gap: frame 3's window is 1-3, not 1-5
    assert [(r["first_scan"], r["last_scan"]) for r in rows] == [(_stem(0), _stem(3)), (_stem(1), _stem(3))]


def test_refuses_a_single_frame(synthetic_drive, sequence, tmp_path, capsys):
    drive = write_drive(tmp_path / "raw", sequence, frames=[0])
    _refused(["targets", "--drive", drive, "--out-dir", tmp_path / "out"], capsys, tmp_path / "out",
             f"crfdepth targets: error: --drive {drive}: expected at least 2 frames (accumulation needs "
             f"neighbouring scans), got 1 (frame 0000000000)")


@pytest.mark.parametrize("frames, expected", [
    ("3:20", "--frames 3:20: expected frames within the drive's 0 to 6, got 3 to 20"),
    ("4:2", "--frames: expected A:B, two frame numbers with 0 <= A <= B (both included), got '4:2'"),
    ("3", "--frames: expected A:B, two frame numbers with 0 <= A <= B (both included), got '3'"),
    ("a:b", "--frames: expected A:B, two frame numbers with 0 <= A <= B (both included), got 'a:b'"),
])
def test_refuses_bad_frames(synthetic_drive, tmp_path, capsys, frames, expected):
    _refused(["targets", "--drive", synthetic_drive, "--poses", poses_file(synthetic_drive), "--frames", frames,
              "--out-dir", tmp_path / "out"], capsys, tmp_path / "out", f"crfdepth targets: error: {expected}")


def test_refuses_a_negative_window(synthetic_drive, tmp_path, capsys):
    _refused(["targets", "--drive", synthetic_drive, "-k", "-1", "--out-dir", tmp_path / "out"], capsys,
             tmp_path / "out", "crfdepth targets: error: -k/--window: expected an integer in [0, 2147483647], got '-1'")


def test_refuses_a_poses_file_with_the_wrong_count(synthetic_drive, tmp_path, capsys):
    short = tmp_path / "short.txt"
    short.write_text("\n".join(poses_file(synthetic_drive).read_text().splitlines()[:5]) + "\n")
    _refused(["targets", "--drive", synthetic_drive, "--poses", short, "--out-dir", tmp_path / "out"], capsys,
             tmp_path / "out", f"crfdepth targets: error: --poses {short}: expected 7 poses (one per frame of the "
                               f"drive, in frame order), got 5")


def test_refuses_a_missing_poses_file(synthetic_drive, tmp_path, capsys):
    missing = tmp_path / "nope.txt"
    code, _, err = run(["targets", "--drive", synthetic_drive, "--poses", missing, "--out-dir", tmp_path / "out"],
                       capsys)
    assert code == 2 and first_line(err).startswith(f"crfdepth targets: error: --poses {missing}: ")
    assert "no such file" in first_line(err) and not (tmp_path / "out").exists()


def test_refuses_odometry_that_fails(synthetic_drive, tmp_path, capsys):
    """A degenerate scan (300 returns) in the middle: the odometry's check names its frame."""
    pytest.importorskip("kiss_icp")
    drive = copy_drive(synthetic_drive, tmp_path)
    path = drive / "velodyne_points" / "data" / f"{_stem(3)}.bin"
    np.fromfile(path, np.float32).reshape(-1, 4)[:300].tofile(path)
    code, _, err = run(["targets", "--drive", drive, "--poses", "odometry", "--out-dir", tmp_path / "out"], capsys)
    assert code == 2
    line = first_line(err)
    assert line.startswith("crfdepth targets: error: --poses odometry: expected LiDAR odometry without failures, "
                           "got ")
    assert "frame 0000000003: " in line and "a degenerate scan" in line and line.endswith(
        "nothing written; choose --frames that avoid them or give --poses FILE")
    assert not (tmp_path / "out").exists()


@pytest.mark.parametrize("mode, why", [("odometry", ""), ("auto", "the drive has no oxts/data, and ")])
def test_odometry_without_kiss_icp_names_the_extra(synthetic_drive, tmp_path, capsys, monkeypatch, mode, why):
    monkeypatch.setattr(pose_source, "kiss_installed", lambda: False)
    _refused(["targets", "--drive", synthetic_drive, "--poses", mode, "--out-dir", tmp_path / "out"], capsys,
             tmp_path / "out", f"crfdepth targets: error: --poses {mode}: {why}LiDAR odometry needs the kiss-icp "
                               f"package, not installed; pip install \"crfdepth[odometry]\", or give --poses FILE")


def test_kiss_icp_missing_is_detected(monkeypatch):
    import sys

    monkeypatch.setitem(sys.modules, "kiss_icp", None)
    assert pose_source.kiss_installed() is False


def test_refuses_an_output_folder_inside_the_drive(synthetic_drive, tmp_path, capsys):
    drive = copy_drive(synthetic_drive, tmp_path)
    out = drive / "targets"
    _refused(["targets", "--drive", drive, "--poses", poses_file(drive), "--out-dir", out], capsys, out,
             f"crfdepth targets: error: --out-dir: {out} is inside the input drive {drive}; refusing to write there")


def test_refuses_a_locked_output_folder(synthetic_drive, tmp_path, capsys):
    out = tmp_path / "out"
    from crfdepth.io.files import lock_folder

    out.mkdir()
    with lock_folder(out, "--out-dir"):
        code, _, err = run(["targets", "--drive", synthetic_drive, "--poses", poses_file(synthetic_drive),
                            "--out-dir", out], capsys)
    assert code == 2
    assert first_line(err).startswith(f"crfdepth targets: error: --out-dir: the folder {out} is being written by "
                                      f"another crfdepth run")
    assert files(out) == []  # the lock is released, nothing written


def test_ctrl_c_reports_the_frames_written(synthetic_drive, tmp_path, capsys, monkeypatch):
    real, calls = drive_targets.camera_view_targets, []

    def interrupting(*args, **kwargs):
        if len(calls) == 2:
            raise KeyboardInterrupt
        calls.append(1)
        return real(*args, **kwargs)

    monkeypatch.setattr(drive_targets, "camera_view_targets", interrupting)
    out = tmp_path / "out"
    code, _, err = run(["targets", "--drive", synthetic_drive, "--poses", poses_file(synthetic_drive), "-k", 1,
                        "--out-dir", out], capsys)
    assert code == 130
    assert err == f"crfdepth targets: interrupted after 2 of {N_FRAMES} frame(s) written to {out / DRIVE}\n"
    assert files(out / DRIVE / "proj_depth" / "groundtruth") == ["image_02/0000000000.png", "image_02/0000000001.png"]
    rows = list(csv.DictReader((out / DRIVE / "index_image_02.csv").open()))
    assert [r["frame"] for r in rows] == [_stem(0), _stem(1)]  # the index lists exactly the frames written
    assert not (out / LOCK_NAME).exists()


def test_odometry_on_the_flat_street_drops_the_ground(synthetic_drive, sequence, tmp_path, capsys):
    """All points slide on the flat street (about 1 m short per 1 m step); the registration check
    fails every step, the retry without the ground passes, and the poses follow the true ones."""
    pytest.importorskip("kiss_icp")
    out = tmp_path / "out"
    code, stdout, err = run(["targets", "--drive", synthetic_drive, "--poses", "odometry", "-k", 1, "--out-dir", out],
                            capsys)
    assert code == 0, err
    assert "poses: LiDAR odometry (KISS-ICP; the full scans' registration slid, so points below z = -1.3" in stdout
    est = read_kitti_poses(out / DRIVE / "poses.txt", sequence.T_cam_lidar)
    # measured: at most 0.3 m from the true poses after 0.6 s at 10 m/s (6 m)
    assert np.abs(est[:, :3, 3] - sequence.lidar_poses()[:, :3, 3]).max() < 0.5


def test_refuses_odometry_that_slides(tmp_path, capsys):
    """At 4 m/s KISS-ICP slides with and without the ground (0.3-0.4 m short per step, no speed or
    jump check fires): the registration check names the frames, nothing is written."""
    pytest.importorskip("kiss_icp")
    drive = write_drive(tmp_path / "raw", make_sequence(6, 0, speed=4.0, height=88, width=304))
    out = tmp_path / "out"
    code, _, err = run(["targets", "--drive", drive, "--poses", "odometry", "--out-dir", out], capsys)
    assert code == 2
    line = first_line(err)
    # measured: frames 2, 3 and 5 fail, +0.36 to +0.42 m along x
    assert re.match(r"crfdepth targets: error: --poses odometry: expected LiDAR odometry without failures, got [1-5] "
                    r"failed step\(s\) \(frame 000000000[1-5]: the registration slid: the scan's structure fits the "
                    r"previous scan best \+0\.[3-9]\d m along x from the estimate \(limit 0\.3 m, 0\.5 deg; mean "
                    r"distance 0\.\d+ m at the estimate, 0\.\d+ m at the best\)", line), line
    assert "m along x from the estimate (limit 0.3 m, 0.5 deg; mean distance " in line
    assert line.endswith("nothing written; choose --frames that avoid them or give --poses FILE")
    assert not out.exists()


# --------------------------------------------------------------------------- the real drive

REAL_DRIVE = "sequences/2011_09_26/2011_09_26_drive_0060_sync"


@pytest.mark.kitti
def test_five_real_frames_with_odometry(kitti_root, tmp_path, capsys):
    """Frames 10-14 of drive 0060, poses from KISS-ICP over their windows' scans (5-19)."""
    pytest.importorskip("kiss_icp")
    drive = kitti_root / REAL_DRIVE
    if not drive.is_dir():
        pytest.skip(f"drive not found at {drive}")
    out = tmp_path / "out"
    code, stdout, err = run(["targets", "--drive", drive, "--poses", "odometry", "--frames", "10:14",
                             "--out-dir", out], capsys)
    assert code == 0, err
    rows = list(csv.DictReader((out / drive.name / "index_image_02.csv").open()))
    assert [r["frame"] for r in rows] == [_stem(i) for i in range(10, 15)]
    for r in rows:
        depth = read_depth_png(out / drive.name / "proj_depth" / "groundtruth" / "image_02" / f"{r['frame']}.png")
        assert abs(float(r["density"]) - float((depth > 0).mean())) < 1e-5
        # measured: see the README (density about 3x the single scan's)
        assert float(r["density"]) >= 2.0 * float(r["scan_density"]), r
    assert len(read_kitti_poses(out / drive.name / "poses.txt")) == 15
    assert "LiDAR odometry (KISS-ICP) over frames 0000000005-0000000019" in stdout  # no retry: the check passed


def test_refuses_oxts_poses_without_oxts(synthetic_drive, tmp_path, capsys):
    _refused(["targets", "--drive", synthetic_drive, "--poses", "oxts", "--out-dir", tmp_path / "out"], capsys,
             tmp_path / "out", f"crfdepth targets: error: --poses oxts: expected the drive's oxts/data folder, got no "
                               f"{synthetic_drive / 'oxts' / 'data'}")


def test_help_lists_the_options(capsys):
    code, stdout, _ = run(["targets", "--help"], capsys)
    assert code == 0
    for flag in ("--drive", "--camera", "--frames", "--window", "--poses", "--out-dir", "--vis", "--quiet"):
        assert flag in stdout


def test_a_failure_during_the_run_says_how_far_it_got(synthetic_drive, tmp_path, capsys, monkeypatch):
    """A file that breaks after the checks (here: the writer fails on the 3rd frame) stops the run with the
    count of frames written; the index lists them."""
    real, calls = drive_targets.write_depth_png, []

    def failing(path, depth):
        if len(calls) == 2:
            raise PermissionError(f"depth png: cannot write {path}")
        calls.append(1)
        return real(path, depth)

    monkeypatch.setattr(drive_targets, "write_depth_png", failing)
    out = tmp_path / "out"
    code, _, err = run(["targets", "--drive", synthetic_drive, "--poses", poses_file(synthetic_drive), "-k", 1,
                        "--out-dir", out], capsys)
    target = out / DRIVE / "proj_depth" / "groundtruth" / "image_02" / "0000000002.png"
    assert code == 2
    assert first_line(err) == (f"crfdepth targets: error: depth png: cannot write {target} [stopped at frame "
                               f"0000000002; 2 of {N_FRAMES} frame(s) written to {out / DRIVE}]")
    rows = list(csv.DictReader((out / DRIVE / "index_image_02.csv").open()))
    assert [r["frame"] for r in rows] == [_stem(0), _stem(1)]


@pytest.mark.kitti
@pytest.mark.slow
def test_stereo_check_drops_what_the_pair_contradicts(kitti_root, tmp_path, capsys):
    """Drive 0048 has both colour cameras: --stereo-check drops a few per cent of the targets (windows, roof
    outlines: docs/results/stereo_check), never adds one, and counts them in the index."""
    drive = kitti_root / "stereo" / "2011_09_26" / "2011_09_26_drive_0048_sync"
    plain, checked = tmp_path / "plain", tmp_path / "checked"
    for out, extra in ((plain, []), (checked, ["--stereo-check"])):
        assert run(["targets", "--drive", str(drive), "--out-dir", str(out), "--poses", "odometry", "-k", "1",
                    "--quiet", *extra], capsys)[0] == 0
    rows = list(csv.DictReader((checked / drive.name / "index_image_02.csv").open()))
    assert [r["stereo_dropped"] for r in list(csv.DictReader((plain / drive.name / "index_image_02.csv").open()))] \
        == ["", "", ""]
    for row in rows:
        name = f"{drive.name}/proj_depth/groundtruth/image_02/{row['frame']}.png"
        before, after = read_depth_png(plain / name), read_depth_png(checked / name)
        assert np.all((after == before) | (after == 0))  # only drops
        dropped = int(np.count_nonzero((before > 0) & (after == 0)))
        assert dropped == int(row["stereo_dropped"])
        assert 0.005 < dropped / np.count_nonzero(before) < 0.10


def test_stereo_check_needs_both_cameras(synthetic_drive, tmp_path, capsys):
    code, _, err = run(["targets", "--drive", synthetic_drive, "--out-dir", tmp_path / "o", "--poses",
                        poses_file(synthetic_drive), "--stereo-check"], capsys)
    assert code == 2
    assert err.splitlines()[0].startswith("crfdepth targets: error: --stereo-check: expected the other colour "
                                          "camera's folder ")
    assert not (tmp_path / "o").exists()
