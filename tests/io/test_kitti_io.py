"""Tests of crfdepth.io.kitti: synthetic round trips, the shared KITTI files, bad input.

The KITTI calibration files are tested in tests/io/test_calibration.py."""

from __future__ import annotations

import os
import re
from pathlib import Path

import cv2
import numpy as np
import pytest

from crfdepth.errors import InputError
from crfdepth.io import kitti
from crfdepth.io.calibration import read_raw_calibration
from crfdepth.io.kitti import read_depth_png, read_intrinsics, read_rgb, read_velodyne, write_depth_png

DRIVE = "2011_09_26_drive_0001_sync"
FRAME = "0000000005"


# --------------------------------------------------------------------------- synthetic


def test_depth_png_round_trip_is_exact(tmp_path):
    rng = np.random.default_rng(0)
    codes = rng.integers(0, 65536, size=(37, 53))
    codes[rng.random(codes.shape) < 0.5] = 0
    depth = (codes / 256.0).astype(np.float32)  # multiples of 1/256, exact in float32
    path = tmp_path / "depth.png"
    write_depth_png(path, depth)
    on_disk = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    assert on_disk.dtype == np.uint16 and on_disk.shape == (37, 53)
    np.testing.assert_array_equal(on_disk, codes)
    back = read_depth_png(path)
    assert back.dtype == np.float32 and back.shape == (37, 53)
    np.testing.assert_array_equal(back, depth)
    assert np.count_nonzero(back == 0) == np.count_nonzero(codes == 0)


def test_write_depth_png_rounds_and_clips(tmp_path):
    depth = np.array([[0.0, 1.0 + 0.4 / 256, 1.0 + 0.6 / 256, 1e-4, 300.0]])
    path = tmp_path / "d.png"
    write_depth_png(path, depth)
    on_disk = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    np.testing.assert_array_equal(on_disk, [[0, 256, 257, 0, 65535]])
    assert depth[0, 4] == 300.0  # input not modified


def test_write_depth_png_accepts_integer_metres(tmp_path):
    write_depth_png(tmp_path / "i.png", np.array([[0, 2], [5, 7]], dtype=np.int32))
    np.testing.assert_array_equal(read_depth_png(tmp_path / "i.png"), [[0, 2], [5, 7]])


def test_write_depth_png_is_atomic(tmp_path, monkeypatch):
    path = tmp_path / "d.png"
    write_depth_png(path, np.full((4, 4), 2.0))

    def failing_replace(src, dst):
        raise OSError("disk full (simulated)")

    monkeypatch.setattr(kitti.os, "replace", failing_replace)
    with pytest.raises(OSError, match="simulated"):
        write_depth_png(path, np.full((4, 4), 9.0))
    # The old file is intact and no temporary file is left behind.
    np.testing.assert_array_equal(read_depth_png(path), np.full((4, 4), 2.0))
    assert sorted(p.name for p in tmp_path.iterdir()) == ["d.png"]


# --------------------------------------------------------------------------- shared files


@pytest.mark.kitti
@pytest.mark.parametrize("kind, folder, valid_range", [
    ("velodyne_raw", "data_depth_velodyne", (0.03, 0.05)),
    ("groundtruth", "data_depth_annotated", (0.15, 0.25)),
])
@pytest.mark.parametrize("camera", ["image_02", "image_03"])
def test_read_shared_depth_pngs(kitti_root, kind, folder, valid_range, camera):
    path = (kitti_root / "depth_completion" / folder / "train" / DRIVE / "proj_depth" / kind
            / camera / f"{FRAME}.png")
    depth = read_depth_png(path)
    assert depth.shape == (375, 1242) and depth.dtype == np.float32
    valid = depth > 0
    assert valid_range[0] < valid.mean() < valid_range[1]
    assert depth.min() == 0
    assert 1.0 < depth[valid].min() and depth.max() < 90.0  # metres, not millimetres or codes
    assert 5.0 < np.median(depth[valid]) < 30.0


