"""A KITTI ``.bin`` scan is read as what it is (crfdepth.io.kitti.read_velodyne, the one reader of
``.bin`` scans): N x 4 float32 in metres, or refused naming what was expected and what was found.
``crfdepth project --velodyne`` and ``crfdepth complete --points`` refuse with the same message,
each naming its flag; the real and synthetic scans still read."""

from __future__ import annotations

import numpy as np
import pytest

from crfdepth.cli import main
from crfdepth.data.synthetic import make_scene
from crfdepth.errors import InputError
from crfdepth.io.kitti import read_velodyne
from crfdepth.io.pointcloud import read_points

DRIVE = "raw/2011_09_26/2011_09_26_drive_0001_sync"


@pytest.fixture(scope="module")
def scan() -> np.ndarray:
    """A synthetic 64-beam scan in the sensor's order, (N, 4) float32, N a multiple of 12, metres."""
    points = make_scene(seed=0).points.astype(np.float32)
    return np.ascontiguousarray(points[: len(points) - len(points) % 12])


def _scaled(points: np.ndarray, factor: float) -> np.ndarray:
    out = points.copy()
    out[:, :3] *= factor
    return out


def _with(points: np.ndarray, row: int, column: int, value: float) -> np.ndarray:
    out = points.copy()
    out[row, column] = value
    return out


def _shuffled(points: np.ndarray) -> np.ndarray:
    return points[np.random.default_rng(0).permutation(len(points))]


# case: (bytes of the file from the scan, the start of the message after "<name>: ", substrings it holds)
CASES = {
    "empty": (lambda p: b"", "expected a KITTI Velodyne scan (N x 4 float32: x, y, z, reflectance; 16 bytes per "
                             "point), got an empty file (0 bytes): ", []),
    "truncated": (lambda p: p.tobytes()[:-4], "expected a file size that is a multiple of 16 bytes (N x 4 float32: "
                                              "x, y, z, reflectance), got ", ["not a whole number of points"]),
    "float64 N x 4": (lambda p: p.astype("<f8").tobytes(), "expected a KITTI Velodyne scan",
                      ["looks like float64 (", " x 4 float64, 32 bytes per point)", "read as float64 its points have "
                       "a median range of 8.59 m", "points.astype(numpy.float32).tofile(path)"]),
    "float64 N x 4 not from float32": (lambda p: (p.astype("<f8") + 1e-9).tobytes(), "expected a KITTI Velodyne scan",
                                       ["looks like float64 (", "NaN or infinite"]),
    "float64 N x 3": (lambda p: p[:, :3].astype("<f8").tobytes(), "expected a KITTI Velodyne scan",
                      ["looks like float64 (", " x 3 float64, 24 bytes per point)", "with a reflectance column"]),
    "float64 N x 3, odd N": (lambda p: p[:-1, :3].astype("<f8").tobytes(), "expected a file size that is a multiple of "
                             "16 bytes", ["not a whole number of points", "it looks like float64 (",
                                          " x 3 float64, 24 bytes per point)"]),
    "N x 3 float32": (lambda p: np.ascontiguousarray(p[:, :3]).tobytes(), "expected a KITTI Velodyne scan",
                      ["looks like N x 3 float32 (x, y, z without reflectance, 12 bytes per point)",
                       "consecutive points lie", "a scan's order", "add a reflectance column"]),
    "N x 3 float32 shuffled": (lambda p: np.ascontiguousarray(_shuffled(p)[:, :3]).tobytes(),
                               "expected a KITTI Velodyne scan",
                               ["looks like N x 3 float32", "of the reflectance values (4th column) negative"]),
    "N x 3 float32, N not a multiple of 4": (lambda p: np.ascontiguousarray(p[:-3, :3]).tobytes(),
                                             "expected a file size that is a multiple of 16 bytes",
                                             ["it looks like N x 3 float32", "add a reflectance column"]),
    "millimetres": (lambda p: _scaled(p, 1000).tobytes(), "expected coordinates in metres (a median range from the "
                    "sensor of 0.1 to 300 m), got a median range of 8", ["looks like millimetres: divide the "
                                                                         "coordinates by 1000"]),
    "centimetres": (lambda p: _scaled(p, 100).tobytes(), "expected coordinates in metres",
                    ["got a median range of 8", "looks like centimetres: divide the coordinates by 100"]),
    "kilometres": (lambda p: _scaled(p, 1e-3).tobytes(), "expected coordinates in metres",
                   ["got a median range of 0.008", "looks like kilometres: multiply the coordinates by 1000"]),
    "NaN": (lambda p: _with(p, 7, 1, np.nan).tobytes(), "expected finite values, got 1 NaN or infinite value(s) "
                                                        "among ", []),
    "infinite reflectance": (lambda p: _with(p, 7, 3, np.inf).tobytes(), "expected finite values, got 1 NaN", []),
    "huge": (lambda p: _with(p, 7, 0, 3e9).tobytes(), "expected coordinates within +-1e+07 (metres), got values "
                                                      "up to 3e+09", []),
    "zeros": (lambda p: np.zeros((100, 4), np.float32).tobytes(), "expected coordinates in metres",
              ["a median range of 0 (every point at the sensor)"]),
}


