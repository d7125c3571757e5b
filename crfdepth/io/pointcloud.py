"""Point-cloud files: KITTI ``.bin``, NumPy ``.npy``, PLY and PCD (docs/design.md section 1).

:func:`read_points` returns an ``(N, 3)`` or ``(N, 4)`` float32 array (x, y, z in the
sensor frame, metres, plus intensity when the file has it) from:

- ``.bin``: KITTI Velodyne scan, raw little-endian float32, 4 values per point, read and
  checked by :func:`crfdepth.io.kitti.read_velodyne` (empty files, sizes not a multiple of 16
  bytes, non-finite values, coordinates not in metres, float64 and N x 3 float32 files are
  refused, the last two named);
- ``.npy``: a 2-D array with 3 or 4 columns (further columns are an error: say which
  three are x y z by slicing before saving);
- ``.ply``, read by `plyfile <https://github.com/dranjan/python-plyfile>`_: ``ascii``,
  ``binary_little_endian`` or ``binary_big_endian``, an ``element vertex`` with scalar
  properties ``x y z`` and optionally ``intensity`` (other vertex properties and other
  elements, e.g. faces, are read by plyfile and ignored here);
- ``.pcd``, read by `pypcd4 <https://github.com/MapIV/pypcd4>`_: ``DATA ascii``, ``binary``
  or ``binary_compressed`` (LZF), fields ``x y z`` and optionally ``intensity`` (other
  fields are ignored; a field with COUNT > 1 contributes its first value). pypcd4 needs
  the COUNT and POINTS lines, at most 10 header lines besides comments, and ascii rows
  separated by single spaces (PCL's own output is all three).

x, y, z (and intensity) of any numeric type are converted to float32 (integers exactly
up to 2**24, float64 rounded to nearest). :func:`write_ply` (plyfile) and
:func:`write_pcd` (pypcd4) write files that :func:`read_points` reads back exactly.
The ``.bin`` and ``.npy`` readers stay hand-written: both formats are a bare array that
``numpy.fromfile`` / ``numpy.load`` read directly; no library reads them better.

Both libraries raise their own exceptions (pydantic, LZF, struct and NumPy errors from
pypcd4; ``PlyParseError`` from plyfile) and pypcd4 returns fewer points than announced
for a binary file cut at a point boundary, so every call is wrapped: missing files
raise ``FileNotFoundError``; unsupported formats, malformed headers, missing x/y/z,
wrong column counts and truncated files raise :class:`crfdepth.errors.InputError`, one
line starting ``points:`` that names the file, what was expected and what was found.
"""

from __future__ import annotations

import os
import struct
from pathlib import Path
from typing import Callable

import numpy as np
from plyfile import PlyData, PlyElement, PlyElementParseError, PlyHeaderParseError, PlyListProperty
from pypcd4 import Encoding, MetaData, PointCloud

from crfdepth.errors import InputError
from crfdepth.io.files import atomic_write, check_input_file, check_output_file
from crfdepth.io.kitti import read_velodyne

__all__ = ["POINT_FORMATS", "read_points", "write_pcd", "write_ply"]

PathLike = str | os.PathLike
POINT_FORMATS = (".bin", ".npy", ".ply", ".pcd")
_NPY_MAGIC = b"\x93NUMPY"
_NAMES = ("x", "y", "z", "intensity")
# pypcd4 reads at most this many non-comment header lines looking for DATA.
_PCD_HEADER_LINES = 10
# What pypcd4 raises on data that does not match its header: NumPy (frombuffer, loadtxt,
# broadcasting) and LZF ValueErrors, struct.error (short size prefix), TypeError (LZF
# output that does not fit) and RuntimeError (wrong decompressed size).
_PCD_DATA_ERRORS = (ValueError, TypeError, RuntimeError, struct.error)


def _columns(fields: dict[str, np.ndarray], path: Path, what: str) -> np.ndarray:
    """Stack x, y, z (+ intensity) into float32 (N, 3|4); InputError when x y z are missing."""
    missing = [name for name in _NAMES[:3] if name not in fields]
    if missing:
        raise InputError(f"points: {what} {path} has no {', '.join(missing)} field(s); expected x y z "
                         f"[intensity], found {' '.join(fields) or 'none'}")
    names = _NAMES if "intensity" in fields else _NAMES[:3]
    return np.stack([np.asarray(fields[n], dtype=np.float32) for n in names], axis=1)


def _reason(exc: BaseException, *, name: bool = True) -> str:
    """A library exception as one short line: its class (``struct.error``, ``ValueError``) and the
    first clause of its message, at most 120 characters."""
    text = (str(exc).strip().splitlines() or [""])[0].split("; ")[0]
    text = text if len(text) <= 120 else text[:117] + "..."
    cls = type(exc)
    qualified = cls.__name__ if cls.__module__ == "builtins" else f"{cls.__module__}.{cls.__name__}"
    return f"{qualified}: {text}" if name and text else (text or qualified)


