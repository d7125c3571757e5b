"""Tests of crfdepth.io.pointcloud: the readers against hand-written files (independent
oracle: bytes written here with struct / plain text), round trips of the writers, and
the errors for unsupported, malformed and truncated files."""

from __future__ import annotations

import struct

import numpy as np
import pytest

from crfdepth.errors import InputError
from crfdepth.io.kitti import read_velodyne
from crfdepth.io.pointcloud import read_points, write_pcd, write_ply

POINTS = np.array([[1.5, -2.25, 0.125, 0.5], [10.0, 3.0, -1.75, 0.0], [np.pi, np.e, 1e-7, 1.0]], dtype=np.float32)


def test_read_kitti_bin_matches_read_velodyne(kitti_root):
    path = kitti_root / "raw/2011_09_26/2011_09_26_drive_0001_sync/velodyne_points/data/0000000005.bin"
    points = read_points(path)
    assert points.dtype == np.float32 and points.shape[1] == 4 and points.shape[0] > 100_000
    np.testing.assert_array_equal(points, read_velodyne(path))


@pytest.mark.parametrize("columns", [3, 4])
@pytest.mark.parametrize("binary", [True, False])
@pytest.mark.parametrize("writer,suffix", [(write_ply, ".ply"), (write_pcd, ".pcd")])
def test_round_trip_is_exact(tmp_path, writer, suffix, binary, columns):
    path = writer(tmp_path / f"cloud{suffix}", POINTS[:, :columns], binary=binary)
    back = read_points(path)
    assert back.dtype == np.float32 and back.shape == (3, columns)
    np.testing.assert_array_equal(back, POINTS[:, :columns])


@pytest.mark.parametrize("columns", [3, 4])
def test_npy(tmp_path, columns):
    np.save(tmp_path / "c.npy", POINTS[:, :columns].astype(np.float64))
    np.testing.assert_array_equal(read_points(tmp_path / "c.npy"), POINTS[:, :columns])


def test_binary_ply_written_by_hand_with_extra_properties_and_faces(tmp_path):
    # double x y z, a uchar property in between, intensity last, then a face element.
    header = ("ply\nformat binary_little_endian 1.0\ncomment by hand\nelement vertex 2\nproperty double x\n"
              "property uchar red\nproperty double y\nproperty double z\nproperty float intensity\n"
              "element face 1\nproperty list uchar int vertex_indices\nend_header\n").encode()
    body = struct.pack("<dBddf", 1.0, 7, 2.0, 3.0, 0.25) + struct.pack("<dBddf", -4.0, 9, 5.5, 6.0, 0.75)
    body += struct.pack("<Biii", 3, 0, 1, 0)
    (tmp_path / "h.ply").write_bytes(header + body)
    np.testing.assert_array_equal(read_points(tmp_path / "h.ply"), [[1, 2, 3, 0.25], [-4, 5.5, 6, 0.75]])


def test_ascii_ply_and_pcd_by_hand(tmp_path):
    (tmp_path / "a.ply").write_text("ply\nformat ascii 1.0\nelement vertex 2\nproperty float x\nproperty float y\n"
                                    "property float z\nend_header\n1 2 3\n4 5 6\n")
    np.testing.assert_array_equal(read_points(tmp_path / "a.ply"), [[1, 2, 3], [4, 5, 6]])
    (tmp_path / "a.pcd").write_text("# .PCD v0.7\nVERSION 0.7\nFIELDS x y z rgb intensity\nSIZE 4 4 4 4 4\n"
                                    "TYPE F F F U F\nCOUNT 1 1 1 1 1\nWIDTH 2\nHEIGHT 1\nPOINTS 2\nDATA ascii\n"
                                    "1 2 3 255 0.5\n-1 -2 -3 0 1\n")
    np.testing.assert_array_equal(read_points(tmp_path / "a.pcd"), [[1, 2, 3, 0.5], [-1, -2, -3, 1]])


def test_binary_pcd_by_hand_with_nan_kept(tmp_path):
    header = b"VERSION .7\nFIELDS intensity x y z\nSIZE 2 4 4 4\nTYPE U F F F\nCOUNT 1 1 1 1\nWIDTH 2\n" \
             b"HEIGHT 1\nPOINTS 2\nDATA binary\n"
    body = struct.pack("<Hfff", 7, 1.0, 2.0, 3.0) + struct.pack("<Hfff", 9, np.nan, np.nan, np.nan)
    (tmp_path / "b.pcd").write_bytes(header + body)
    points = read_points(tmp_path / "b.pcd")
    np.testing.assert_array_equal(points[0], [1, 2, 3, 7])
    assert np.isnan(points[1, :3]).all()  # the reader keeps NaN rows; complete_depth drops them


