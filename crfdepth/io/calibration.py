"""Camera + LiDAR calibration: the two calibration types and every reader (docs/design.md section 1).

:class:`Calibration` is one KITTI camera as the KITTI files give it (``P_rect``,
``R_rect``, ``T_velo_to_cam``), read from a raw-data day folder (``calib_cam_to_cam.txt``
+ ``calib_velo_to_cam.txt``) or an object-benchmark file (``P0..P3``, ``R0_rect``,
``Tr_velo_to_cam``) by :func:`load_calibration`. :class:`RigCalibration` is any rig:
``K``, ``T_cam_lidar`` and optional ``distortion`` / ``image_size``, from a small YAML
(``.yaml`` / ``.yml``) or JSON (``.json``) file::

    # LiDAR -> camera; metres and pixels
    K: [[1450.0, 0.0, 960.0],        # 3x3 nested list, or 9 numbers row-major
        [0.0, 1450.0, 720.0],
        [0.0, 0.0, 1.0]]
    T_cam_lidar:                     # 4x4 rigid transform, maps LiDAR points into the
      - [0.0, -1.0,  0.0,  0.02]     # camera frame (x right, y down, z forward):
      - [0.0,  0.0, -1.0, -0.08]     # p_cam = T_cam_lidar @ [x, y, z, 1]
      - [1.0,  0.0,  0.0, -0.05]
      - [0.0,  0.0,  0.0,  1.0]
    distortion: [0.1, -0.25, 0.0, 0.0, 0.1]   # optional, OpenCV k1 k2 p1 p2 [k3 [k4 k5 k6 ...]]
    image_size: [1440, 1920]                  # optional, [height, width] in pixels

:func:`load_any_calibration` reads either kind into a :class:`RigCalibration` (a KITTI
one keeps its :class:`Calibration`), so callers need not care which they were given.
Projecting points with either type is :mod:`crfdepth.geometry.projection`'s job; KITTI's
``key: values`` text is parsed by :mod:`crfdepth.io.key_values`. This module imports nothing
above :mod:`crfdepth.checks` and :mod:`crfdepth.io` (``files``, ``key_values``).

Checks: ``K`` and ``T_cam_lidar`` by :func:`crfdepth.intrinsics.check_intrinsics` and
:func:`~crfdepth.checks.check_rigid` (a transform in millimetres passes, its rotation being
fine: it is caught when no point lands in the image); KITTI's transforms by ``check_rigid``
as read (``project`` and ``complete`` refuse the same files); binary files refused; ``distortion`` 4, 5, 8, 12 or 14
finite numbers that keep the image in view (:mod:`crfdepth.io.distortion`); ``image_size`` two
positive integers. A failure is an :class:`~crfdepth.errors.InputError` naming the file and the key.

Every calibration file is read as what it is, before it is parsed: a regular file (not
``/dev/zero`` or a FIFO) of at most ``MAX_CALIBRATION_BYTES`` (1 MiB), each key once, and for
YAML no anchors or aliases and bounded nesting (:mod:`crfdepth.io.key_values`).
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from crfdepth.checks import check_rigid
from crfdepth.errors import InputError
from crfdepth.intrinsics import check_intrinsics
from crfdepth.io.distortion import DISTORTION_LENGTHS, check_distortion  # noqa: F401 (DISTORTION_LENGTHS: re-exported)
from crfdepth.io.files import MAX_CALIBRATION_BYTES, check_input_file, read_text
from crfdepth.io.key_values import entry_array, is_rig_file, list_keys, quote_value, read_key_values, read_mapping

__all__ = [
    "Calibration",
    "RigCalibration",
    "is_rig_file",
    "load_any_calibration",
    "load_calibration",
    "read_object_calibration",
    "read_raw_calibration",
    "read_rig_calibration",
]

PathLike = str | os.PathLike
RIG_SUFFIXES = (".yaml", ".yml", ".json")
_RAW_CAM_TO_CAM = "calib_cam_to_cam.txt"
_RAW_VELO_TO_CAM = "calib_velo_to_cam.txt"


# --------------------------------------------------------------------------- the two types


@dataclass(eq=False)
class Calibration:
    """Camera and Velodyne calibration of one KITTI camera.

    A Velodyne point ``x`` (homogeneous, metres) maps to pixels by
    ``y = P_rect @ R_rect @ T_velo_to_cam @ x`` (docs/design.md section 1, paper Sec. 3.1),
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