@pytest.mark.kitti
def test_read_cropped_selection(kitti_root):
    root = kitti_root / "depth_selection" / "val_selection_cropped"
    name = f"{DRIVE}_velodyne_raw_{FRAME}_image_02.png"
    sparse = read_depth_png(root / "velodyne_raw" / name)
    assert sparse.shape == (352, 1216)
    assert 0.03 < (sparse > 0).mean() < 0.05
    image = read_rgb(root / "image" / f"{DRIVE}_image_{FRAME}_image_02.png")
    assert image.shape == (352, 1216, 3) and image.dtype == np.uint8


@pytest.mark.kitti
def test_read_rgb_converts_bgr_to_rgb(kitti_root):
    path = kitti_root / "raw" / "2011_09_26" / DRIVE / "image_02" / "data" / f"{FRAME}.png"
    rgb = read_rgb(path)
    assert rgb.shape == (375, 1242, 3) and rgb.dtype == np.uint8
    bgr = cv2.imread(str(path), cv2.IMREAD_COLOR)
    np.testing.assert_array_equal(rgb, bgr[:, :, ::-1])
    assert not np.array_equal(rgb, bgr)  # a colour image: the channel order matters


@pytest.mark.kitti
def test_read_rgb_repeats_greyscale(kitti_root):
    path = kitti_root / "raw" / "2011_09_26" / DRIVE / "image_00" / "data" / f"{FRAME}.png"
    grey = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    assert grey.ndim == 2
    rgb = read_rgb(path)
    assert rgb.shape == grey.shape + (3,)
    for channel in range(3):
        np.testing.assert_array_equal(rgb[:, :, channel], grey)


@pytest.mark.kitti
def test_read_intrinsics_matches_file(kitti_root):
    path = (kitti_root / "depth_selection" / "val_selection_cropped" / "intrinsics"
            / f"{DRIVE}_image_{FRAME}_image_02.txt")
    K = read_intrinsics(path)
    assert K.shape == (3, 3) and K.dtype == np.float64
    np.testing.assert_array_equal(K, [[721.5377, 0.0, 596.5593], [0.0, 721.5377, 149.854], [0.0, 0.0, 1.0]])
    # The benchmark crop shifts the principal point of P_rect_02 by (-13, -23).
    P = read_raw_calibration(kitti_root / "raw" / "2011_09_26", camera=2).P_rect
    np.testing.assert_allclose(K[:2, 2], P[:2, 2] - [13, 23], atol=1e-9)


