"""Tests of crfdepth.io.pointcloud: the readers against hand-written files (bytes written
here with struct / plain text) and against files written by pypcd4 and plyfile directly
(binary_compressed PCD with extra fields, big-endian PLY with faces), exact round trips
of the writers, and the one-line InputError for every empty, malformed, unsupported and
truncated file."""

from __future__ import annotations

import struct

import numpy as np
import pytest
from plyfile import PlyData, PlyElement
from pypcd4 import Encoding, PointCloud

from crfdepth.errors import InputError
from crfdepth.io.kitti import read_velodyne
from crfdepth.io.pointcloud import read_points, write_pcd, write_ply

POINTS = np.array([[1.5, -2.25, 0.125, 0.5], [10.0, 3.0, -1.75, 0.0], [np.pi, np.e, 1e-7, 1.0]], dtype=np.float32)


def test_read_kitti_bin_matches_read_velodyne(kitti_root):
    path = kitti_root / "raw/2011_09_26/2011_09_26_drive_0001_sync/velodyne_points/data/0000000005.bin"
    points = read_points(path)
    assert points.dtype == np.float32 and points.shape[1] == 4 and points.shape[0] > 100_000
    np.testing.assert_array_equal(points, read_velodyne(path))


# Values that a fixed-decimal text format would lose (pypcd4's own ASCII writer uses %.10f).
HARD = np.array([[1.2345678e-6, -3.0e38, 7.006492e-30, 65504.125]], dtype=np.float32)
# Tiled rows: LZF shrinks them, so write_pcd(compressed=True) really writes binary_compressed.
CLOUD = np.vstack([np.tile(POINTS, (50, 1)), HARD])
WRITERS = {"ply binary": (write_ply, ".ply", {}), "ply ascii": (write_ply, ".ply", {"binary": False}),
           "pcd binary": (write_pcd, ".pcd", {}), "pcd ascii": (write_pcd, ".pcd", {"binary": False}),
           "pcd compressed": (write_pcd, ".pcd", {"compressed": True})}
HEADER_LINE = {"ply binary": b"format binary_little_endian 1.0", "ply ascii": b"format ascii 1.0",
               "pcd binary": b"DATA binary\n", "pcd ascii": b"DATA ascii\n",
               "pcd compressed": b"DATA binary_compressed\n"}


@pytest.mark.parametrize("columns", [3, 4])
@pytest.mark.parametrize("kind", list(WRITERS))
def test_round_trip_is_exact(tmp_path, kind, columns):
    writer, suffix, options = WRITERS[kind]
    path = writer(tmp_path / f"cloud{suffix}", CLOUD[:, :columns], **options)
    assert HEADER_LINE[kind] in path.read_bytes()
    back = read_points(path)
    assert type(back) is np.ndarray and back.dtype == np.float32 and back.shape == (len(CLOUD), columns)
    np.testing.assert_array_equal(back, CLOUD[:, :columns])
    assert list(tmp_path.iterdir()) == [path]  # atomic write: no temporary file left


@pytest.mark.parametrize("kind", list(WRITERS))
def test_nan_rows_are_kept_and_empty_clouds_round_trip(tmp_path, kind):
    writer, suffix, options = WRITERS[kind]
    cloud = CLOUD.copy()
    cloud[3, :3] = np.nan
    back = read_points(writer(tmp_path / f"nan{suffix}", cloud, **options))
    assert back.shape == cloud.shape and np.isnan(back[3, :3]).all()
    np.testing.assert_array_equal(back, cloud)  # NaNs compare equal position by position
    empty = read_points(writer(tmp_path / f"empty{suffix}", np.zeros((0, 3)), **options))
    assert empty.shape == (0, 3) and empty.dtype == np.float32


def test_compressed_falls_back_to_binary_when_lzf_cannot_shrink_the_data(tmp_path):
    # pypcd4 writes DATA binary when LZF output would not be smaller (here 9 distinct floats).
    path = write_pcd(tmp_path / "small.pcd", POINTS[:, :3], compressed=True)
    assert b"DATA binary\n" in path.read_bytes()
    np.testing.assert_array_equal(read_points(path), POINTS[:, :3])


def test_compressed_needs_binary(tmp_path):
    with pytest.raises(InputError, match=r"^compressed: .*expected binary=True with compressed=True, got binary=False"):
        write_pcd(tmp_path / "x.pcd", POINTS, binary=False, compressed=True)
    assert list(tmp_path.iterdir()) == []