def _check_not_empty(path: Path, what: str) -> None:
    if path.stat().st_size == 0:
        raise InputError(f"points: {path} is empty (0 bytes); expected a {what} file")


# --------------------------------------------------------------------------- reading


def read_points(path: PathLike) -> np.ndarray:
    """Read a point cloud file, chosen by its extension (see the module docstring).

    Args:
        path: a ``.bin``, ``.npy``, ``.ply`` or ``.pcd`` file.

    Returns:
        (N, 3) or (N, 4) float32 points: x, y, z in the file's frame (metres for LiDAR
        data), then intensity when the file has one (a KITTI ``.bin`` always has 4
        columns). Rows are in file order; NaN rows of ``.npy``, PLY and PCD files are kept
        (the caller decides; :func:`crfdepth.api.complete_depth` drops them with a warning).

    Raises:
        FileNotFoundError: ``path`` does not exist.
        InputError: unsupported extension, empty file, malformed or unsupported header,
            missing x/y/z fields, list or unsupported field types, wrong column count,
            truncated data, or a ``.bin`` that is not a float32 scan in metres
            (:func:`crfdepth.io.kitti.read_velodyne`).
    """
    path = check_input_file(path, "points")
    suffix = path.suffix.lower()
    if suffix == ".bin":
        return _read_bin(path)
    if suffix == ".npy":
        return _read_npy(path)
    if suffix == ".ply":
        return _read_ply(path)
    if suffix == ".pcd":
        return _read_pcd(path)
    raise InputError(f"points: unsupported point-cloud format {suffix or '(no extension)'!r} for {path}; "
                     f"expected one of {', '.join(POINT_FORMATS)}")


def _read_bin(path: Path) -> np.ndarray:
    """A KITTI scan through the one reader of ``.bin`` scans, :func:`crfdepth.io.kitti.read_velodyne`, with its
    checks (size, finite values in metres, float64 or N x 3 float32 files named), its errors naming ``points``."""
    return read_velodyne(path, "points")


def _read_npy(path: Path) -> np.ndarray:
    with open(path, "rb") as handle:
        start = handle.read(len(_NPY_MAGIC) + 24)
    if not start.startswith(_NPY_MAGIC):
        text = start.decode("ascii", errors="replace").split("\n")[0][:24]
        raise InputError(f"points: {path} is not a NumPy .npy file: expected one written by numpy.save (it starts "
                         f"with the bytes \\x93NUMPY), got a file starting with {text!r} (a text table? read it "
                         f"with numpy.loadtxt and save the (N, 3) or (N, 4) array with numpy.save)")
    try:
        array = np.load(path, allow_pickle=False)
    except (ValueError, OSError, EOFError) as exc:
        if "pickle" in str(exc):  # an object array: never load pickles from a point-cloud file
            raise InputError(f"points: .npy {path}: expected an array of numbers (N, 3) or (N, 4), got an array of "
                             f"Python objects; save the points as numbers, e.g. numpy.save(path, "
                             f"numpy.asarray(points, dtype=numpy.float32))") from None
        raise InputError(f"points: .npy {path}: expected a complete NumPy array file, got one that cannot be "
                         f"read ({str(exc).splitlines()[0] if str(exc) else type(exc).__name__}): truncated or "
                         f"damaged") from None
    if array.ndim != 2 or array.shape[1] not in (3, 4):
        raise InputError(f"points: .npy {path}: expected an (N, 3) or (N, 4) array (x y z [intensity]), "
                         f"got shape {array.shape}")
    if not np.issubdtype(array.dtype, np.number) or np.issubdtype(array.dtype, np.complexfloating):
        raise InputError(f"points: .npy {path}: expected real numbers, got dtype {array.dtype}")
    return array.astype(np.float32)


