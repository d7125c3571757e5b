"""Calibrations read as what they are (crfdepth.io.calibration, key_values, files, distortion).

A key given twice (KITTI text, rig YAML or JSON) is refused naming the key and the file; a
calibration that is a special file, huge, or a YAML with anchors and aliases is refused before it
is read or built whole, with a message that quotes no huge value; distortion coefficients that move
most of the image out of view or fold it are refused. Oracles: the real KITTI calibrations (every
one must still load), OpenCV's own distortion model, and hand-written files.
"""

from __future__ import annotations

import json
import os
import re
import shutil
import time
from pathlib import Path

import numpy as np
import pytest

from crfdepth.errors import InputError
from crfdepth.io.calibration import (
    RigCalibration,
    load_any_calibration,
    load_calibration,
    read_object_calibration,
    read_raw_calibration,
    read_rig_calibration,
)
from crfdepth.io.distortion import check_distortion
from crfdepth.io.files import MAX_CALIBRATION_BYTES, read_text
from crfdepth.io.key_values import MAX_YAML_DEPTH, MAX_YAML_NODES
from crfdepth.io.kitti import read_intrinsics
from crfdepth.sequences.poses import read_imu_to_velo

K = [[500.0, 0.0, 320.0], [0.0, 500.0, 240.0], [0.0, 0.0, 1.0]]
T = [[1.0, 0, 0, 0], [0, 1.0, 0, 0], [0, 0, 1.0, 0], [0, 0, 0, 1.0]]
RIG = f"K: {json.dumps(K)}\nT_cam_lidar: {json.dumps(T)}\nimage_size: [480, 640]\n"
LONGEST_MESSAGE = 600  # characters: a message quotes a prefix of a value, never the value


def _write(path: Path, text: str) -> Path:
    path.write_text(text)
    return path


def _refused(call, *args, match: str, **kwargs) -> str:
    """The message of the InputError ``call`` raises (matching ``match``), checked to be one short line."""
    with pytest.raises(InputError, match=match) as info:
        call(*args, **kwargs)
    message = str(info.value)
    assert "\n" not in message and len(message) < LONGEST_MESSAGE, message[:2000]
    return message


# --------------------------------------------------------------------------- the real calibrations


@pytest.mark.kitti
def test_every_real_kitti_calibration_still_loads(kitti_root):
    days = sorted({p.parent for p in kitti_root.rglob("calib_cam_to_cam.txt")})
    objects = sorted((kitti_root / "object" / "training" / "calib").glob("*.txt"))
    assert len(days) >= 4 and len(objects) == 11
    for camera in range(4):
        for day in days:
            calib = read_raw_calibration(day, camera)
            assert calib.image_size == (375, 1242) or camera < 2
            for path in (day, day / "calib_cam_to_cam.txt", day / "calib_velo_to_cam.txt"):
                assert load_any_calibration(path, camera).kitti == calib
            np.testing.assert_allclose(read_imu_to_velo(day)[3], [0, 0, 0, 1])
        for path in objects:
            assert load_any_calibration(path, camera).kitti == read_object_calibration(path, camera)
    intrinsics = sorted((kitti_root / "depth_selection").rglob("intrinsics/*.txt"))
    assert len(intrinsics) == 2
    for path in intrinsics:
        RigCalibration(K=read_intrinsics(path), T_cam_lidar=np.eye(4), image_size=(352, 1216), source=str(path))


@pytest.mark.kitti
def test_real_kitti_lens_distortion_is_accepted(kitti_root):
    """calib_cam_to_cam.txt holds each camera's unrectified K_0X, D_0X and S_0X: real lenses keep the image."""
    from crfdepth.io.key_values import read_key_values

    entries = read_key_values(kitti_root / "raw" / "2011_09_26" / "calib_cam_to_cam.txt", "calibration")
    for camera in "0123":
        K_raw = np.array(entries[f"K_0{camera}"].split(), float).reshape(3, 3)
        D = np.array(entries[f"D_0{camera}"].split(), float)
        width, height = (round(float(v)) for v in entries[f"S_0{camera}"].split())
        np.testing.assert_array_equal(check_distortion(D, K_raw, (height, width)), D)
        np.testing.assert_array_equal(check_distortion(D, K_raw, None), D)  # the image centred on (cx, cy)