def test_binary_compressed_pcd_written_by_pypcd4_with_extra_fields(tmp_path):
    n = 300
    ring = (np.arange(n) % 16).astype(np.uint16)
    columns = [np.resize(CLOUD[:, i], n) for i in range(4)]  # the tiled rows again: compressible
    time = np.linspace(0.0, 0.1, n)  # float64
    fields = ("x", "y", "z", "ring", "intensity", "time")
    cloud = PointCloud.from_points([*columns[:3], ring, columns[3], time], fields,
                                   (np.float32, np.float32, np.float32, np.uint16, np.float32, np.float64))
    cloud.save(tmp_path / "lidar.pcd", encoding=Encoding.BINARY_COMPRESSED)
    assert b"DATA binary_compressed\n" in (tmp_path / "lidar.pcd").read_bytes()
    np.testing.assert_array_equal(read_points(tmp_path / "lidar.pcd"), np.stack(columns, axis=1))


@pytest.mark.parametrize("text,byte_order,format_line", [(False, ">", b"binary_big_endian"), (True, "=", b"ascii")])
def test_ply_written_by_plyfile_with_extra_properties_and_faces(tmp_path, text, byte_order, format_line):
    vertex = np.array([(1.0, 7, 2.0, 3.0, 0.25), (-4.0, 9, 5.5, 6.0, 0.75), (0.1, 0, np.nan, 1.0, 1.0)],
                      dtype=[("x", ">f8"), ("red", "u1"), ("y", ">f4"), ("z", ">f4"), ("intensity", ">f4")])
    faces = np.empty(1, dtype=[("vertex_indices", "O")])
    faces["vertex_indices"][0] = np.array([0, 1, 2], dtype=np.int32)
    PlyData([PlyElement.describe(vertex, "vertex"), PlyElement.describe(faces, "face")], text=text,
            byte_order=byte_order).write(str(tmp_path / "mesh.ply"))
    assert format_line in (tmp_path / "mesh.ply").read_bytes()[:40]
    expected = np.array([[1, 2, 3, 0.25], [-4, 5.5, 6, 0.75], [np.float32(0.1), np.nan, 1, 1]], dtype=np.float32)
    np.testing.assert_array_equal(read_points(tmp_path / "mesh.ply"), expected)


def test_integer_and_float64_coordinates_become_float32(tmp_path):
    # TYPE I/U fields, and intensity with COUNT 2 (its first value is taken).
    (tmp_path / "i.pcd").write_text("VERSION 0.7\nFIELDS x y z intensity\nSIZE 4 2 1 4\nTYPE I U I F\n"
                                    "COUNT 1 1 1 2\nWIDTH 2\nHEIGHT 1\nPOINTS 2\nDATA ascii\n"
                                    "-7 65535 -128 0.5 9\n16777216 0 127 1 2\n")
    np.testing.assert_array_equal(read_points(tmp_path / "i.pcd"), [[-7, 65535, -128, 0.5], [2**24, 0, 127, 1]])
    (tmp_path / "i.ply").write_text("ply\nformat ascii 1.0\nelement vertex 1\nproperty int x\nproperty short y\n"
                                    "property uchar z\nend_header\n-5 300 255\n")
    np.testing.assert_array_equal(read_points(tmp_path / "i.ply"), [[-5, 300, 255]])
    xyz = np.array([[0.1, 1e-9, 123456.789]], dtype=np.float64)
    PointCloud.from_points(xyz, ("x", "y", "z"), (np.float64,) * 3).save(tmp_path / "d.pcd", encoding=Encoding.BINARY)
    back = read_points(tmp_path / "d.pcd")
    assert back.dtype == np.float32
    np.testing.assert_array_equal(back, xyz.astype(np.float32))

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


PCD_HEADER = ("VERSION 0.7\nFIELDS x y z intensity\nSIZE 4 4 4 4\nTYPE F F F F\nCOUNT 1 1 1 1\nWIDTH 3\nHEIGHT 1\n"
              "VIEWPOINT 0 0 0 1 0 0 0\nPOINTS 3\nDATA ascii\n")
PCD_ROWS = "1 2 3 0.5\n4 5 6 0.25\n7 8 9 1\n"
PLY_HEADER = "ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\nproperty float y\nproperty float z\n"