def _read_ply(path: Path) -> np.ndarray:
    """PLY through ``plyfile.PlyData.read`` (memory-mapped binary, copied out here)."""
    _check_not_empty(path, "PLY")
    try:
        ply = PlyData.read(str(path))
    except PlyHeaderParseError as exc:
        if exc.line == 1:
            raise InputError(f"points: {path} is not a PLY file: expected a first line 'ply', "
                             f"got another one (plyfile: {_reason(exc, name=False)})") from None
        raise InputError(f"points: PLY {path}: malformed or unsupported header (plyfile: "
                         f"{_reason(exc, name=False)}); expected format ascii, binary_little_endian or "
                         f"binary_big_endian 1.0 and scalar types char uchar short ushort int uint float double "
                         f"(or int8 ... float64)") from None
    except PlyElementParseError as exc:
        raise InputError(f"points: PLY {path}: {_ply_data_reason(exc)}") from None
    except ValueError as exc:  # non-ASCII header, two elements of one name, a negative count
        raise InputError(f"points: PLY {path}: malformed header ({_reason(exc)})") from None
    if "vertex" not in ply:
        found = " ".join(element.name for element in ply.elements) or "none"
        raise InputError(f"points: PLY {path} has no 'vertex' element; expected 'element vertex N' with "
                         f"properties x y z [intensity], found elements: {found}")
    vertex = ply["vertex"]
    lists = [prop.name for prop in vertex.properties if isinstance(prop, PlyListProperty)]
    if lists:
        raise InputError(f"points: PLY {path}: list property {', '.join(lists)} in the vertex element; "
                         f"expected scalar vertex properties x y z [intensity]")
    return _columns({prop.name: vertex[prop.name] for prop in vertex.properties}, path, "PLY")


def _ply_data_reason(exc: PlyElementParseError) -> str:
    """What a plyfile element error means: truncation (with counts) or data not matching the header."""
    element = exc.element
    if exc.message == "early end-of-file" and element is not None:
        what = "vertices" if element.name == "vertex" else f"{element.name!r} elements"
        return f"header announces {element.count} {what}, the file holds {exc.row} (truncated)"
    return f"data do not match the header (plyfile: {_reason(exc, name=False)})"


def _pcd_header(path: Path) -> MetaData:
    """The header as pypcd4 parses it, checked before pypcd4 reads the data.

    pypcd4 collects up to 10 non-comment lines, stops at ``DATA`` and validates them with
    ``MetaData.parse_header``; a header without ``DATA`` is silently taken as
    ``binary_compressed`` and unequal FIELDS/SIZE/TYPE lists misread, so the same lines
    are collected here and those cases refused by name.
    """
    lines = []
    with open(path, "rb") as handle:
        while len(lines) < _PCD_HEADER_LINES and (raw := handle.readline(1 << 16)):
            try:
                line = raw.decode("utf-8").strip()
            except UnicodeDecodeError:
                raise InputError(f"points: {path} is not a PCD file: expected a text header ending with a DATA "
                                 f"line, found binary bytes after {len(lines)} header line(s)") from None
            if line and not line.startswith("#"):
                lines.append(line)
                if line.startswith("DATA"):
                    break
    if not lines or not lines[-1].startswith("DATA"):
        found = " | ".join(line[:40] for line in lines[:3]) or "no text"
        raise InputError(f"points: {path} is not a PCD file or its header is malformed: expected at most "
                         f"{_PCD_HEADER_LINES} header lines (VERSION FIELDS SIZE TYPE COUNT WIDTH HEIGHT "
                         f"[VIEWPOINT] POINTS) ending with DATA, found {found!r}")
    try:
        header = MetaData.parse_header(lines)
    except ValueError as exc:  # pydantic.ValidationError, int()/float() of a header value
        raise InputError(f"points: PCD {path}: malformed or unsupported header ({_header_reason(exc)})") from None
    _check_pcd_fields(header, path)
    return header


def _header_reason(exc: ValueError) -> str:
    """A pydantic ValidationError as ``field: message (got value)``; other errors via :func:`_reason`."""
    errors = getattr(exc, "errors", None)
    if not callable(errors):
        return _reason(exc)
    parts = []
    for error in errors()[:3]:
        where = ".".join(str(part) for part in error["loc"]).upper()
        got = "" if error["type"] == "missing" else f", got {error['input']!r}"
        parts.append(f"{where}: {error['msg']}{got}")
    return "; ".join(parts)


def _check_pcd_fields(header: MetaData, path: Path) -> None:
    """InputError unless FIELDS, SIZE, TYPE and COUNT agree and name types NumPy can read."""
    lengths = [len(header.fields), len(header.size), len(header.type), len(header.count)]
    if len(set(lengths)) > 1:
        raise InputError(f"points: PCD {path}: malformed header: expected FIELDS, SIZE, TYPE and COUNT to list "
                         f"one entry per field, found {'/'.join(map(str, lengths))} entries")
    try:
        header.build_dtype()
    except KeyError as exc:  # pypcd4's (TYPE, SIZE) -> NumPy table has no entry
        kind, size = exc.args[0]
        name = next(n for n, k, s in zip(header.fields, header.type, header.size) if (k, s) == (kind, size))
        raise InputError(f"points: PCD {path}: unsupported field type {kind} of size {size} for field {name!r}; "
                         f"expected F 4/8 or I/U 1/2/4/8") from None


