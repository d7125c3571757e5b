"""Point-cloud files: KITTI ``.bin``, NumPy ``.npy``, PLY and PCD (docs/design.md section 1).

:func:`read_points` returns an ``(N, 3)`` or ``(N, 4)`` float32 array (x, y, z in the
sensor frame, metres, plus intensity when the file has it) from:

- ``.bin``: KITTI Velodyne scan, raw little-endian float32, 4 values per point;
- ``.npy``: a 2-D array with 3 or 4 columns (further columns are an error: say which
  three are x y z by slicing before saving);
- ``.ply``: ``ascii`` or ``binary_little_endian``, ``element vertex`` with properties
  ``x y z`` and optionally ``intensity`` (other vertex properties are skipped; other
  elements after the vertices, e.g. faces, are ignored);
- ``.pcd``: ``DATA ascii`` or ``DATA binary`` (not ``binary_compressed``), fields ``x y z``
  and optionally ``intensity`` (other fields are skipped).

:func:`write_ply` and :func:`write_pcd` write binary (default) or ascii files that
:func:`read_points` reads back exactly (float32). No dependency beyond NumPy: the
readers parse the headers and hand the body to ``numpy.frombuffer`` / ``numpy.loadtxt``.

Missing files raise ``FileNotFoundError``; unsupported formats, wrong column counts and
truncated files raise :class:`crfdepth.errors.InputError` naming the file, what was
expected and what was found.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from crfdepth.errors import InputError
from crfdepth.io.files import atomic_write_bytes, check_input_file, check_output_file

__all__ = ["POINT_FORMATS", "read_points", "write_pcd", "write_ply"]

PathLike = str | os.PathLike
POINT_FORMATS = (".bin", ".npy", ".ply", ".pcd")
_NPY_MAGIC = b"\x93NUMPY"

# PLY scalar type names (both spellings) -> little-endian NumPy dtype.
_PLY_TYPES = {
    "char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1",
    "short": "<i2", "int16": "<i2", "ushort": "<u2", "uint16": "<u2",
    "int": "<i4", "int32": "<i4", "uint": "<u4", "uint32": "<u4",
    "float": "<f4", "float32": "<f4", "double": "<f8", "float64": "<f8",
}
# PCD (TYPE, SIZE) -> NumPy dtype (PCD binary data is little-endian in practice).
_PCD_TYPES = {("F", 4): "<f4", ("F", 8): "<f8", ("I", 1): "i1", ("I", 2): "<i2", ("I", 4): "<i4",
              ("I", 8): "<i8", ("U", 1): "u1", ("U", 2): "<u2", ("U", 4): "<u4", ("U", 8): "<u8"}


def _columns(fields: dict[str, np.ndarray], path: Path, what: str) -> np.ndarray:
    """Stack x, y, z (+ intensity) into float32 (N, 3|4); InputError when x y z are missing."""
    missing = [name for name in ("x", "y", "z") if name not in fields]
    if missing:
        raise InputError(f"points: {what} {path} has no {', '.join(missing)} field(s); expected x y z "
                         f"[intensity], found {' '.join(fields) or 'none'}")
    names = ["x", "y", "z"] + (["intensity"] if "intensity" in fields else [])
    return np.stack([np.asarray(fields[n], dtype=np.float32) for n in names], axis=1)


# --------------------------------------------------------------------------- reading


def read_points(path: PathLike) -> np.ndarray:
    """Read a point cloud file, chosen by its extension (see the module docstring).

    Args:
        path: a ``.bin``, ``.npy``, ``.ply`` or ``.pcd`` file.

    Returns:
        (N, 3) or (N, 4) float32 points: x, y, z in the file's frame (metres for LiDAR
        data), then intensity when the file has one (a KITTI ``.bin`` always has 4
        columns). Rows are in file order; NaN rows are kept (the caller decides;
        :func:`crfdepth.api.complete_depth` drops them with a warning).

    Raises:
        FileNotFoundError: ``path`` does not exist.
        InputError: unsupported extension, malformed header, missing x/y/z fields, wrong
            column count or truncated data.
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
    size = path.stat().st_size
    if size % 16:
        raise InputError(f"points: KITTI .bin {path} holds {size} bytes, not a whole number of points "
                         f"(4 float32 = 16 bytes each): truncated file or not a Velodyne scan")
    return np.fromfile(path, dtype="<f4").astype(np.float32).reshape(-1, 4)


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


def _read_header(handle, path: Path, what: str, end: str, max_lines: int = 200) -> list[str]:
    """Header lines up to and including the one starting with ``end`` (ASCII)."""
    lines = []
    for _ in range(max_lines):
        raw = handle.readline()
        if not raw:
            break
        line = raw.decode("ascii", errors="replace").strip()
        lines.append(line)
        if line.split(" ", 1)[0] == end:
            return lines
    raise InputError(f"points: {what} {path}: header has no '{end}' line (truncated or not a {what} file)")