# --------------------------------------------------------------------------- a key given twice


def _kitti_day(tmp_path, kitti_root) -> Path:
    day = tmp_path / "2011_09_26"
    day.mkdir()
    for name in ("calib_cam_to_cam.txt", "calib_velo_to_cam.txt", "calib_imu_to_velo.txt"):
        shutil.copy(kitti_root / "raw" / "2011_09_26" / name, day / name)
    return day


@pytest.mark.kitti
@pytest.mark.parametrize("name, key", [("calib_cam_to_cam.txt", "P_rect_02"), ("calib_cam_to_cam.txt", "S_rect_02"),
                                       ("calib_velo_to_cam.txt", "T")])
def test_raw_calibration_key_given_twice_is_refused(tmp_path, kitti_root, name, key):
    day = _kitti_day(tmp_path, kitti_root)
    path = day / name
    lines = path.read_text().splitlines()
    first = next(i for i, line in enumerate(lines, 1) if line.startswith(f"{key}:"))
    path.write_text("\n".join(lines + [lines[first - 1]]) + "\n")
    expected = (f"^calibration: expected each key once in {path}, got '{key}' twice \\(lines {first} and "
                f"{len(lines) + 1}\\): which value is meant cannot be told$")
    for call in (read_raw_calibration, load_calibration, load_any_calibration):
        _refused(call, day, match=expected)
    _refused(load_any_calibration, path, match=expected)


@pytest.mark.kitti
def test_imu_calibration_key_given_twice_is_refused(tmp_path, kitti_root):
    path = _kitti_day(tmp_path, kitti_root) / "calib_imu_to_velo.txt"
    path.write_text(path.read_text() + "R: 1 0 0 0 1 0 0 0 1\n")
    _refused(read_imu_to_velo, path.parent, match=r"^calibration: expected each key once in .*, got 'R' twice")


@pytest.mark.kitti
def test_object_calibration_key_given_twice_is_refused(tmp_path, kitti_root):
    text = (kitti_root / "object" / "training" / "calib" / "000000.txt").read_text()
    path = _write(tmp_path / "000000.txt", text + "P2: 1 0 0 0 0 1 0 0 0 0 1 0\n")
    for call in (read_object_calibration, load_calibration, load_any_calibration):
        message = _refused(call, path, match=r"^calibration: expected each key once in ")
        assert message.startswith(f"calibration: expected each key once in {path}, got 'P2' twice (lines 3 and ")


@pytest.mark.parametrize("text, key, lines", [
    (RIG + f"K: {json.dumps(K)}\n", "K", "(lines 1 and 4)"),
    (RIG + "distortion: null\ndistortion: [0.1, 0, 0, 0]\n", "distortion", "(lines 4 and 5)"),
    ("K: {fx: 1, fx: 2}\nT_cam_lidar: 1\n", "fx", "(lines 1 and 1)"),  # nested mappings too
])
def test_rig_yaml_key_given_twice_is_refused(tmp_path, text, key, lines):
    path = _write(tmp_path / "rig.yaml", text)
    _refused(read_rig_calibration, path, match=rf"^calibration: expected each key once in {path}, got '{key}' twice "
                                               + re.escape(lines))


def test_rig_json_key_given_twice_is_refused(tmp_path):
    path = _write(tmp_path / "rig.json", '{"K": %s, "T_cam_lidar": %s, "K": [1, 0, 0, 0, 1, 0, 0, 0, 1]}'
                  % (json.dumps(K), json.dumps(T)))
    _refused(load_any_calibration, path, match=rf"^calibration: expected each key once in {path}, got 'K' twice: ")


# --------------------------------------------------------------------------- special, huge and hostile files


@pytest.mark.skipif(not os.path.exists("/dev/zero"), reason="no /dev/zero")
@pytest.mark.parametrize("call", [load_any_calibration, load_calibration, read_object_calibration,
                                  read_rig_calibration, read_intrinsics])
def test_dev_zero_is_refused_before_reading(call):
    name = "intrinsics" if call is read_intrinsics else "calibration"
    _refused(call, "/dev/zero",
             match=rf"^{name}: expected a regular file, got a character device \(like /dev/zero\) /dev/zero$")