@dataclass(eq=False)
class RigCalibration:
    """Camera intrinsics and LiDAR -> camera extrinsics, whatever file they came from.

    Attributes:
        K: (3, 3) float64 pinhole intrinsics of the (undistorted) image, pixels.
        T_cam_lidar: (4, 4) float64 rigid transform from the LiDAR frame to the camera
            frame (x right, y down, z forward), metres.
        distortion: (D,) float64 OpenCV distortion coefficients (k1 k2 p1 p2 [k3 ...]) of
            the raw image, or None for an undistorted / rectified image.
        image_size: (height, width) in pixels, or None when the file does not say.
        kitti: the KITTI :class:`Calibration` this came from, or None. When set,
            :func:`crfdepth.geometry.projection.project_points` projects with ``P_rect R_rect
            T_velo_to_cam`` exactly (:func:`~crfdepth.geometry.projection.project_velodyne`), so
            results match the KITTI tools bit for bit. Here ``K = P_rect[:, :3]`` and ``T_cam_lidar`` is the transform
            into the chosen camera's own frame, ``[I | K^-1 P_rect[:, 3]] R_rect
            T_velo_to_cam`` (so ``K [I | 0] T_cam_lidar == P_rect R_rect T_velo_to_cam``);
            it differs from ``Calibration.velo_to_rect_cam()`` (camera 0's rectified
            frame) by camera 2's 0.54 m stereo baseline.
        source: where it was read from (for messages).
    """

    K: np.ndarray
    T_cam_lidar: np.ndarray
    distortion: np.ndarray | None = None
    image_size: tuple[int, int] | None = None
    kitti: Calibration | None = None
    source: str = "calibration"

    def __post_init__(self) -> None:
        if self.image_size is not None:
            self.image_size = _check_size(self.image_size, self.name("image_size"))
        self.K = check_intrinsics(self.K, self.name("K"), self.image_size)
        self.T_cam_lidar = check_rigid(self.T_cam_lidar, self.name("T_cam_lidar"))
        if self.distortion is not None:
            self.distortion = check_distortion(self.distortion, self.K, self.image_size, self.name("distortion"))

    def name(self, key: str) -> str:
        """The user's name of an entry: ``T_cam_lidar`` (``source="arguments"``: given as an argument),
        ``calibration.T_cam_lidar`` (``source="calibration"``: of an object the caller built) or
        ``T_cam_lidar (rig.yaml)`` (read from that file)."""
        if self.source == "arguments":
            return key
        return f"calibration.{key}" if self.source == "calibration" else f"{key} ({self.source})"

    @classmethod
    def from_kitti(cls, calib: Calibration, source: str = "KITTI calibration") -> RigCalibration:
        """The rig view of a KITTI :class:`Calibration` (see ``kitti`` above)."""
        K = calib.P_rect[:, :3].copy()
        offset = np.eye(4)
        offset[:3, 3] = np.linalg.solve(K, calib.P_rect[:, 3])
        return cls(K=K, T_cam_lidar=offset @ calib.velo_to_rect_cam(), distortion=None,
                   image_size=calib.image_size, kitti=calib, source=source)


def _check_size(value, what: str) -> tuple[int, int]:
    try:
        height, width = (int(v) for v in value)
        valid = height > 0 and width > 0 and [float(v) for v in value] == [height, width]
    except (TypeError, ValueError, OverflowError):
        valid = False
    if not valid:
        raise InputError(f"{what}: expected [height, width] as two positive integers (pixels), got {quote_value(value)}")
    return height, width


# --------------------------------------------------------------------------- KITTI files