@pytest.mark.kitti
def test_read_velodyne_shared_scan(kitti_root):
    path = kitti_root / "raw" / "2011_09_26" / DRIVE / "velodyne_points" / "data" / f"{FRAME}.bin"
    points = read_velodyne(path)
    assert points.dtype == np.float32 and points.shape == (os.path.getsize(path) // 16, 4)
    assert points.shape[0] == 121948
    assert 0.0 <= points[:, 3].min() and points[:, 3].max() <= 1.0  # reflectance
    assert np.abs(points[:, :3]).max() < 130.0  # metres (HDL-64E range ~120 m)


# --------------------------------------------------------------------------- bad input


def test_missing_files_name_the_path(tmp_path):
    missing = tmp_path / "nope" / "0000000005"
    for reader, suffix in [(read_depth_png, ".png"), (read_rgb, ".png"), (read_intrinsics, ".txt"),
                           (read_velodyne, ".bin")]:
        path = missing.with_suffix(suffix)
        with pytest.raises(FileNotFoundError, match=re.escape(str(path))):
            reader(path)


def test_depth_png_must_be_16_bit(tmp_path):
    path = tmp_path / "eight_bit.png"
    cv2.imwrite(str(path), np.full((5, 6), 7, dtype=np.uint8))
    with pytest.raises(InputError, match=r"16-bit.*got uint8.*eight_bit\.png"):
        read_depth_png(path)
    colour = tmp_path / "colour16.png"
    cv2.imwrite(str(colour), np.full((5, 6, 3), 7, dtype=np.uint16))
    with pytest.raises(InputError, match=r"single-channel.*3 channel"):
        read_depth_png(colour)


def test_undecodable_image(tmp_path):
    path = tmp_path / "garbage.png"
    path.write_bytes(b"not a png at all")
    with pytest.raises(InputError, match=r"garbage\.png is not a readable image"):
        read_depth_png(path)
    with pytest.raises(InputError, match=r"garbage\.png"):
        read_rgb(path)


def test_rgb_must_be_8_bit(tmp_path):
    path = tmp_path / "sixteen.png"
    cv2.imwrite(str(path), np.full((5, 6, 3), 700, dtype=np.uint16))
    with pytest.raises(InputError, match=r"8-bit.*got uint16"):
        read_rgb(path)


def test_velodyne_size_must_be_multiple_of_16(tmp_path):
    path = tmp_path / "scan.bin"
    np.zeros(5, dtype=np.float32).tofile(path)  # 20 bytes
    with pytest.raises(InputError, match=r"multiple of 16 bytes.*got 20 bytes.*scan\.bin"):
        read_velodyne(path)


def test_intrinsics_must_hold_nine_numbers(tmp_path):
    path = tmp_path / "K.txt"
    path.write_text("1 0 2 0 1 3 0 0\n")
    with pytest.raises(InputError, match=r"expected 9 numbers.*K\.txt, got 8"):
        read_intrinsics(path)
    path.write_text("1 0 2 0 1 3 0 0 x\n")
    with pytest.raises(InputError, match=r"non-numeric"):
        read_intrinsics(path)


@pytest.mark.parametrize("depth, match", [
    (np.array([[1.0, np.nan]]), r"depth: expected finite values.*1 NaN"),
    (np.array([[1.0, np.inf]]), r"depth: expected finite values"),
    (np.array([[1.0, -0.5]]), r"depth: expected values >= 0.*-0\.5"),
    (np.zeros((2, 3, 1)), r"depth: expected a 2-D \(H, W\) array.*\(2, 3, 1\)"),
    (np.zeros(4), r"depth: expected a 2-D.*\(4,\)"),
    (np.array([["a", "b"]]), r"depth: expected a real-valued array"),
])
def test_write_depth_png_rejects_bad_depth(tmp_path, depth, match):
    path = tmp_path / "d.png"
    with pytest.raises(InputError, match=match):
        write_depth_png(path, depth)
    assert list(tmp_path.iterdir()) == []


def test_write_depth_png_bad_paths(tmp_path):
    with pytest.raises(FileNotFoundError, match=re.escape(str(tmp_path / "missing_dir"))):
        write_depth_png(tmp_path / "missing_dir" / "d.png", np.ones((2, 2)))
    a_file = tmp_path / "a_file"
    a_file.write_text("")
    with pytest.raises(FileNotFoundError, match="output directory does not exist"):
        write_depth_png(a_file / "d.png", np.ones((2, 2)))
    with pytest.raises(InputError, match=r"path: expected a file name ending in \.png.*d\.jpg"):
        write_depth_png(tmp_path / "d.jpg", np.ones((2, 2)))
    assert [p.name for p in tmp_path.iterdir()] == ["a_file"]


@pytest.mark.skipif(not hasattr(os, "geteuid") or os.geteuid() == 0,
                    reason="directory permissions do not bind root or non-POSIX systems")
def test_write_depth_png_unwritable_directory(tmp_path):
    locked = tmp_path / "locked"
    locked.mkdir()
    locked.chmod(0o500)
    try:
        with pytest.raises(PermissionError):
            write_depth_png(locked / "d.png", np.ones((2, 2)))
        assert list(locked.iterdir()) == []
    finally:
        locked.chmod(0o700)


@pytest.mark.skipif(os.name != "posix", reason="POSIX permission bits")
def test_new_file_permissions_follow_umask(tmp_path):
    path = tmp_path / "d.png"
    write_depth_png(path, np.ones((2, 2)))
    umask = os.umask(0)
    os.umask(umask)
    assert Path(path).stat().st_mode & 0o777 == 0o666 & ~umask