@pytest.mark.skipif(not hasattr(os, "mkfifo"), reason="no FIFOs")
@pytest.mark.parametrize("name", ["rig.yaml", "calib.txt", "K.txt"])
def test_fifo_is_refused_without_blocking(tmp_path, name):
    fifo = tmp_path / name
    os.mkfifo(fifo)
    call = read_intrinsics if name == "K.txt" else load_any_calibration
    what = "intrinsics" if name == "K.txt" else "calibration"
    _refused(call, fifo, match=rf"^{what}: expected a regular file, got a FIFO \(named pipe\) {fifo}$")
    # read_text itself, without the path check before it: opened non-blocking, refused on fstat
    _refused(read_text, fifo, "calibration", "a rig", match=r"^calibration: expected a regular file with a rig, got a "
                                                             r"FIFO \(named pipe\) ")


def test_folder_named_like_a_rig_is_refused(tmp_path):
    folder = tmp_path / "rig.yaml"
    folder.mkdir()
    with pytest.raises(IsADirectoryError, match=f"^calibration: expected a file, got a folder: {folder}$"):
        load_any_calibration(folder)
    _refused(read_text, folder, "calibration", "a rig", match=r"^calibration: expected a regular file with a rig, got "
                                                               r"a folder ")


@pytest.mark.parametrize("name", ["rig.yaml", "rig.json", "calib.txt"])
def test_calibration_over_1_mib_is_refused_before_parsing(tmp_path, name):
    path = tmp_path / name
    padding = "#" + "x" * MAX_CALIBRATION_BYTES + "\n"
    path.write_text(padding + RIG if name != "rig.json" else '{"K": "' + "x" * MAX_CALIBRATION_BYTES + '"}')
    size = path.stat().st_size
    _refused(load_any_calibration, path, match=rf"^calibration: expected a text file of at most 1 MiB \(1,048,576 "
                                               rf"bytes\) with .*, got 1 MiB \({size:,} bytes\) in {path}$")
    path.write_text("#" + "x" * (MAX_CALIBRATION_BYTES - 200) + "\n" + RIG)  # just under: read as usual
    if name == "rig.yaml":
        assert load_any_calibration(path).image_size == (480, 640)


BOMB = "\n".join(["a: &a [lol, lol, lol, lol, lol, lol, lol, lol, lol]"]
                 + [f"{c}: &{c} [{', '.join([f'*{p}'] * 9)}]" for p, c in zip("abcdefgh", "bcdefghi")]) + "\n"


def test_yaml_alias_bomb_is_refused_at_once(tmp_path):
    """A 1 KB 'billion laughs' (9^9 strings once expanded) is refused at its first anchor."""
    path = _write(tmp_path / "rig.yaml", BOMB)
    assert path.stat().st_size < 1024
    start = time.perf_counter()
    _refused(read_rig_calibration, path, match=rf"^calibration: expected plain YAML without anchors or aliases "
                                               rf"\(&name, \*name\) in {path}, got an anchor &a on line 1$")
    assert time.perf_counter() - start < 1.0


def test_yaml_alias_and_anchor_are_refused(tmp_path):
    path = _write(tmp_path / "rig.yaml", "K: *k\nT_cam_lidar: 1\n")
    _refused(read_rig_calibration, path, match=r"got an alias \*k on line 1$")
    path = _write(tmp_path / "rig.yaml", f"K: &k {json.dumps(K)}\nT_cam_lidar: {json.dumps(T)}\n")
    _refused(read_rig_calibration, path, match=r"got an anchor &k on line 1$")


