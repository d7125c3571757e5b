"""Calibrations read as what they are, through the CLI: ``complete --calib`` (rig YAML/JSON or KITTI),
``complete --intrinsics``, ``complete --bag --calib`` and ``project --calib``. A special file, a huge or
hostile YAML, a key given twice, an implausible K or distortion: exit status 2, one line on stderr naming
the flag, nothing written (crfdepth.io.calibration, crfdepth.io.key_values, crfdepth.checks)."""

from __future__ import annotations

import json
import os
import time
from pathlib import Path

import cv2
import numpy as np
import pytest

from crfdepth.cli import main
from crfdepth.inputs import points_to_sparse
from crfdepth.io.calibration import load_any_calibration
from crfdepth.io.kitti import write_depth_png
from crfdepth.io.pointcloud import read_points

EXAMPLE = Path(__file__).resolve().parents[2] / "docs" / "example"
RIG = (EXAMPLE / "rig.yaml").read_text()
K_EXAMPLE = "379.7567 0 313.984 0 379.7567 204.336 0 0 1"


def _first_line(capsys, argv, out: Path) -> str:
    started = time.perf_counter()
    assert main([str(a) for a in argv]) == 2
    assert time.perf_counter() - started < 30  # refused up front: nothing read whole, nothing completed
    err = capsys.readouterr().err
    first = err.splitlines()[0]
    assert len(err) < 1000, err[:2000]  # no huge value quoted, no traceback
    assert not out.exists()
    return first


def _points(calib, out):
    return ["complete", "--image", EXAMPLE / "image.png", "--points", EXAMPLE / "scan.pcd", "--calib", calib,
            "--out", out]


@pytest.fixture()
def sparse_png(tmp_path) -> Path:
    rig = load_any_calibration(EXAMPLE / "rig.yaml")
    path = tmp_path / "sparse.png"
    write_depth_png(path, points_to_sparse(read_points(EXAMPLE / "scan.pcd"), rig, (480, 640)))
    return path


def _one_frame(sparse, intrinsics, out):
    return ["complete", "--image", EXAMPLE / "image.png", "--sparse", sparse, "--intrinsics", intrinsics, "--out", out]


# --------------------------------------------------------------------------- special files


@pytest.mark.skipif(not os.path.exists("/dev/zero"), reason="no /dev/zero")
def test_dev_zero_as_calib_is_refused(capsys, tmp_path):
    out = tmp_path / "out.png"
    first = _first_line(capsys, _points("/dev/zero", out), out)
    assert first.startswith("crfdepth complete: error: --calib")
    assert first.endswith("expected a regular file, got a character device (like /dev/zero) /dev/zero")


@pytest.mark.skipif(not os.path.exists("/dev/zero"), reason="no /dev/zero")
def test_dev_zero_as_intrinsics_is_refused(capsys, tmp_path, sparse_png):
    out = tmp_path / "out.png"
    first = _first_line(capsys, _one_frame(sparse_png, "/dev/zero", out), out)
    assert first.startswith("crfdepth complete: error: --intrinsics")
    assert first.endswith("expected a regular file, got a character device (like /dev/zero) /dev/zero")


@pytest.mark.skipif(not hasattr(os, "mkfifo"), reason="no FIFOs")
@pytest.mark.parametrize("name", ["rig.yaml", "calib.txt"])
def test_fifo_as_calib_is_refused_without_blocking(capsys, tmp_path, name):
    fifo, out = tmp_path / name, tmp_path / "out.png"
    os.mkfifo(fifo)
    first = _first_line(capsys, _points(fifo, out), out)
    assert first.startswith("crfdepth complete: error: --calib")
    assert first.endswith(f"expected a regular file, got a FIFO (named pipe) {fifo}")


@pytest.mark.skipif(not os.path.exists("/dev/zero"), reason="no /dev/zero")
def test_project_refuses_dev_zero_as_calib(capsys, tmp_path):
    out = tmp_path / "out.png"
    first = _first_line(capsys, ["project", "--velodyne", _scan(tmp_path), "--calib", "/dev/zero", "--image",
                                 EXAMPLE / "image.png", "--out", out], out)
    assert first == ("crfdepth project: error: --calib: expected a regular file, got a character device (like "
                     "/dev/zero) /dev/zero")