def _read_pcd(path: Path) -> np.ndarray:
    """PCD through ``pypcd4.PointCloud.from_path``, header checked first and point count after."""
    _check_not_empty(path, "PCD")
    header = _pcd_header(path)
    data = header.data.value
    try:
        cloud = PointCloud.from_path(path)
    except _PCD_DATA_ERRORS as exc:
        raise InputError(f"points: PCD {path}: header announces {header.points} points (DATA {data}), the data "
                         f"cannot be read ({_reason(exc)}): truncated, damaged or not as the header "
                         f"describes") from None
    table = np.atleast_1d(cloud.pc_data)[: header.points]  # pypcd4 gives a 0-d array for one ascii point
    if len(table) < header.points:
        raise InputError(f"points: PCD {path}: header announces {header.points} points, the file holds "
                         f"{len(table)} (DATA {data}, truncated)")
    meta = cloud.metadata
    fields = {name: table[name if count == 1 else f"{name}__0000"] for name, count in zip(meta.fields, meta.count)}
    return _columns(fields, path, "PCD")


# --------------------------------------------------------------------------- writing


def _points_for_writing(points: np.ndarray) -> np.ndarray:
    array = np.asarray(points)
    if array.ndim != 2 or array.shape[1] not in (3, 4):
        raise InputError(f"points: expected an (N, 3) or (N, 4) array (x y z [intensity]), got shape {array.shape}")
    if not np.issubdtype(array.dtype, np.number) or np.issubdtype(array.dtype, np.complexfloating):
        raise InputError(f"points: expected real numbers, got dtype {array.dtype}")
    return np.ascontiguousarray(array, dtype=np.float32)


def _write_atomic(path: PathLike, write: Callable[[Path], None]) -> Path:
    """Check ``path`` as an output file (named ``path``), then ``write`` it atomically."""
    path = check_output_file(path, "path")
    atomic_write(path, write)
    return path


def write_ply(path: PathLike, points: np.ndarray, *, binary: bool = True) -> Path:
    """Write points as a PLY file with plyfile (vertex x y z [intensity], float32).

    Args:
        path: output file (its folder must exist); conventionally ``.ply``. Written
            atomically (a temporary file renamed over it).
        points: (N, 3) or (N, 4) x, y, z (+ intensity); written as float32 (the input is
            not modified).
        binary: ``binary_little_endian`` (default) or ``ascii`` (plyfile writes 18 significant digits).

    Returns:
        ``path`` as a Path. :func:`read_points` returns the same float32 values.
    """
    table = _points_for_writing(points)
    records = table.view(np.dtype([(name, np.float32) for name in _NAMES[: table.shape[1]]])).reshape(-1)
    ply = PlyData([PlyElement.describe(records, "vertex")], text=not binary, byte_order="<",
                  comments=["written by crfdepth"])
    return _write_atomic(path, lambda temporary: ply.write(str(temporary)))


def write_pcd(path: PathLike, points: np.ndarray, *, binary: bool = True, compressed: bool = False) -> Path:
    """Write points as a PCD v0.7 file with pypcd4 (fields x y z [intensity], float32, unorganised).

    Args:
        path: output file (its folder must exist); conventionally ``.pcd``. Written
            atomically (a temporary file renamed over it).
        points: (N, 3) or (N, 4) x, y, z (+ intensity); written as float32.
        binary: ``DATA binary`` (default) or ``DATA ascii``.
        compressed: ``DATA binary_compressed`` (LZF, per-field layout); needs ``binary``.
            pypcd4 falls back to ``DATA binary`` when LZF cannot shrink the data (a few
            points, noise-like values); :func:`read_points` reads either.

    Returns:
        ``path`` as a Path. :func:`read_points` returns the same float32 values.

    Raises:
        InputError: bad ``points`` shape or dtype, or ``compressed`` without ``binary``.
    """
    if compressed and not binary:
        raise InputError("compressed: binary_compressed is a binary PCD encoding; expected binary=True with "
                         "compressed=True, got binary=False")
    table = _points_for_writing(points)
    names = _NAMES[: table.shape[1]]
    cloud = PointCloud.from_points(table, names, [np.float32] * len(names))
    if not binary:
        return _write_atomic(path, lambda temporary: _save_pcd_ascii(cloud, table, temporary))
    encoding = Encoding.BINARY_COMPRESSED if compressed else Encoding.BINARY
    return _write_atomic(path, lambda temporary: cloud.save(temporary, encoding=encoding))


def _save_pcd_ascii(cloud: PointCloud, table: np.ndarray, file: Path) -> None:
    """pypcd4's ASCII header, then the (N, C) float32 ``table`` at 9 significant digits.

    pypcd4's own ASCII body uses ``%.10f`` (10 decimals), which loses float32 values
    below about 1e-3; 9 significant digits read back bit for bit.
    """
    with open(file, "wb") as handle:
        handle.write(cloud.metadata.compose_header(data=Encoding.ASCII).encode("ascii"))
        np.savetxt(handle, table, fmt="%.9g")
