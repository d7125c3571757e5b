"""Tests of ``crfdepth project`` (crfdepth.cli.project) on the shared KITTI frames.

Bad input: exit status 2, one line on stderr naming the flag, nothing written.
"""

from __future__ import annotations

import os

import cv2
import numpy as np
import pytest

from crfdepth import cli
from crfdepth.geometry.projection import keep_every_ring, keep_fraction, project_velodyne
from crfdepth.io.calibration import load_calibration
from crfdepth.io.kitti import read_depth_png, read_velodyne

DRIVE = "2011_09_26_drive_0001_sync"
FRAME = "0000000005"


def test_project_is_registered():
    assert "crfdepth.cli.project" in cli._COMMANDS


@pytest.fixture
def main(monkeypatch):
    """``crfdepth.cli.main`` with only this sub-command registered.

    Keeps these tests about ``project`` alone: another sub-command's import cannot make
    them fail (those are tested in their own files).
    """
    monkeypatch.setattr(cli, "_COMMANDS", ("crfdepth.cli.project",))
    return cli.main


@pytest.fixture
def raw_paths(kitti_root):
    day = kitti_root / "raw" / "2011_09_26"
    return {
        "day": day,
        "velodyne": day / DRIVE / "velodyne_points" / "data" / f"{FRAME}.bin",
        "image": day / DRIVE / "image_02" / "data" / f"{FRAME}.png",
    }


def _args(velodyne, calib, image, out, *extra):
    return ["project", "--velodyne", str(velodyne), "--calib", str(calib), "--image", str(image),
            "--out", str(out), *map(str, extra)]


def _exit(main, argv) -> int:
    """The exit status of ``main(argv)``, whether returned or raised by argparse."""
    try:
        return main(argv)
    except SystemExit as exc:
        return exc.code


@pytest.mark.kitti
def test_project_raw_frame(main, raw_paths, tmp_path, capsys):
    out = tmp_path / "sparse.png"
    assert main(_args(raw_paths["velodyne"], raw_paths["day"], raw_paths["image"], out)) == 0
    assert capsys.readouterr().out == f"wrote {out}: 19137 LiDAR pixels, 375x1242\n"
    assert [p.name for p in tmp_path.iterdir()] == ["sparse.png"]
    assert cv2.imread(str(out), cv2.IMREAD_UNCHANGED).dtype == np.uint16
    depth = read_depth_png(out)
    assert depth.shape == cv2.imread(str(raw_paths["image"])).shape[:2] == (375, 1242)
    expected = project_velodyne(read_velodyne(raw_paths["velodyne"]), load_calibration(raw_paths["day"]),
                                (375, 1242))
    assert np.count_nonzero(depth) == np.count_nonzero(expected) == 19137
    np.testing.assert_allclose(depth, expected, atol=1 / 512)  # PNG quantisation: 1/256 m


@pytest.mark.kitti
def test_project_with_subsampling(main, raw_paths, tmp_path, capsys):
    out = tmp_path / "sparse.png"
    status = main(_args(raw_paths["velodyne"], raw_paths["day"], raw_paths["image"], out,
                        "--keep-every-ring", 4, "--keep-fraction", 0.5, "--seed", 7, "--quiet"))
    assert status == 0
    assert capsys.readouterr().out == ""  # --quiet
    points = keep_fraction(keep_every_ring(read_velodyne(raw_paths["velodyne"]), 4), 0.5, seed=7)
    expected = project_velodyne(points, load_calibration(raw_paths["day"]), (375, 1242))
    depth = read_depth_png(out)
    assert np.count_nonzero(depth) == np.count_nonzero(expected)
    assert 0.10 < np.count_nonzero(depth) / 19137 < 0.15  # a quarter of the rings, half the points


@pytest.mark.kitti
@pytest.mark.parametrize("camera", [2, 3])
def test_project_object_frame(main, kitti_root, tmp_path, camera):
    root = kitti_root / "object" / "training"
    out = tmp_path / "sparse.png"
    status = main(_args(root / "velodyne" / "000010.bin", root / "calib" / "000010.txt",
                        root / "image_2" / "000010.png", out, "--camera", camera))
    assert status == 0
    image_size = cv2.imread(str(root / "image_2" / "000010.png")).shape[:2]
    depth = read_depth_png(out)
    assert depth.shape == image_size
    expected = project_velodyne(read_velodyne(root / "velodyne" / "000010.bin"),
                                load_calibration(root / "calib" / "000010.txt", camera=camera), image_size)
    assert np.count_nonzero(depth) == np.count_nonzero(expected)
    assert 0.03 < np.count_nonzero(depth) / depth.size < 0.06


@pytest.mark.kitti
@pytest.mark.parametrize("broken, flag, what", [("velodyne", "--velodyne", "no such file"),
                                                 ("day", "--calib", "no such file"),
                                                 ("image", "--image", "no such file")])