def _check_camera(camera: int) -> int:
    if isinstance(camera, bool) or not isinstance(camera, (int, np.integer)) or not 0 <= camera <= 3:
        raise InputError(f"camera: expected one of 0, 1, 2, 3 (KITTI camera index), got {camera!r}")
    return int(camera)


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
    cam_path = check_input_file(day_dir / _RAW_CAM_TO_CAM, "calibration")
    velo_path = check_input_file(day_dir / _RAW_VELO_TO_CAM, "calibration")
    cam = read_key_values(cam_path, "calibration")
    velo = read_key_values(velo_path, "calibration")

    width, height = entry_array(cam, f"S_rect_0{camera}", (2,), cam_path)
    T = np.eye(4)
    T[:3, :3] = entry_array(velo, "R", (3, 3), velo_path)
    T[:3, 3] = entry_array(velo, "T", (3,), velo_path)
    check_rigid(T, f"calibration: keys 'R', 'T' in {velo_path}")
    return Calibration(
        P_rect=entry_array(cam, f"P_rect_0{camera}", (3, 4), cam_path),
        R_rect=check_rigid(_pad_rotation(entry_array(cam, "R_rect_00", (3, 3), cam_path)),
                           f"calibration: key 'R_rect_00' in {cam_path}"),
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
    path = check_input_file(path, "calibration")
    entries = read_key_values(path, "calibration")
    P_rect = entry_array(entries, f"P{camera}", (3, 4), path)
    R_rect = check_rigid(_pad_rotation(entry_array(entries, "R0_rect", (3, 3), path)), f"calibration: key 'R0_rect' in {path}")
    T = check_rigid(_pad_transform(entry_array(entries, "Tr_velo_to_cam", (3, 4), path)),
                    f"calibration: key 'Tr_velo_to_cam' in {path}")
    return Calibration(P_rect=P_rect, R_rect=R_rect, T_velo_to_cam=T, image_size=None)


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
    path = check_input_file(path, "calibration")
    if path.name in (_RAW_CAM_TO_CAM, _RAW_VELO_TO_CAM):
        return read_raw_calibration(path.parent, camera)
    keys = read_key_values(path, "calibration").keys()
    if "R_rect_00" in keys or ({"R", "T"} <= keys and "Tr_velo_to_cam" not in keys):
        return read_raw_calibration(path.parent, camera)
    return read_object_calibration(path, camera)


# --------------------------------------------------------------------------- rig files


def read_rig_calibration(path: PathLike) -> RigCalibration:
    """Read a rig calibration YAML / JSON file (format in the module docstring).

    Keys: ``K`` (required), ``T_cam_lidar`` (required), ``distortion`` and
    ``image_size`` (optional, may be null). Unknown keys are an error (a typo such as
    ``distorsion`` would otherwise be silently ignored), and so is a key given twice
    (anywhere in the file: PyYAML and ``json`` would keep the last silently).

    Raises:
        FileNotFoundError: ``path`` does not exist.
        IsADirectoryError: ``path`` is a folder.
        InputError: not a regular file (``/dev/zero``, a FIFO), larger than
            ``MAX_CALIBRATION_BYTES`` (1 MiB), binary, not YAML/JSON, YAML anchors, aliases or
            too deep or large (:func:`crfdepth.io.key_values.read_mapping`), a key given twice,
            not a mapping, a key missing or unknown, or a value failing the checks of
            :class:`RigCalibration`.
    """
    path = check_input_file(path, "calibration")
    text = read_text(path, "calibration", "a YAML/JSON rig calibration (K, T_cam_lidar)",
                     max_bytes=MAX_CALIBRATION_BYTES)
    data = read_mapping(text, path, "JSON" if path.suffix.lower() == ".json" else "YAML")
    if not isinstance(data, dict):
        raise InputError(f"calibration: {path}: expected a mapping with keys K and T_cam_lidar, got "
                         f"{type(data).__name__}")
    known = {"K", "T_cam_lidar", "distortion", "image_size"}
    missing = [key for key in ("K", "T_cam_lidar") if key not in data]
    if missing:
        raise InputError(f"calibration: {path}: missing key(s) {', '.join(missing)} (keys present: "
                         f"{list_keys(data) or 'none'})")
    unknown = sorted(str(key) for key in data if key not in known)
    if unknown:
        raise InputError(f"calibration: {path}: unknown key(s) {list_keys(unknown)}; expected "
                         f"K, T_cam_lidar, distortion, image_size")
    return RigCalibration(K=data["K"], T_cam_lidar=data["T_cam_lidar"], distortion=data.get("distortion"),
                          image_size=data.get("image_size"), source=str(path))


def load_any_calibration(path: PathLike, camera: int = 2) -> RigCalibration:
    """Read a rig YAML/JSON file or any KITTI calibration into a :class:`RigCalibration`.

    Args:
        path: ``.yaml`` / ``.yml`` / ``.json`` rig file (:func:`read_rig_calibration`); or
            a KITTI raw-data day folder, one of its ``calib_*.txt`` files, or an object
            benchmark ``calib/*.txt`` (:func:`load_calibration`). A file of another name
            (``rig.txt``, ``rig``) is told by its content (:func:`is_rig_file`): a top-level
            ``K`` or ``T_cam_lidar`` key makes it a rig file, else it is read as KITTI.
        camera: KITTI camera index 0-3 (2 = left colour); ignored for rig files.

    Returns:
        :class:`RigCalibration`; for KITTI its ``kitti`` attribute holds the original
        calibration and :func:`crfdepth.geometry.projection.project_points` reproduces
        ``project_velodyne``.
    """
    path = Path(path)
    if path.suffix.lower() in RIG_SUFFIXES or is_rig_file(path):
        return read_rig_calibration(path)
    return RigCalibration.from_kitti(load_calibration(path, camera), source=str(path))