@pytest.mark.parametrize("case", list(CASES))
@pytest.mark.parametrize("reader, name", [(read_velodyne, "velodyne"), (read_points, "points")])
def test_bad_scan_is_refused_with_what_was_expected_and_found(tmp_path, scan, case, reader, name):
    make, start, parts = CASES[case]
    path = tmp_path / "scan.bin"
    path.write_bytes(make(scan))
    with pytest.raises(InputError) as info:
        reader(path)
    message = str(info.value)
    assert message.startswith(f"{name}: {start}"), message
    assert str(path) in message and "\n" not in message, message
    for part in parts:
        assert part in message, (part, message)


def test_the_size_is_named_in_bytes(tmp_path):
    path = tmp_path / "scan.bin"
    path.write_bytes(b"\0" * 20)
    with pytest.raises(InputError, match=r"^velodyne: expected a file size that is a multiple of 16 bytes .*, got 20 "
                                         r"bytes in .*scan\.bin: not a whole number of points"):
        read_velodyne(path)


def test_a_signed_fourth_column_in_scan_order_is_read(tmp_path, scan):
    """A fourth field that may be negative (a time offset) is no evidence of N x 3 when the N x 4 reading keeps
    the scan's order: read as it is."""
    points = scan.copy()
    points[:, 3] = np.linspace(-0.05, 0.05, len(points))
    points.tofile(tmp_path / "scan.bin")
    np.testing.assert_array_equal(read_velodyne(tmp_path / "scan.bin"), points)


def test_synthetic_scan_reads_back_exactly(tmp_path, scan):
    scan.tofile(tmp_path / "scan.bin")
    np.testing.assert_array_equal(read_velodyne(tmp_path / "scan.bin"), scan)
    np.testing.assert_array_equal(read_points(tmp_path / "scan.bin"), scan)


@pytest.mark.kitti
def test_every_real_scan_reads(kitti_root):
    scans = sorted(kitti_root.rglob("*.bin"))
    assert len(scans) >= 100
    for path in scans:
        points = read_velodyne(path)
        assert points.shape[1] == 4 and points.dtype == np.float32 and len(points) > 60_000, path
        assert points.size * 4 == path.stat().st_size


# --------------------------------------------------------------------------- the two commands


def _project(kitti_root, scan, out):
    return ["project", "--velodyne", str(scan), "--calib", str(kitti_root / "raw/2011_09_26"),
            "--image", str(kitti_root / DRIVE / "image_02/data/0000000005.png"), "--out", str(out)]


def _complete(kitti_root, scan, out):
    return ["complete", "--image", str(kitti_root / DRIVE / "image_02/data/0000000005.png"), "--points", str(scan),
            "--calib", str(kitti_root / "raw/2011_09_26"), "--out", str(out)]


@pytest.mark.kitti
@pytest.mark.parametrize("case", ["empty", "truncated", "float64 N x 4", "N x 3 float32", "millimetres", "NaN"])
def test_project_and_complete_refuse_a_bad_scan_alike(kitti_root, tmp_path, capsys, scan, case):
    """Both commands read a .bin through read_velodyne: exit status 2, the same one line after the flag,
    nothing written."""
    make, start, _ = CASES[case]
    path = tmp_path / "scan.bin"
    path.write_bytes(make(scan))
    out = tmp_path / "out.png"
    lines = {}
    for command, argv, flag in (("project", _project(kitti_root, path, out), "--velodyne"),
                                ("complete", _complete(kitti_root, path, out), "--points")):
        assert main(argv) == 2
        first = capsys.readouterr().err.splitlines()[0]
        prefix = f"crfdepth {command}: error: {flag}: "
        assert first.startswith(prefix + start), first
        lines[command] = first.removeprefix(prefix)
        assert not out.exists()
    assert lines["project"] == lines["complete"]
    assert "points:" not in lines["complete"]  # one name, the flag's