def test_project_missing_input_fails_cleanly(main, raw_paths, tmp_path, capsys, broken, flag, what):
    paths = dict(raw_paths)
    paths[broken] = tmp_path / "does_not_exist"
    out = tmp_path / "sparse.png"
    assert main(_args(paths["velodyne"], paths["day"], paths["image"], out)) == 2
    err = capsys.readouterr().err
    assert err == f"crfdepth project: error: {flag}: {what}: {tmp_path / 'does_not_exist'}\n"
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize("option, value, message", [
    ("--keep-every-ring", "0", "--keep-every-ring: expected an integer in [1, 128] (keep one laser ring in K), got '0'"),
    ("--keep-every-ring", "two", "--keep-every-ring: expected an integer in [1, 128] (keep one laser ring in K), got 'two'"),
    ("--keep-fraction", "0", "--keep-fraction: expected a number in (0, 1] (the share of points kept), got '0'"),
    ("--keep-fraction", "1.5", "--keep-fraction: expected a number in (0, 1] (the share of points kept), got '1.5'"),
    ("--keep-fraction", "nan", "--keep-fraction: expected a number in (0, 1] (the share of points kept), got 'nan'"),
])
def test_project_bad_options_fail_at_parse_time(main, tmp_path, capsys, option, value, message):
    """Refused by argparse before any file is looked at (the inputs here do not even exist)."""
    argv = _args(tmp_path / "x.bin", tmp_path / "calib", tmp_path / "img.png", tmp_path / "sparse.png", option, value)
    assert _exit(main, argv) == 2
    err = capsys.readouterr().err
    assert err == f"crfdepth project: error: {message}\n"
    assert list(tmp_path.iterdir()) == []


@pytest.mark.kitti
@pytest.mark.parametrize("out, message", [
    ("no_dir/sparse.png", "--out: the folder of {tmp}/no_dir/sparse.png does not exist"),
    ("/proc/o.png", "--out: cannot create /proc/o.png: the folder /proc does not accept new files"),
    ("sparse.jpg", "--out: expected a file name ending in .png, got {tmp}/sparse.jpg"),
])
def test_project_bad_out_fails_before_reading_inputs(main, raw_paths, tmp_path, capsys, monkeypatch, out, message):
    """--out is checked first: no input is read (the readers would fail loudly) and nothing is written."""
    if out.startswith("/proc") and not os.path.isdir("/proc"):
        pytest.skip("no /proc on this system")
    import crfdepth.cli.project as project

    def never(*args, **kwargs):
        raise AssertionError("an input was read before --out was checked")

    for reader in ("read_velodyne", "load_calibration", "read_rgb"):
        monkeypatch.setattr(project, reader, never)
    target = out if out.startswith("/") else tmp_path / out
    assert main(_args(raw_paths["velodyne"], raw_paths["day"], raw_paths["image"], target)) == 2
    err = capsys.readouterr().err
    assert err.startswith(f"crfdepth project: error: {message.format(tmp=tmp_path)}") and err.count("\n") == 1
    assert ".tmp" not in err
    assert list(tmp_path.iterdir()) == []


@pytest.mark.kitti
def test_project_out_may_not_be_an_input(main, raw_paths, tmp_path, capsys):
    image = tmp_path / "image.png"
    image.write_bytes(raw_paths["image"].read_bytes())
    assert main(_args(raw_paths["velodyne"], raw_paths["day"], image, image)) == 2
    assert "--out: expected a new file, got" in capsys.readouterr().err
    assert image.read_bytes() == raw_paths["image"].read_bytes()


@pytest.mark.kitti
def test_project_calibration_not_of_this_image(main, raw_paths, tmp_path, capsys):
    """A 17x9 image with the KITTI calibration: K's principal point is far outside, named --calib."""
    small = tmp_path / "small.png"
    cv2.imwrite(str(small), np.zeros((9, 17, 3), dtype=np.uint8))
    out = tmp_path / "sparse.png"
    assert main(_args(raw_paths["velodyne"], raw_paths["day"], small, out)) == 2
    err = capsys.readouterr().err
    assert err.startswith("crfdepth project: error: --calib: expected the principal point of the 17x9 (WxH) image")
    assert not out.exists()


@pytest.mark.kitti
def test_project_bad_calibration_file_names_calib(main, raw_paths, tmp_path, capsys):
    calib = tmp_path / "calib.txt"
    calib.write_text("P2: 1 2 3\n")
    out = tmp_path / "sparse.png"
    assert main(_args(raw_paths["velodyne"], calib, raw_paths["image"], out)) == 2
    err = capsys.readouterr().err
    assert err.startswith(f"crfdepth project: error: --calib: key 'P2' in {calib}: expected 12 numbers")
    assert not out.exists()


def test_project_truncated_scan(main, tmp_path, capsys):
    scan = tmp_path / "scan.bin"
    scan.write_bytes(b"\0" * 20)
    out = tmp_path / "sparse.png"
    assert main(_args(scan, tmp_path / "calib.txt", tmp_path / "img.png", out)) == 2
    err = capsys.readouterr().err
    assert err.startswith("crfdepth project: error: --velodyne: expected a file size that is a multiple of 16 bytes")
    assert not out.exists()