def test_deep_or_large_yaml_is_refused_before_it_is_built(tmp_path):
    deep = MAX_YAML_DEPTH + 1
    path = _write(tmp_path / "rig.yaml", "K: " + "[" * deep + "]" * deep + "\n")
    _refused(read_rig_calibration, path, match=rf"^calibration: expected YAML nested at most {MAX_YAML_DEPTH} levels "
                                               rf"deep in {path}, got deeper nesting on line 1$")
    path = _write(tmp_path / "rig.yaml", "K: " + "[" * 100_000 + "]" * 100_000 + "\n")
    _refused(read_rig_calibration, path, match=r"^calibration: ")
    path = _write(tmp_path / "rig.yaml", "K: [" + ", ".join(["1"] * 300_000) + "]\nT_cam_lidar: 1\n")  # 900 kB
    start = time.perf_counter()
    _refused(read_rig_calibration, path, match=rf"^calibration: expected a calibration of at most {MAX_YAML_NODES} "
                                               rf"YAML values in {path}, got more \(line 1\)$")
    assert time.perf_counter() - start < 1.0
    path = _write(tmp_path / "rig.json", '{"K": ' + "[" * 100_000 + "]" * 100_000 + "}")
    _refused(read_rig_calibration, path, match=rf"^calibration: expected JSON nested a few levels deep \(a rig needs "
                                               rf"3\) in {path}, got nesting too deep to parse$")
    path = _write(tmp_path / "rig.json", '{"K": ' + "1" * 5000 + "}")  # over Python's 4300 digits
    _refused(read_rig_calibration, path, match=rf"^calibration: {path} is not valid JSON: ")


@pytest.mark.parametrize("name, text, match", [
    ("rig.yaml", "K: '" + "x" * 900_000 + "'\nT_cam_lidar: 1\n", r"^K \(.*\): expected a 3x3 matrix of numbers, got 'x"),
    ("rig.json", '{"K": [' + ", ".join(["1"] * 300_000) + '], "T_cam_lidar": 1}',
     r"^K \(.*\): expected a 3x3 matrix or 9 numbers \(row-major\), got shape \(300000,\)$"),
    ("rig.json", '{"K": %s, "T_cam_lidar": %s, "image_size": [%s]}' % (json.dumps(K), json.dumps(T),
                                                                         ", ".join(["7"] * 300_000)),
     r"^image_size \(.*\): expected \[height, width\] as two positive integers \(pixels\), got \[7, 7, 7, 7, 7, 7, "
     r"\.\.\.\]$"),
    ("rig.json", '{"K": %s, "T_cam_lidar": %s, "distortion": [%s]}' % (json.dumps(K), json.dumps(T),
                                                                         ", ".join(["0"] * 300_000)),
     r"^distortion \(.*\): expected 4, 5, 8, 12, 14 finite numbers .*, got 300000 numbers$"),
    ("rig.json", "{" + ", ".join(f'"k{i}": 1' for i in range(50_000)) + "}",
     r"^calibration: .*: missing key\(s\) K, T_cam_lidar \(keys present: k0, k1, .*, k11 and 49988 more\)$"),
    ("rig.yaml", RIG + "y" * 5000 + ": 1\n", r"^calibration: "),
    ("calib.txt", "P2: " + "1 " * 300_000 + "\n", r"^calibration: key 'P2' in .*: expected 12 numbers \(3, 4\), got "
                                                   r"300000$"),
    ("calib.txt", "".join(f"k{i}: 1\n" for i in range(50_000)), r"^calibration: key 'P2' not found in .* \(keys "
                                                                  r"present: .* and 49988 more\)$"),
    ("calib.txt", "z" * 500_000 + ": 1\n" + "z" * 500_000 + ": 2\n",
     r"^calibration: expected each key once in .*, got 'zzzz.*'\.\.\. \(500000 characters\) twice \(lines 1 and 2\)"),
])
def test_huge_values_are_quoted_briefly(tmp_path, name, text, match):
    path = _write(tmp_path / name, text)
    assert path.stat().st_size <= MAX_CALIBRATION_BYTES
    _refused(load_any_calibration, path, match=match)


def test_unquotable_values_are_named_by_type():
    """A value whose repr itself fails (an int over Python's 4300 digits) is described by its type."""
    _refused(RigCalibration, 10 ** 5000, np.eye(4), match=r"^calibration.K: expected a 3x3 matrix of numbers, got int$")


# --------------------------------------------------------------------------- distortion


def _rig(tmp_path, distortion, image_size="[480, 640]") -> Path:
    return _write(tmp_path / "rig.yaml", f"K: {json.dumps(K)}\nT_cam_lidar: {json.dumps(T)}\n"
                                         f"image_size: {image_size}\ndistortion: {json.dumps(distortion)}\n")