# --------------------------------------------------------------------------- huge and hostile YAML


def test_huge_rig_is_refused_before_parsing(capsys, tmp_path):
    rig, out = tmp_path / "rig.yaml", tmp_path / "out.png"
    rig.write_text(RIG + "# " + "x" * (2 << 20) + "\n")
    first = _first_line(capsys, _points(rig, out), out)
    assert first.startswith("crfdepth complete: error: --calib")
    size = rig.stat().st_size
    assert first.endswith(f"expected a text file of at most 1 MiB (1,048,576 bytes) with a YAML/JSON rig calibration "
                          f"(K, T_cam_lidar), got {size / 2 ** 20:.4g} MiB ({size:,} bytes) in {rig}")


def test_yaml_alias_bomb_is_refused_at_once(capsys, tmp_path):
    rig, out = tmp_path / "rig.yaml", tmp_path / "out.png"
    rig.write_text("\n".join(["a: &a [lol, lol, lol, lol, lol, lol, lol, lol, lol]"]
                             + [f"{c}: &{c} [{', '.join([f'*{p}'] * 9)}]" for p, c in zip("abcdefgh", "bcdefghi")]))
    first = _first_line(capsys, _points(rig, out), out)
    assert first.startswith("crfdepth complete: error: --calib")
    assert first.endswith(f"expected plain YAML without anchors or aliases (&name, *name) in {rig}, got an anchor &a "
                          f"on line 1")


def test_rig_key_given_twice_is_refused(capsys, tmp_path):
    rig, out = tmp_path / "rig.yaml", tmp_path / "out.png"
    rig.write_text(RIG + "K: [500, 0, 320, 0, 500, 240, 0, 0, 1]\n")
    line = 1 + next(i for i, text in enumerate(RIG.splitlines()) if text.startswith("K:"))
    first = _first_line(capsys, _points(rig, out), out)
    assert first.startswith("crfdepth complete: error: --calib")
    assert first.endswith(f"expected each key once in {rig}, got 'K' twice (lines {line} and "
                          f"{len(RIG.splitlines()) + 1}): which value is meant cannot be told")


def test_bag_calib_key_given_twice_is_refused(capsys, tmp_path):
    """``--bag --calib`` reads the rig with the same reader."""
    from crfdepth.data.example_bag import EXAMPLE_TOPICS, write_example_bag

    bag, rig, out = tmp_path / "street.bag", tmp_path / "rig.json", tmp_path / "depth"
    write_example_bag(bag, frames=1)
    rig.write_text('{"K": [1, 0, 0, 0, 1, 0, 0, 0, 1], "K": [1, 0, 0, 0, 1, 0, 0, 0, 1], "T_cam_lidar": 1}')
    first = _first_line(capsys, ["complete", "--bag", bag, "--image-topic", EXAMPLE_TOPICS["image"], "--points-topic",
                                 EXAMPLE_TOPICS["points"], "--calib", rig, "--out-dir", out], out)
    assert first.startswith("crfdepth complete: error: --calib")
    assert first.endswith(f"expected each key once in {rig}, got 'K' twice: which value is meant cannot be told")


def _scan(tmp_path) -> Path:
    path = tmp_path / "scan.bin"
    rng = np.random.default_rng(0)
    np.column_stack([rng.uniform(5, 30, 200), rng.uniform(-5, 5, 200), rng.uniform(-1.5, 1, 200),
                     np.zeros(200)]).astype("<f4").tofile(path)
    return path


def test_project_refuses_a_kitti_key_given_twice(capsys, tmp_path):
    P2 = "721.5377 0 609.5593 44.85728 0 721.5377 172.854 0.2163791 0 0 1 0.002745884"
    calib, image, out = tmp_path / "calib.txt", tmp_path / "image.png", tmp_path / "out.png"
    calib.write_text(f"P0: {P2}\nP1: {P2}\nP2: {P2}\nP3: {P2}\nR0_rect: 1 0 0 0 1 0 0 0 1\n"
                     f"Tr_velo_to_cam: 0 -1 0 0 0 0 -1 0 1 0 0 0\nP2: {P2.replace('721.5377', '700')}\n")
    cv2.imwrite(str(image), np.zeros((375, 1242, 3), np.uint8))
    argv = ["project", "--velodyne", _scan(tmp_path), "--calib", calib, "--image", image, "--out", out]
    first = _first_line(capsys, argv, out)
    assert first == (f"crfdepth project: error: --calib: expected each key once in {calib}, got 'P2' twice (lines 3 "
                     f"and 7): which value is meant cannot be told")
    first = _first_line(capsys, _points(calib, out), out)  # complete --points reads KITTI files alike
    assert first.startswith("crfdepth complete: error: --calib")
    assert first.endswith(f"expected each key once in {calib}, got 'P2' twice (lines 3 and 7): which value is meant "
                          f"cannot be told")