def _read_ply(path: Path) -> np.ndarray:
    with open(path, "rb") as handle:
        if handle.readline().strip() != b"ply":
            raise InputError(f"points: {path} is not a PLY file (first line is not 'ply')")
        header = _read_header(handle, path, "PLY", "end_header")
        body = handle.read()
    fmt, count, props, in_vertex, seen_vertex = None, None, [], False, False
    for line in header:
        tokens = line.split()
        if not tokens or tokens[0] in ("comment", "obj_info"):
            continue
        if tokens[0] == "format":
            fmt = tokens[1] if len(tokens) > 1 else ""
        elif tokens[0] == "element":
            in_vertex = len(tokens) == 3 and tokens[1] == "vertex"
            if in_vertex:
                if seen_vertex:
                    raise InputError(f"points: PLY {path}: two 'element vertex' lines")
                seen_vertex, count = True, int(tokens[2])
            elif not seen_vertex:
                raise InputError(f"points: PLY {path}: element {tokens[1:2]} comes before 'element vertex'; "
                                 f"only files whose first element is the vertices are supported")
        elif tokens[0] == "property" and in_vertex:
            if tokens[1] == "list":
                raise InputError(f"points: PLY {path}: list property in the vertex element is not supported")
            if tokens[1] not in _PLY_TYPES or len(tokens) != 3:
                raise InputError(f"points: PLY {path}: unknown vertex property type in {line!r}")
            props.append((tokens[2], _PLY_TYPES[tokens[1]]))
    if count is None:
        raise InputError(f"points: PLY {path}: no 'element vertex N' line in the header")
    names = [name for name, _ in props]
    if fmt == "ascii":
        rows = body.decode("ascii", errors="replace").split("\n")
        rows = [r for r in rows if r.strip()][:count]
        if len(rows) < count:
            raise InputError(f"points: PLY {path}: header announces {count} vertices, the file holds "
                             f"{len(rows)} (truncated)")
        try:
            table = np.array([r.split()[: len(props)] for r in rows], dtype=np.float64).reshape(count, len(props))
        except ValueError:
            raise InputError(f"points: PLY {path}: expected {len(props)} numbers per vertex line") from None
        fields = {name: table[:, i] for i, name in enumerate(names)}
    elif fmt == "binary_little_endian":
        dtype = np.dtype([(f"f{i}", t) for i, (_, t) in enumerate(props)])
        need = count * dtype.itemsize
        if len(body) < need:
            raise InputError(f"points: PLY {path}: header announces {count} vertices ({need} bytes), the "
                             f"file holds {len(body)} bytes of data (truncated)")
        table = np.frombuffer(body, dtype=dtype, count=count)
        fields = {name: table[f"f{i}"] for i, name in enumerate(names)}
    else:
        raise InputError(f"points: PLY {path}: unsupported format {fmt!r}; expected ascii or "
                         f"binary_little_endian")
    return _columns(fields, path, "PLY")


def _read_pcd(path: Path) -> np.ndarray:
    with open(path, "rb") as handle:
        header = _read_header(handle, path, "PCD", "DATA")
        body = handle.read()
    entries = {}
    for line in header:
        tokens = line.split()
        if tokens and not tokens[0].startswith("#"):
            entries[tokens[0].upper()] = tokens[1:]
    for key in ("FIELDS", "SIZE", "TYPE"):
        if key not in entries:
            raise InputError(f"points: PCD {path}: header has no {key} line")
    names, sizes, types = entries["FIELDS"], entries["SIZE"], entries["TYPE"]
    counts = entries.get("COUNT", ["1"] * len(names))
    if not len(names) == len(sizes) == len(types) == len(counts):
        raise InputError(f"points: PCD {path}: FIELDS, SIZE, TYPE and COUNT list different numbers of entries")
    try:
        sizes, counts = [int(s) for s in sizes], [int(c) for c in counts]
        n = int(entries["POINTS"][0]) if "POINTS" in entries else (
            int(entries["WIDTH"][0]) * int(entries.get("HEIGHT", ["1"])[0]))
    except (ValueError, IndexError, KeyError):
        raise InputError(f"points: PCD {path}: malformed SIZE/COUNT/POINTS/WIDTH in the header") from None
    data = entries["DATA"][0].lower() if entries["DATA"] else ""
    columns = []  # (name, dtype, count)
    for name, size, kind, cnt in zip(names, sizes, types, counts):
        dtype = _PCD_TYPES.get((kind.upper(), size))
        if dtype is None:
            raise InputError(f"points: PCD {path}: unsupported field type {kind} of size {size} for {name!r}")
        columns.append((name, dtype, cnt))
    if data == "ascii":
        width = sum(c for _, _, c in columns)
        rows = [r for r in body.decode("ascii", errors="replace").split("\n") if r.strip()][:n]
        if len(rows) < n:
            raise InputError(f"points: PCD {path}: header announces {n} points, the file holds {len(rows)} "
                             f"(truncated)")
        try:
            table = np.array([r.split() for r in rows], dtype=np.float64).reshape(n, width)
        except ValueError:
            raise InputError(f"points: PCD {path}: expected {width} numbers per point line") from None
        fields, offset = {}, 0
        for name, _, cnt in columns:
            fields[name] = table[:, offset]
            offset += cnt
    elif data == "binary":
        dtype = np.dtype([(f"f{i}", t, (c,)) if c > 1 else (f"f{i}", t) for i, (_, t, c) in enumerate(columns)])
        need = n * dtype.itemsize
        if len(body) < need:
            raise InputError(f"points: PCD {path}: header announces {n} points ({need} bytes), the file holds "
                             f"{len(body)} bytes of data (truncated)")
        table = np.frombuffer(body, dtype=dtype, count=n)
        fields = {name: table[f"f{i}"] if c == 1 else table[f"f{i}"][:, 0]
                  for i, (name, _, c) in enumerate(columns)}
    else:
        raise InputError(f"points: PCD {path}: unsupported DATA {data!r}; expected ascii or binary "
                         f"(re-save binary_compressed clouds as binary, e.g. pcl_convert_pcd_ascii_binary)")
    return _columns(fields, path, "PCD")


