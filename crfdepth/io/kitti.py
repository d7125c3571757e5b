"""Readers and writers for the KITTI file formats (DESIGN.md section 1).

Covers the depth-completion PNGs (uint16, depth = value / 256, 0 = missing), the
camera images, the 3x3 intrinsics of ``val_selection_cropped/intrinsics``, the Velodyne
scans (``N x 4`` float32 ``.bin``) and both calibration formats: the raw-data day folder
(``calib_cam_to_cam.txt`` + ``calib_velo_to_cam.txt``) and the object-benchmark per-frame
file (``P0..P3``, ``R0_rect``, ``Tr_velo_to_cam``).

Missing files raise ``FileNotFoundError`` naming the path; files that exist but hold
the wrong content raise :class:`crfdepth.errors.InputError` naming the file, what was
expected and what was found.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from crfdepth.errors import InputError
from crfdepth.io.files import atomic_write_bytes

__all__ = [
    "Calibration",
    "load_calibration",
    "read_depth_png",
    "read_intrinsics",
    "read_object_calibration",
    "read_raw_calibration",
    "read_rgb",
    "read_velodyne",
    "write_depth_png",
]

PathLike = str | os.PathLike

# KITTI depth PNGs store depth * 256 as uint16.
_DEPTH_SCALE = 256.0
_UINT16_MAX = np.iinfo(np.uint16).max

_RAW_CAM_TO_CAM = "calib_cam_to_cam.txt"
_RAW_VELO_TO_CAM = "calib_velo_to_cam.txt"


# --------------------------------------------------------------------------- helpers


def _existing_file(path: PathLike, what: str) -> Path:
    """``path`` as a Path, or ``FileNotFoundError`` naming ``what`` and the path."""
    path = Path(path)
    if not path.exists():
        raise FileNotFoundError(f"{what}: no such file: {path}")
    if path.is_dir():
        raise IsADirectoryError(f"{what}: expected a file, got a directory: {path}")
    return path


def _decode_image(path: PathLike, what: str) -> np.ndarray:
    """Decode an image file with ``cv2.IMREAD_UNCHANGED`` (no bit-depth or channel change)."""
    path = _existing_file(path, what)
    buffer = np.fromfile(path, dtype=np.uint8)
    image = cv2.imdecode(buffer, cv2.IMREAD_UNCHANGED) if buffer.size else None
    if image is None:
        raise InputError(f"{what}: {path} is not a readable image ({buffer.size} bytes)")
    return image


def _check_camera(camera: int) -> int:
    if isinstance(camera, bool) or not isinstance(camera, (int, np.integer)) or not 0 <= camera <= 3:
        raise InputError(f"camera: expected one of 0, 1, 2, 3 (KITTI camera index), got {camera!r}")
    return int(camera)


# --------------------------------------------------------------------------- depth PNG


def read_depth_png(path: PathLike) -> np.ndarray:
    """Read a KITTI depth PNG (velodyne_raw, groundtruth or a prediction).

    Args:
        path: 16-bit single-channel PNG holding ``depth * 256``.

    Returns:
        (H, W) float32 depth in metres (``value / 256``); 0 = no measurement.

    Raises:
        FileNotFoundError: ``path`` does not exist.
        InputError: the file is not a 16-bit single-channel image.
    """
    image = _decode_image(path, "depth png")
    if image.dtype != np.uint16 or image.ndim != 2:
        channels = 1 if image.ndim == 2 else image.shape[2]
        raise InputError(
            f"depth png: expected a 16-bit single-channel PNG (depth * 256), got {image.dtype} "
            f"with {channels} channel(s) in {path}")
    return image.astype(np.float32) / np.float32(_DEPTH_SCALE)


def write_depth_png(path: PathLike, depth: np.ndarray) -> None:
    """Write a depth map as a KITTI depth PNG (uint16, ``round(depth * 256)``).

    The file appears atomically: the PNG is written to a temporary file in the same
    directory and moved onto ``path`` only when complete, so a failure never leaves a
    half-written file. ``read_depth_png(write_depth_png(p, x))`` returns ``x`` exactly when
    every value is a multiple of 1/256 m in [0, 65535/256].

    Args:
        path: output file; must end in ``.png``; its directory must exist.
        depth: (H, W) depth in metres, 0 = missing. Values are rounded to the nearest
            1/256 m, so a positive depth below 1/512 m also becomes 0 (missing); depths
            above 65535/256 m (about 256 m) are clipped to the largest code.

    Raises:
        InputError: ``depth`` is not a 2-D real array, holds NaN, infinite or negative
            values, or ``path`` does not end in ``.png``.
        FileNotFoundError: the directory of ``path`` does not exist.
        PermissionError: the directory is not writable.
    """
    path = Path(path)
    array = np.asarray(depth)
    if array.ndim != 2:
        raise InputError(f"depth: expected a 2-D (H, W) array in metres, got shape {array.shape}")
    if not (np.issubdtype(array.dtype, np.floating) or np.issubdtype(array.dtype, np.integer)):
        raise InputError(f"depth: expected a real-valued array in metres, got dtype {array.dtype}")
    if array.size and not np.all(np.isfinite(array)):
        raise InputError(f"depth: expected finite values in metres (0 = missing), got "
                         f"{int(np.count_nonzero(~np.isfinite(array)))} NaN or infinite value(s)")
    if array.size and array.min() < 0:
        raise InputError(f"depth: expected values >= 0 metres (0 = missing), got minimum {array.min()}")
    if path.suffix.lower() != ".png":
        raise InputError(f"path: expected a file name ending in .png, got {path}")
    directory = path.parent
    if not directory.is_dir():
        raise FileNotFoundError(f"depth png: output directory does not exist: {directory}")

    codes = np.clip(np.round(array.astype(np.float64) * _DEPTH_SCALE), 0, _UINT16_MAX).astype(np.uint16)
    ok, encoded = cv2.imencode(".png", codes)
    if not ok:  # pragma: no cover - cv2 encodes any 2-D uint16 array
        raise InputError(f"depth: could not encode an array of shape {codes.shape} as PNG")

    atomic_write_bytes(path, encoded.tobytes())


# --------------------------------------------------------------------------- images


def read_rgb(path: PathLike) -> np.ndarray:
    """Read a camera image as RGB.

    Args:
        path: 8-bit PNG/JPEG. A greyscale image (KITTI cameras 0 and 1) is repeated over
            the three channels; an alpha channel is dropped.

    Returns:
        (H, W, 3) uint8 image in RGB channel order.

    Raises:
        FileNotFoundError: ``path`` does not exist.
        InputError: the file is not an 8-bit image.
    """
    image = _decode_image(path, "image")
    if image.dtype != np.uint8:
        raise InputError(f"image: expected an 8-bit image, got {image.dtype} in {path}")
    if image.ndim == 2:
        return np.repeat(image[:, :, None], 3, axis=2)
    if image.shape[2] == 4:
        return cv2.cvtColor(image, cv2.COLOR_BGRA2RGB)
    if image.shape[2] == 3:
        return cv2.cvtColor(image, cv2.COLOR_BGR2RGB)
    raise InputError(f"image: expected 1, 3 or 4 channels, got {image.shape[2]} in {path}")


# --------------------------------------------------------------------------- intrinsics


def read_intrinsics(path: PathLike) -> np.ndarray:
    """Read the 3x3 camera matrix of ``val_selection_cropped/intrinsics/*.txt``.

    Args:
        path: text file with the 9 entries of K, row-major, separated by white space.

    Returns:
        (3, 3) float64 K in pixels (fx, fy, cx, cy already follow the benchmark's crop).

    Raises:
        FileNotFoundError: ``path`` does not exist.
        InputError: the file does not hold exactly 9 numbers.
    """
    path = _existing_file(path, "intrinsics")
    tokens = path.read_text().split()
    try:
        values = np.array([float(token) for token in tokens], dtype=np.float64)
    except ValueError as exc:
        raise InputError(f"intrinsics: expected 9 numbers in {path}, got non-numeric text ({exc})") from None
    if values.size != 9:
        raise InputError(f"intrinsics: expected 9 numbers (row-major 3x3 K) in {path}, got {values.size}")
    return values.reshape(3, 3)


# --------------------------------------------------------------------------- Velodyne


def read_velodyne(path: PathLike) -> np.ndarray:
    """Read a KITTI Velodyne scan.

    Args:
        path: ``.bin`` file of little-endian float32 records (x, y, z, reflectance).

    Returns:
        (N, 4) float32: x, y, z in metres in the Velodyne frame (x forward, y left,
        z up) and reflectance in [0, 1], in the sensor's scan order (which
        :func:`crfdepth.projection.recover_rings` relies on).

    Raises:
        FileNotFoundError: ``path`` does not exist.
        InputError: the file size is not a multiple of 16 bytes (4 float32 per point).
    """
    path = _existing_file(path, "velodyne")
    size = path.stat().st_size
    if size % 16:
        raise InputError(f"velodyne: expected a file size that is a multiple of 16 bytes "
                         f"(4 float32 per point), got {size} bytes in {path}")
    return np.fromfile(path, dtype="<f4").astype(np.float32, copy=False).reshape(-1, 4)


# --------------------------------------------------------------------------- calibration


@dataclass(eq=False)
class Calibration:
    """Camera and Velodyne calibration of one KITTI camera.

    A Velodyne point ``x`` (homogeneous, metres) maps to pixels by
    ``y = P_rect @ R_rect @ T_velo_to_cam @ x`` (DESIGN.md section 1, paper Sec. 3.1),
    ``u = y[0] / y[2]``, ``v = y[1] / y[2]``.

    Depth convention: crfdepth stores ``y[2]``, the third row of that product. It equals
    the z of the point in the rectified frame of camera 0 plus ``P_rect[2, 3]`` (the chosen
    camera's offset along the optical axis: 2.7 mm for KITTI camera 2, 0 for camera 0),
    i.e. the z-depth in the chosen camera's own frame.

    Attributes:
        P_rect: (3, 4) rectified projection matrix of the chosen camera (pixels).
        R_rect: (4, 4) rectifying rotation of camera 0 (``R_rect_00`` / ``R0_rect``),
            padded with a 1 on the diagonal.
        T_velo_to_cam: (4, 4) rigid transform from the Velodyne frame to the unrectified
            camera-0 frame, metres.
        image_size: (height, width) in pixels of the rectified image (``S_rect_0X`` in
            raw-data calibration); None where the file does not say (object benchmark).

    The matrices are stored as float64 copies; two calibrations compare equal when
    every matrix and the image size are equal.
    """

    P_rect: np.ndarray
    R_rect: np.ndarray
    T_velo_to_cam: np.ndarray
    image_size: tuple[int, int] | None = None

    def __post_init__(self) -> None:
        for name, shape in (("P_rect", (3, 4)), ("R_rect", (4, 4)), ("T_velo_to_cam", (4, 4))):
            matrix = np.array(getattr(self, name), dtype=np.float64)
            if matrix.shape != shape:
                raise InputError(f"Calibration.{name}: expected shape {shape}, got {matrix.shape}")
            setattr(self, name, matrix)
        if self.image_size is not None:
            size = tuple(self.image_size)
            if len(size) != 2 or any(int(n) != n or n <= 0 for n in size):
                raise InputError(f"Calibration.image_size: expected (height, width) of positive integers "
                                 f"or None, got {self.image_size!r}")
            self.image_size = (int(size[0]), int(size[1]))

    def __eq__(self, other: object) -> bool:
        if not isinstance(other, Calibration):
            return NotImplemented
        return (self.image_size == other.image_size
                and all(np.array_equal(getattr(self, name), getattr(other, name))
                        for name in ("P_rect", "R_rect", "T_velo_to_cam")))

    @property
    def K(self) -> np.ndarray:
        """(3, 3) intrinsics of the rectified camera, ``P_rect[:, :3]`` (pixels)."""
        return self.P_rect[:, :3].copy()

    def velo_to_rect_cam(self) -> np.ndarray:
        """(4, 4) transform Velodyne -> rectified camera-0 frame, ``R_rect @ T_velo_to_cam``."""
        return self.R_rect @ self.T_velo_to_cam

    def velo_to_image(self) -> np.ndarray:
        """(3, 4) projection Velodyne -> image, ``P_rect @ R_rect @ T_velo_to_cam``.

        The third row gives the stored z-depth (see the class docstring).
        """
        return self.P_rect @ self.R_rect @ self.T_velo_to_cam


def _read_key_values(path: Path, what: str) -> dict[str, str]:
    """``key: values`` lines of a KITTI calibration file (values kept as text)."""
    entries = {}
    for line in path.read_text().splitlines():
        key, sep, value = line.partition(":")
        if sep and key.strip():
            entries[key.strip()] = value.strip()
    if not entries:
        raise InputError(f"{what}: expected 'key: values' lines in {path}, found none")
    return entries


def _matrix(entries: dict[str, str], key: str, shape: tuple[int, ...], path: Path) -> np.ndarray:
    """Entry ``key`` of a calibration file as a float64 array of ``shape``."""
    if key not in entries:
        raise InputError(f"calibration: key '{key}' not found in {path} (keys present: "
                         f"{', '.join(sorted(entries))})")
    try:
        values = np.array([float(token) for token in entries[key].split()], dtype=np.float64)
    except ValueError:
        raise InputError(f"calibration: key '{key}' in {path}: expected numbers, "
                         f"got {entries[key][:60]!r}") from None
    if values.size != int(np.prod(shape)):
        raise InputError(f"calibration: key '{key}' in {path}: expected {int(np.prod(shape))} numbers "
                         f"{shape}, got {values.size}")
    return values.reshape(shape)


def _pad_rotation(R: np.ndarray) -> np.ndarray:
    """(3, 3) -> (4, 4) with a 1 in the corner."""
    padded = np.eye(4)
    padded[:3, :3] = R
    return padded


def _pad_transform(Rt: np.ndarray) -> np.ndarray:
    """(3, 4) ``[R | t]`` -> (4, 4) homogeneous transform."""
    padded = np.eye(4)
    padded[:3, :] = Rt
    return padded


def read_raw_calibration(day_dir: PathLike, camera: int = 2) -> Calibration:
    """Read the calibration of a KITTI raw-data day folder (e.g. ``raw/2011_09_26``).

    Args:
        day_dir: folder holding ``calib_cam_to_cam.txt`` and ``calib_velo_to_cam.txt``.
        camera: KITTI camera index 0-3 (2 = left colour camera).

    Returns:
        :class:`Calibration` with ``P_rect = P_rect_0X``, ``R_rect = R_rect_00`` (every
        ``P_rect_0X`` is defined on camera 0's rectified frame), ``T_velo_to_cam = [R | T]``
        and ``image_size`` from ``S_rect_0X`` (stored as width height; returned as
        (height, width)).

    Raises:
        FileNotFoundError: the folder or one of the two files is missing.
        InputError: a key is missing or does not hold the expected count of numbers.
    """
    camera = _check_camera(camera)
    day_dir = Path(day_dir)
    if not day_dir.is_dir():
        raise FileNotFoundError(f"calibration: no such directory: {day_dir}")
    cam_path = _existing_file(day_dir / _RAW_CAM_TO_CAM, "calibration")
    velo_path = _existing_file(day_dir / _RAW_VELO_TO_CAM, "calibration")
    cam = _read_key_values(cam_path, "calibration")
    velo = _read_key_values(velo_path, "calibration")

    width, height = _matrix(cam, f"S_rect_0{camera}", (2,), cam_path)
    T = np.eye(4)
    T[:3, :3] = _matrix(velo, "R", (3, 3), velo_path)
    T[:3, 3] = _matrix(velo, "T", (3,), velo_path)
    return Calibration(
        P_rect=_matrix(cam, f"P_rect_0{camera}", (3, 4), cam_path),
        R_rect=_pad_rotation(_matrix(cam, "R_rect_00", (3, 3), cam_path)),
        T_velo_to_cam=T,
        image_size=(int(round(height)), int(round(width))),
    )


def read_object_calibration(path: PathLike, camera: int = 2) -> Calibration:
    """Read a KITTI object-benchmark calibration file (``training/calib/000000.txt``).

    Args:
        path: text file with keys ``P0``..``P3``, ``R0_rect`` and ``Tr_velo_to_cam``.
        camera: KITTI camera index 0-3 (2 = left colour camera).

    Returns:
        :class:`Calibration` with ``P_rect = P{camera}``, ``R_rect = R0_rect`` padded,
        ``T_velo_to_cam = Tr_velo_to_cam`` padded and ``image_size = None`` (the file does
        not give it; take it from the image).

    Raises:
        FileNotFoundError: ``path`` does not exist.
        InputError: a key is missing or does not hold the expected count of numbers.
    """
    camera = _check_camera(camera)
    path = _existing_file(path, "calibration")
    entries = _read_key_values(path, "calibration")
    return Calibration(
        P_rect=_matrix(entries, f"P{camera}", (3, 4), path),
        R_rect=_pad_rotation(_matrix(entries, "R0_rect", (3, 3), path)),
        T_velo_to_cam=_pad_transform(_matrix(entries, "Tr_velo_to_cam", (3, 4), path)),
        image_size=None,
    )


def load_calibration(path: PathLike, camera: int = 2) -> Calibration:
    """Read either KITTI calibration format, chosen from what ``path`` is.

    Args:
        path: a raw-data day folder; or one of its two files (``calib_cam_to_cam.txt``,
            ``calib_velo_to_cam.txt``, recognised by name or by their keys), which stands
            for its folder; or an object-benchmark calibration file.
        camera: KITTI camera index 0-3 (2 = left colour camera).

    Returns:
        :class:`Calibration` (see :func:`read_raw_calibration` and
        :func:`read_object_calibration`).

    Raises:
        FileNotFoundError: ``path`` (or a file it needs) does not exist.
        InputError: a key is missing or malformed.
    """
    path = Path(path)
    if path.is_dir():
        return read_raw_calibration(path, camera)
    path = _existing_file(path, "calibration")
    if path.name in (_RAW_CAM_TO_CAM, _RAW_VELO_TO_CAM):
        return read_raw_calibration(path.parent, camera)
    keys = _read_key_values(path, "calibration").keys()
    if "R_rect_00" in keys or ({"R", "T"} <= keys and "Tr_velo_to_cam" not in keys):
        return read_raw_calibration(path.parent, camera)
    return read_object_calibration(path, camera)
