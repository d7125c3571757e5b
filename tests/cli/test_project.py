"""Tests of ``crfdepth project`` (crfdepth.cli.project) on the shared KITTI frames."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from crfdepth import cli
from crfdepth.io.kitti import load_calibration, read_depth_png, read_velodyne
from crfdepth.projection import keep_every_ring, keep_fraction, project_velodyne

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


@pytest.mark.kitti
def test_project_raw_frame(main, raw_paths, tmp_path):
    out = tmp_path / "sparse.png"
    assert main(_args(raw_paths["velodyne"], raw_paths["day"], raw_paths["image"], out)) == 0
    assert cv2.imread(str(out), cv2.IMREAD_UNCHANGED).dtype == np.uint16
    depth = read_depth_png(out)
    assert depth.shape == cv2.imread(str(raw_paths["image"])).shape[:2] == (375, 1242)
    expected = project_velodyne(read_velodyne(raw_paths["velodyne"]), load_calibration(raw_paths["day"]),
                                (375, 1242))
    assert np.count_nonzero(depth) == np.count_nonzero(expected) == 19137
    np.testing.assert_allclose(depth, expected, atol=1 / 512)  # PNG quantisation: 1/256 m


@pytest.mark.kitti
def test_project_with_subsampling(main, raw_paths, tmp_path):
    out = tmp_path / "sparse.png"
    status = main(_args(raw_paths["velodyne"], raw_paths["day"], raw_paths["image"], out,
                        "--keep-every-ring", 4, "--keep-fraction", 0.5, "--seed", 7))
    assert status == 0
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
@pytest.mark.parametrize("broken", ["velodyne", "day", "image"])
def test_project_missing_input_fails_cleanly(main, raw_paths, tmp_path, capsys, broken):
    paths = dict(raw_paths)
    paths[broken] = tmp_path / "does_not_exist"
    out = tmp_path / "sparse.png"
    assert main(_args(paths["velodyne"], paths["day"], paths["image"], out)) == 2
    assert "does_not_exist" in capsys.readouterr().err
    assert not out.exists()
    assert list(tmp_path.iterdir()) == []


@pytest.mark.kitti
def test_project_bad_options_fail_cleanly(main, raw_paths, tmp_path, capsys):
    out = tmp_path / "sparse.png"
    status = main(_args(raw_paths["velodyne"], raw_paths["day"], raw_paths["image"], out, "--keep-fraction", 0))
    assert status == 2
    assert "fraction: expected a number in (0, 1]" in capsys.readouterr().err
    status = main(_args(raw_paths["velodyne"], raw_paths["day"], raw_paths["image"], out, "--keep-every-ring", 0))
    assert status == 2
    assert "k: expected an integer >= 1" in capsys.readouterr().err
    status = main(_args(raw_paths["velodyne"], raw_paths["day"], raw_paths["image"],
                        tmp_path / "no_dir" / "sparse.png"))
    assert status == 2
    assert "no_dir" in capsys.readouterr().err
    assert list(tmp_path.iterdir()) == []


def test_project_truncated_scan(main, tmp_path, capsys):
    scan = tmp_path / "scan.bin"
    scan.write_bytes(b"\0" * 20)
    out = tmp_path / "sparse.png"
    assert main(_args(scan, tmp_path / "calib.txt", tmp_path / "img.png", out)) == 2
    assert "multiple of 16 bytes" in capsys.readouterr().err
    assert not out.exists()