# --------------------------------------------------------------------------- implausible K and distortion


def _rig_with(tmp_path, **entries) -> Path:
    data = {"K": [[379.7567, 0.0, 313.984], [0.0, 379.7567, 204.336], [0.0, 0.0, 1.0]],
            "T_cam_lidar": [[0.0, -1.0, 0.0, 0.06], [0.0, 0.0, -1.0, -0.08], [1.0, 0.0, 0.0, -0.27],
                            [0.0, 0.0, 0.0, 1.0]], "image_size": [480, 640], **entries}
    path = tmp_path / "rig.json"
    path.write_text(json.dumps(data))
    return path


def test_rig_with_a_skewed_k_is_refused(capsys, tmp_path):
    rig, out = _rig_with(tmp_path, K=[[379.7567, 60.0, 313.984], [0.0, 379.7567, 204.336], [0.0, 0.0, 1.0]]), \
        tmp_path / "out.png"
    first = _first_line(capsys, _points(rig, out), out)
    assert first.startswith("crfdepth complete: error: --calib")
    assert f"K ({rig}): expected a skew |K[0][1]| <= 0.1 fx = 37.9757 px" in first


def test_rig_with_distortion_out_of_view_is_refused(capsys, tmp_path):
    rig, out = _rig_with(tmp_path, distortion=[4.0, 0.0, 0.0, 0.0, 0.0]), tmp_path / "out.png"
    first = _first_line(capsys, _points(rig, out), out)
    assert first.startswith("crfdepth complete: error: --calib")
    assert (f"distortion ({rig}): expected distortion coefficients that keep the 640x480 (WxH) image in view (at "
            f"least 50% of its pixels mapped inside the raw image), got 4 0 0 0 0, which map ") in first


def test_rig_with_folding_distortion_is_refused(capsys, tmp_path):
    rig, out = _rig_with(tmp_path, distortion=[-1.5, 0.0, 0.0, 0.0]), tmp_path / "out.png"
    first = _first_line(capsys, _points(rig, out), out)
    assert first.startswith("crfdepth complete: error: --calib")
    assert (f"distortion ({rig}): expected distortion coefficients whose mapping does not fold over the 640x480 "
            f"(WxH) image, got -1.5 0 0 0, which fold it from a normalised radius of ") in first


@pytest.mark.parametrize("K_text, message", [
    ("379.7567 60 313.984 0 379.7567 204.336 0 0 1", "expected a skew |K[0][1]| <= 0.1 fx = 37.9757 px"),
    ("379.7567 0 313.984 3 379.7567 204.336 0 0 1", "expected an upper-triangular K, K[1][0] = 0"),
    ("379.7567 0 0 0 379.7567 0 313.984 204.336 1", "K looks transposed (cx and cy belong in the last column)"),
])
def test_implausible_intrinsics_are_refused(capsys, tmp_path, sparse_png, K_text, message):
    k_path, out = tmp_path / "K.txt", tmp_path / "out.png"
    k_path.write_text(K_text)
    first = _first_line(capsys, _one_frame(sparse_png, k_path, out), out)
    assert first.startswith(f"crfdepth complete: error: --intrinsics {k_path}: expected ")
    assert message in first


def test_the_example_still_completes(capsys, tmp_path, sparse_png):
    """The checks refuse nothing real: the example rig, its K as --intrinsics."""
    k_path, out = tmp_path / "K.txt", tmp_path / "out.png"
    k_path.write_text(K_EXAMPLE)
    assert main([str(a) for a in _one_frame(sparse_png, k_path, out)] + ["--quiet"]) == 0
    assert out.exists()