@pytest.mark.parametrize("case,expected", [
    ("unsupported", ["unsupported point-cloud format", ".las", ".ply"]),
    ("npy columns", ["(N, 3) or (N, 4)", "(5, 2)"]),
    ("bin truncated", ["not a whole number of points", "18 bytes"]),
    ("ply truncated", ["header announces 3 vertices", "truncated"]),
    ("ply ascii truncated", ["header announces 3 vertices", "holds 2"]),
    ("pcd truncated", ["header announces 3 points", "truncated"]),
    ("pcd compressed", ["binary_compressed", "ascii or binary"]),
    ("ply no z", ["no z field"]),
    ("ply big endian", ["binary_big_endian", "binary_little_endian"]),
    ("not ply", ["not a PLY file"]),
])
def test_bad_files(tmp_path, case, expected):
    path = {"unsupported": "c.las", "npy columns": "c.npy", "bin truncated": "c.bin"}.get(
        case, "c.pcd" if "pcd" in case else "c.ply")
    path = tmp_path / path
    if case == "unsupported":
        path.write_bytes(b"x")
    elif case == "npy columns":
        np.save(path, np.zeros((5, 2)))
    elif case == "bin truncated":
        path.write_bytes(b"\0" * 18)
    elif case == "ply truncated":
        write_ply(path, POINTS)
        path.write_bytes(path.read_bytes()[:-5])
    elif case == "ply ascii truncated":
        write_ply(path, POINTS, binary=False)
        path.write_bytes(path.read_bytes().rsplit(b"\n", 2)[0] + b"\n")
    elif case == "pcd truncated":
        write_pcd(path, POINTS)
        path.write_bytes(path.read_bytes()[:-1])
    elif case == "pcd compressed":
        write_pcd(path, POINTS)
        path.write_bytes(path.read_bytes().replace(b"DATA binary", b"DATA binary_compressed"))
    elif case == "ply no z":
        path.write_text("ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\nproperty float y\n"
                        "end_header\n1 2\n")
    elif case == "ply big endian":
        write_ply(path, POINTS)
        path.write_bytes(path.read_bytes().replace(b"binary_little_endian", b"binary_big_endian"))
    elif case == "not ply":
        path.write_text("hello\n")
    with pytest.raises(InputError) as info:
        read_points(path)
    for text in expected:
        assert text in str(info.value)
    assert str(path) in str(info.value) or case in ("npy columns",) or path.name in str(info.value)


def test_missing_file(tmp_path):
    with pytest.raises(FileNotFoundError, match="nope.pcd"):
        read_points(tmp_path / "nope.pcd")


def test_writer_checks_shape_and_leaves_input(tmp_path):
    with pytest.raises(InputError, match=r"\(N, 3\) or \(N, 4\).*\(3, 2\)"):
        write_ply(tmp_path / "x.ply", np.zeros((3, 2)))
    points = POINTS.astype(np.float64)
    before = points.copy()
    write_pcd(tmp_path / "x.pcd", points)
    np.testing.assert_array_equal(points, before)


def test_text_file_named_npy_is_named_and_never_suggests_pickle(tmp_path):
    path = tmp_path / "cloud.npy"
    path.write_text("1.0 2.0 3.0\n4.0 5.0 6.0\n")
    with pytest.raises(InputError) as info:
        read_points(path)
    message = str(info.value)
    assert message == (f"points: {path} is not a NumPy .npy file: expected one written by numpy.save (it starts "
                       f"with the bytes \\x93NUMPY), got a file starting with '1.0 2.0 3.0' (a text table? read it "
                       f"with numpy.loadtxt and save the (N, 3) or (N, 4) array with numpy.save)")
    assert "pickle" not in message and "\n" not in message


def test_object_array_npy_is_refused_without_suggesting_pickle(tmp_path):
    path = tmp_path / "objects.npy"
    np.save(path, np.array([[1.0, 2.0, 3.0], [4.0, 5.0, "x"]], dtype=object))
    with pytest.raises(InputError) as info:
        read_points(path)
    message = str(info.value)
    assert message.startswith(f"points: .npy {path}: expected an array of numbers (N, 3) or (N, 4), got an array "
                              f"of Python objects")
    assert "allow_pickle" not in message


def test_truncated_npy_is_named(tmp_path):
    path = tmp_path / "cut.npy"
    np.save(path, POINTS)
    path.write_bytes(path.read_bytes()[:-7])
    with pytest.raises(InputError, match=r"points: \.npy .*cut\.npy: expected a complete NumPy array file, got one "
                                         r"that cannot be read .*truncated or damaged"):
        read_points(path)


def test_writers_check_the_output_path(tmp_path):
    with pytest.raises(FileNotFoundError, match=r"^path: the folder of .*missing/x\.ply does not exist"):
        write_ply(tmp_path / "missing" / "x.ply", POINTS)
    assert list(tmp_path.iterdir()) == []