# --------------------------------------------------------------------------- writing


def _points_for_writing(points: np.ndarray) -> np.ndarray:
    array = np.asarray(points)
    if array.ndim != 2 or array.shape[1] not in (3, 4):
        raise InputError(f"points: expected an (N, 3) or (N, 4) array (x y z [intensity]), got shape {array.shape}")
    if not np.issubdtype(array.dtype, np.number) or np.issubdtype(array.dtype, np.complexfloating):
        raise InputError(f"points: expected real numbers, got dtype {array.dtype}")
    return np.ascontiguousarray(array, dtype=np.float32)


def _write_atomic(path: Path, data: bytes) -> Path:
    """Write ``data`` to ``path`` atomically, after checking it as an output file (named ``path``)."""
    path = check_output_file(path, "path")
    atomic_write_bytes(path, data)
    return path


def _float_text(table: np.ndarray) -> bytes:
    # repr-precision float32 text (9 significant digits) reads back bit for bit.
    return "".join(" ".join(f"{v:.9g}" for v in row) + "\n" for row in table.tolist()).encode("ascii")


def write_ply(path: PathLike, points: np.ndarray, *, binary: bool = True) -> Path:
    """Write points as a PLY file (vertex x y z [intensity], float32).

    Args:
        path: output file (its folder must exist); conventionally ``.ply``.
        points: (N, 3) or (N, 4) x, y, z (+ intensity); written as float32 (the input is
            not modified).
        binary: ``binary_little_endian`` (default) or ``ascii``.

    Returns:
        ``path`` as a Path. :func:`read_points` returns the same float32 values.
    """
    table = _points_for_writing(points)
    names = ["x", "y", "z", "intensity"][: table.shape[1]]
    header = ["ply", f"format {'binary_little_endian' if binary else 'ascii'} 1.0",
              "comment written by crfdepth", f"element vertex {table.shape[0]}"]
    header += [f"property float {n}" for n in names] + ["end_header"]
    body = table.astype("<f4").tobytes() if binary else _float_text(table)
    return _write_atomic(Path(path), ("\n".join(header) + "\n").encode("ascii") + body)


def write_pcd(path: PathLike, points: np.ndarray, *, binary: bool = True) -> Path:
    """Write points as a PCD v0.7 file (fields x y z [intensity], float32, unorganised).

    Args:
        path: output file (its folder must exist); conventionally ``.pcd``.
        points: (N, 3) or (N, 4) x, y, z (+ intensity); written as float32.
        binary: ``DATA binary`` (default) or ``DATA ascii``.

    Returns:
        ``path`` as a Path. :func:`read_points` returns the same float32 values.
    """
    table = _points_for_writing(points)
    c = table.shape[1]
    names = ["x", "y", "z", "intensity"][:c]
    header = ["# .PCD v0.7 - Point Cloud Data file format (written by crfdepth)", "VERSION 0.7",
              f"FIELDS {' '.join(names)}", f"SIZE {' '.join(['4'] * c)}", f"TYPE {' '.join(['F'] * c)}",
              f"COUNT {' '.join(['1'] * c)}", f"WIDTH {table.shape[0]}", "HEIGHT 1",
              "VIEWPOINT 0 0 0 1 0 0 0", f"POINTS {table.shape[0]}", f"DATA {'binary' if binary else 'ascii'}"]
    body = table.astype("<f4").tobytes() if binary else _float_text(table)
    return _write_atomic(Path(path), ("\n".join(header) + "\n").encode("ascii") + body)