def _opencv_share_in_view(distortion) -> float:
    """Independent oracle: cv2.initUndistortRectifyMap (what cv2.undistort samples), the share inside."""
    import cv2

    map_x, map_y = cv2.initUndistortRectifyMap(np.array(K), np.array(distortion, float), None, np.array(K),
                                               (640, 480), cv2.CV_32FC1)
    return float(np.mean((map_x >= -0.5) & (map_x <= 639.5) & (map_y >= -0.5) & (map_y <= 479.5)))


@pytest.mark.parametrize("distortion", [
    [0.1, -0.25, 0.0, 0.0, 0.1],                            # the module docstring's example
    [-0.28, 0.07, 0.0, 0.0, 0.0],                           # a wide-angle plumb-bob lens
    [0.44, -2.55, 0.0007, -0.0002, 1.57, 0.32, -2.38, 1.5],  # an Azure Kinect colour camera, rational model
    [0.0] * 14,
])
def test_real_lens_distortion_is_accepted(tmp_path, distortion):
    assert _opencv_share_in_view(distortion) > 0.9
    rig = read_rig_calibration(_rig(tmp_path, distortion))
    np.testing.assert_array_equal(rig.distortion, distortion)


@pytest.mark.parametrize("distortion, share", [([3.0, 0, 0, 0, 0], 58), ([5.0, 0, 0, 0, 0, -5.0, 0, 0], 81)])
def test_distortion_out_of_view_is_refused(tmp_path, distortion, share):
    assert _opencv_share_in_view(distortion) < 0.5  # OpenCV agrees: most of the undistorted image is black
    path = _rig(tmp_path, distortion)
    coefficients = " ".join(f"{c:g}" for c in distortion)
    _refused(read_rig_calibration, path,
             match=rf"^distortion \({path}\): expected distortion coefficients that keep the 640x480 \(WxH\) image in "
                   rf"view \(at least 50% of its pixels mapped inside the raw image\), got {coefficients}, which map "
                   rf"{share}% of them outside: ")


@pytest.mark.parametrize("distortion", [[-1.0, 0, 0, 0, 0], [0.0, 0.0, 0.4, 0.4], [0.1, 0.2, 0, 0, 0, 1000.0, 0, 0]])
def test_folding_distortion_is_refused(tmp_path, distortion):
    """Oracle: the radial profile r (1 + k1 r^2) of k1 = -1 turns back at r = 1/sqrt(3) = 0.577, inside the
    640x480 image's corner radius 0.8 (f = 500 px)."""
    path = _rig(tmp_path, distortion)
    message = _refused(read_rig_calibration, path,
                       match=rf"^distortion \({path}\): expected distortion coefficients whose mapping does not fold "
                             rf"over the 640x480 \(WxH\) image, got ")
    if distortion[0] == -1.0:
        radius = float(message.split("normalised radius of ")[1].split()[0])
        assert 1 / np.sqrt(3) - 0.02 <= radius <= 1 / np.sqrt(3)


def test_distortion_given_as_arguments_is_checked_too():
    from crfdepth.api import complete_depth

    image = np.zeros((480, 640, 3), np.float32)
    sparse = np.zeros((480, 640), np.float32)
    sparse[240, 320] = 10.0
    _refused(complete_depth, image, sparse=sparse, K=np.array(K), distortion=[3.0, 0, 0, 0, 0],
             match=r"^distortion: expected distortion coefficients that keep the 640x480 \(WxH\) image in view")
    _refused(RigCalibration, np.array(K), np.eye(4), "nope" * 100_000,
             match=r"^calibration.distortion: expected a list of numbers \(OpenCV k1 k2 p1 p2 \[k3 \.\.\.\]\), got "
                   r"'nopenope")


def test_an_intrinsics_file_is_bounded_like_a_calibration(tmp_path):
    """--intrinsics is a calibration too: at most 1 MiB is read, whatever the file holds after it."""
    from crfdepth.io.kitti import read_intrinsics

    path = tmp_path / "K.txt"
    path.write_text("721.5 0 609.6 0 721.5 172.9 0 0 1\n" + "# padding\n" * 120_000)
    with pytest.raises(InputError, match=r"^intrinsics: expected a text file of at most 1 MiB"):
        read_intrinsics(path)