def _edit(writer, change, **options):
    """A maker: write POINTS (or CLOUD for compressed PCD) with ``writer``, then ``change`` its bytes."""
    def make(path):
        writer(path, CLOUD if options.get("compressed") else POINTS, **options)
        path.write_bytes(change(path.read_bytes()))
    return make


def _text(content):
    return lambda path: path.write_bytes(content.encode("latin-1") if isinstance(content, str) else content)


def _pcd(old, new, rows=PCD_ROWS):
    return _text(PCD_HEADER.replace(old, new) + rows)


BAD = {  # case: (file name, maker, substrings the message must hold)
    "unsupported": ("c.las", _text("x"), ["unsupported point-cloud format", "'.las'", ".ply"]),
    "npy columns": ("c.npy", lambda path: np.save(path, np.zeros((5, 2))), ["(N, 3) or (N, 4)", "(5, 2)"]),
    "bin truncated": ("c.bin", _text(b"\0" * 18), ["not a whole number of points", "18 bytes"]),
    # PLY
    "ply empty": ("c.ply", _text(""), ["is empty (0 bytes)", "expected a PLY file"]),
    "not ply": ("c.ply", _text("hello\n"), ["is not a PLY file", "first line 'ply'"]),
    "ply truncated": ("c.ply", _edit(write_ply, lambda b: b[:-5]), ["header announces 3 vertices", "holds 2",
                                                                      "truncated"]),
    "ply ascii truncated": ("c.ply", _edit(write_ply, lambda b: b.rsplit(b"\n", 2)[0] + b"\n", binary=False),
                            ["header announces 3 vertices", "holds 2", "truncated"]),
    "ply face truncated": ("c.ply", _text(PLY_HEADER + "element face 1\nproperty list uchar int vertex_indices\n"
                                          "end_header\n1 2 3\n"), ["header announces 1 'face' elements", "holds 0"]),
    "ply no z": ("c.ply", _text("ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\nproperty float y\n"
                                "property uchar red\nend_header\n1 2 3\n"), ["no z field", "found x y red"]),
    "ply no vertex": ("c.ply", _text(PLY_HEADER.replace("vertex", "point") + "end_header\n1 2 3\n"),
                      ["no 'vertex' element", "found elements: point"]),
    "ply list": ("c.ply", _text(PLY_HEADER + "property list uchar float normal\nend_header\n1 2 3 2 0 1\n"),
                 ["list property normal in the vertex element", "expected scalar"]),
    "ply type": ("c.ply", _text(PLY_HEADER.replace("float z", "float128 z") + "end_header\n1 2 3\n"),
                 ["malformed or unsupported header", "field type 'float128'"]),
    "ply format": ("c.ply", _text(PLY_HEADER.replace("ascii", "binary_middle_endian") + "end_header\n"),
                   ["malformed or unsupported header", "don't understand format 'binary_middle_endian'"]),
    "ply no end_header": ("c.ply", _text(PLY_HEADER), ["malformed or unsupported header", "early end-of-file"]),
    "ply non-ascii": ("c.ply", _text(PLY_HEADER.replace("float z", "float \xe9") + "end_header\n1 2 3\n"),
                      ["malformed header", "UnicodeDecodeError"]),
    "ply two vertex": ("c.ply", _text(PLY_HEADER + "element vertex 1\nproperty float w\nend_header\n1 2 3\n4\n"),
                       ["malformed header", "two elements with same name"]),
    "ply bad number": ("c.ply", _text(PLY_HEADER + "end_header\n1 two 3\n"),
                       ["data do not match the header", "property 'y': malformed input"]),
    # PCD
    "pcd empty": ("c.pcd", _text(""), ["is empty (0 bytes)", "expected a PCD file"]),
    "not pcd": ("c.pcd", _text("hello\n"), ["is not a PCD file", "ending with DATA", "'hello'"]),
    "pcd binary junk": ("c.pcd", _text(bytes(range(128, 256)) * 4), ["is not a PCD file", "binary bytes"]),
    "pcd no DATA": ("c.pcd", _pcd("DATA ascii\n", ""), ["ending with DATA", "VERSION 0.7 | FIELDS x y z"]),
    "pcd no z": ("c.pcd", _pcd("x y z intensity", "x y q intensity"), ["no z field", "found x y q intensity"]),
    "pcd no xyz": ("c.pcd", _pcd("x y z intensity", "a b c d"), ["no x, y, z field(s)", "found a b c d"]),
    "pcd type": ("c.pcd", _pcd("TYPE F F F F", "TYPE F F F X"), ["malformed or unsupported header", "TYPE.3",
                                                                "got 'X'"]),
    "pcd size": ("c.pcd", _pcd("SIZE 4 4 4 4", "SIZE 4 4 4 2"), ["unsupported field type F of size 2",
                                                                "'intensity'"]),
    "pcd no COUNT": ("c.pcd", _pcd("COUNT 1 1 1 1\n", ""), ["malformed or unsupported header",
                                                             "COUNT: Field required"]),
    "pcd POINTS text": ("c.pcd", _pcd("POINTS 3", "POINTS three"), ["malformed or unsupported header",
                                                                     "invalid literal for int()"]),
    "pcd DATA": ("c.pcd", _pcd("DATA ascii", "DATA lzma"), ["DATA: Input should be 'ascii', 'binary'", "'lzma'"]),
    "pcd fields": ("c.pcd", _pcd("FIELDS x y z intensity", "FIELDS x y z"), ["FIELDS, SIZE, TYPE and COUNT",
                                                                              "found 3/4/4/4 entries"]),
    "pcd ascii truncated": ("c.pcd", _pcd("", "", PCD_ROWS[:-8]), ["header announces 3 points", "holds 2",
                                                                    "DATA ascii, truncated"]),
    "pcd ascii columns": ("c.pcd", _pcd("", "", PCD_ROWS.replace(" 0.25", "")), ["header announces 3 points",
                                                                               "requires 4 columns but 3"]),
    "pcd ascii number": ("c.pcd", _pcd("", "", PCD_ROWS.replace("4 5 6", "4 five 6")),
                         ["could not convert string 'five'"]),
    # pypcd4 reads ascii rows with delimiter " ": a trailing space is one more (empty) column.
    "pcd ascii trailing space": ("c.pcd", _pcd("", "", PCD_ROWS.replace("\n", " \n")),
                                 ["header announces 3 points (DATA ascii)", "requires 4 columns but 5"]),
    # pypcd4 stops after 10 header lines; without this check it would read the rest as binary_compressed.
    "pcd long header": ("c.pcd", _pcd("POINTS 3\n", "POINTS 3\nORIGIN 0 0 0\n"),
                        ["expected at most 10 header lines", "ending with DATA"]),
    "pcd truncated": ("c.pcd", _edit(write_pcd, lambda b: b[:-1]), ["header announces 3 points (DATA binary)",
                                                                     "multiple of element size", "truncated"]),
    "pcd truncated point": ("c.pcd", _edit(write_pcd, lambda b: b[:-16]), ["header announces 3 points, the file "
                                                                           "holds 2 (DATA binary, truncated)"]),
    "pcd POINTS more": ("c.pcd", _edit(write_pcd, lambda b: b.replace(b"POINTS 3", b"POINTS 4")),
                        ["header announces 4 points, the file holds 3"]),
    "pcd compressed truncated": ("c.pcd", _edit(write_pcd, lambda b: b[:-5], compressed=True),
                                 ["header announces 151 points (DATA binary_compressed)",
                                  "RuntimeError: Failed to decompress data", "truncated, damaged"]),
    "pcd compressed no sizes": ("c.pcd", _edit(write_pcd, lambda b: b[: b.index(b"DATA") + 27], compressed=True),
                                ["(DATA binary_compressed)", "error: unpack requires a buffer of 8 bytes"]),
    "pcd compressed mislabelled": ("c.pcd", _edit(write_pcd, lambda b: b.replace(b"DATA binary", b"DATA "
                                                                                 b"binary_compressed")),
                                   ["header announces 3 points (DATA binary_compressed)", "error in compressed data"]),
}


@pytest.mark.parametrize("case", list(BAD))
def test_bad_files(tmp_path, case):
    name, make, expected = BAD[case]
    path = tmp_path / name
    make(path)
    with pytest.raises(InputError) as info:
        read_points(path)
    message = str(info.value)
    assert message.startswith("points: ") and str(path) in message and "\n" not in message, message
    for text in expected:
        assert text in message, (text, message)
    assert info.value.__cause__ is None and (info.value.__context__ is None or info.value.__suppress_context__)

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
