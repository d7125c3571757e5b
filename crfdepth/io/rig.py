"""Calibration of your own camera + LiDAR rig, and one loader for every format (DESIGN.md section 1).

A rig calibration is a small YAML (``.yaml`` / ``.yml``) or JSON (``.json``) file::

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

:func:`load_any_calibration` also reads KITTI calibration (a raw-data day folder, one
of its two files, or an object-benchmark ``calib/*.txt``) and returns the same
:class:`RigCalibration`, so callers need not care which kind they were given.

Checks (each an :class:`crfdepth.errors.InputError` naming the file and the key):
``K`` finite, focal lengths > 0, last row 0 0 1; ``T_cam_lidar`` finite, last row
0 0 0 1 and rotation orthonormal with determinant +1 within 1e-3 (a transform in
millimetres still passes this check: its rotation is fine; it is caught when no point
lands in the image); ``distortion`` 4, 5, 8, 12 or 14 finite numbers; ``image_size`` two
positive integers; the principal point no further outside the image than half its size.
"""

from __future__ import annotations

import json
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import yaml

from crfdepth.errors import InputError
from crfdepth.io.kitti import Calibration, load_calibration

__all__ = ["RigCalibration", "check_intrinsics", "check_rigid", "load_any_calibration", "read_rig_calibration"]

PathLike = str | os.PathLike
RIG_SUFFIXES = (".yaml", ".yml", ".json")
RIGID_TOLERANCE = 1e-3
_DISTORTION_LENGTHS = (4, 5, 8, 12, 14)  # the lengths OpenCV accepts


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
        kitti: the KITTI :class:`~crfdepth.io.kitti.Calibration` this came from, or None.
            When set, :meth:`project` uses :func:`crfdepth.projection.project_velodyne`
            (``P_rect R_rect T_velo_to_cam``) exactly, so results match the KITTI tools
            bit for bit. Here ``K = P_rect[:, :3]`` and ``T_cam_lidar`` is the transform
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
            self.image_size = _check_size(self.image_size, f"image_size ({self.source})")
        self.K = check_intrinsics(self.K, f"K ({self.source})", self.image_size)
        self.T_cam_lidar = check_rigid(self.T_cam_lidar, f"T_cam_lidar ({self.source})")
        if self.distortion is not None:
            self.distortion = _check_distortion(self.distortion, f"distortion ({self.source})")

    def project(self, points: np.ndarray, image_size: tuple[int, int]) -> np.ndarray:
        """Z-buffer projection of LiDAR points into an (H, W) float32 sparse depth (metres, 0 = none).

        KITTI: :func:`~crfdepth.projection.project_velodyne`; otherwise
        :func:`~crfdepth.projection.project_to_depth` with ``K [I | 0] T_cam_lidar``.
        ``points`` is (N, 3+) in the LiDAR frame, metres; extra columns are ignored.
        """
        from crfdepth.projection import project_to_depth, project_velodyne

        if self.kitti is not None:
            return project_velodyne(points, self.kitti, image_size)
        points = np.asarray(points)
        xyz = points[:, :3].astype(np.float64)
        return project_to_depth(xyz @ self.T_cam_lidar[:3, :3].T + self.T_cam_lidar[:3, 3], self.K, image_size)

    @classmethod
    def from_kitti(cls, calib: Calibration, source: str = "KITTI calibration") -> RigCalibration:
        """The rig view of a KITTI :class:`~crfdepth.io.kitti.Calibration` (see ``kitti`` above)."""
        K = calib.P_rect[:, :3].copy()
        offset = np.eye(4)
        offset[:3, 3] = np.linalg.solve(K, calib.P_rect[:, 3])
        return cls(K=K, T_cam_lidar=offset @ calib.velo_to_rect_cam(), distortion=None,
                   image_size=calib.image_size, kitti=calib, source=source)


# --------------------------------------------------------------------------- checks


def _as_matrix(value, shape: tuple[int, int], what: str, allow_flat: bool) -> np.ndarray:
    try:
        array = np.array(value, dtype=np.float64)
    except (TypeError, ValueError):
        raise InputError(f"{what}: expected a {shape[0]}x{shape[1]} matrix of numbers, got {value!r:.80}") from None
    if allow_flat and array.shape == (shape[0] * shape[1],):
        array = array.reshape(shape)
    if array.shape != shape:
        flat = f" or {shape[0] * shape[1]} numbers (row-major)" if allow_flat else ""
        raise InputError(f"{what}: expected a {shape[0]}x{shape[1]} nested list{flat}, got shape {array.shape}")
    if not np.all(np.isfinite(array)):
        raise InputError(f"{what}: expected finite numbers, got {array.ravel().tolist()}")
    return array


def check_intrinsics(K, what: str = "K", image_size: tuple[int, int] | None = None) -> np.ndarray:
    """(3, 3) float64 copy of ``K`` after checking it is a plausible pinhole matrix.

    Accepts a 3x3 nested list/array or 9 numbers (row-major). Requires finite values,
    ``fx = K[0,0] > 0``, ``fy = K[1,1] > 0``, last row 0 0 1 and, when ``image_size`` =
    (height, width) is given, the principal point within half an image of the image
    (``-W/2 <= cx <= 1.5 W``, same for cy): further out almost always means K belongs to
    another resolution or has cx and cy swapped. InputError naming ``what`` otherwise.
    """
    K = _as_matrix(K, (3, 3), what, allow_flat=True)
    if K[0, 0] <= 0 or K[1, 1] <= 0:
        raise InputError(f"{what}: expected focal lengths fx = K[0][0] > 0 and fy = K[1][1] > 0 (pixels), got "
                         f"fx={K[0, 0]:g}, fy={K[1, 1]:g}")
    if not np.allclose(K[2], (0.0, 0.0, 1.0)):
        raise InputError(f"{what}: expected the last row of K to be 0 0 1, got {' '.join(f'{v:g}' for v in K[2])}")
    if image_size is not None:
        height, width = image_size
        cx, cy = K[0, 2], K[1, 2]
        if not (-0.5 * width <= cx <= 1.5 * width and -0.5 * height <= cy <= 1.5 * height):
            raise InputError(f"{what}: principal point (cx, cy) = ({cx:g}, {cy:g}) px is far outside the "
                             f"{width}x{height} (WxH) image; K probably belongs to another image size (scale "
                             f"K with the image after a resize/crop) or cx and cy are swapped")
    return K


def check_rigid(T, what: str = "T_cam_lidar", tolerance: float = RIGID_TOLERANCE) -> np.ndarray:
    """(4, 4) float64 copy of ``T`` after checking it is a rigid transform.

    Requires finite values, last row 0 0 0 1, ``R^T R = I`` (max abs deviation <=
    ``tolerance``) and ``det R > 0`` (a rotation, not a reflection). A scaled rotation
    (e.g. a transform meant for millimetre points) fails the orthonormality test.
    """
    T = _as_matrix(T, (4, 4), what, allow_flat=False)
    if np.max(np.abs(T[3] - (0.0, 0.0, 0.0, 1.0))) > tolerance:
        raise InputError(f"{what}: expected the last row of a rigid 4x4 transform to be 0 0 0 1, got "
                         f"{' '.join(f'{v:g}' for v in T[3])}")
    R = T[:3, :3]
    deviation = float(np.max(np.abs(R.T @ R - np.eye(3))))
    if deviation > tolerance:
        raise InputError(f"{what}: the rotation part T[:3, :3] is not orthonormal (max |R^T R - I| = "
                         f"{deviation:.3g} > {tolerance:g}); expected a rigid transform (rotation + translation "
                         f"in metres), not a projection, a scaled or a hand-typed rotation (check for typos "
                         f"and for too few digits)")
    if np.linalg.det(R) < 0:
        raise InputError(f"{what}: the rotation part has determinant {np.linalg.det(R):.3g} < 0 (a reflection); "
                         f"an axis is flipped: check the axis conventions of both frames")
    return T


def _check_distortion(value, what: str) -> np.ndarray:
    try:
        array = np.array(value, dtype=np.float64).ravel()
    except (TypeError, ValueError):
        raise InputError(f"{what}: expected a list of numbers (OpenCV k1 k2 p1 p2 [k3 ...]), got {value!r:.80}") \
            from None
    if array.size not in _DISTORTION_LENGTHS or not np.all(np.isfinite(array)):
        raise InputError(f"{what}: expected {', '.join(map(str, _DISTORTION_LENGTHS))} finite numbers (OpenCV "
                         f"k1 k2 p1 p2 [k3 [k4 k5 k6 [s1 s2 s3 s4 [tx ty]]]]), got {array.tolist()}")
    return array


def _check_size(value, what: str) -> tuple[int, int]:
    try:
        height, width = (int(v) for v in value)
        valid = height > 0 and width > 0 and [float(v) for v in value] == [height, width]
    except (TypeError, ValueError):
        valid = False
    if not valid:
        raise InputError(f"{what}: expected [height, width] as two positive integers (pixels), got {value!r}")
    return height, width


# --------------------------------------------------------------------------- files


def read_rig_calibration(path: PathLike) -> RigCalibration:
    """Read a rig calibration YAML / JSON file (format in the module docstring).

    Keys: ``K`` (required), ``T_cam_lidar`` (required), ``distortion`` and
    ``image_size`` (optional, may be null). Unknown keys are an error (a typo such as
    ``distorsion`` would otherwise be silently ignored).

    Raises:
        FileNotFoundError: ``path`` does not exist.
        InputError: not YAML/JSON, not a mapping, a key missing or unknown, or a value
            failing the checks of :class:`RigCalibration`.
    """
    path = Path(path)
    if not path.exists():
        raise FileNotFoundError(f"calibration: no such file: {path}")
    if path.is_dir():
        raise IsADirectoryError(f"calibration: expected a YAML/JSON file, got a directory: {path}")
    text = path.read_text(errors="replace")
    try:
        data = json.loads(text) if path.suffix.lower() == ".json" else yaml.safe_load(text)
    except (json.JSONDecodeError, yaml.YAMLError) as exc:
        kind = "JSON" if path.suffix.lower() == ".json" else "YAML"
        raise InputError(f"calibration: {path} is not valid {kind}: {str(exc).splitlines()[0]}") from None
    if not isinstance(data, dict):
        raise InputError(f"calibration: {path}: expected a mapping with keys K and T_cam_lidar, got "
                         f"{type(data).__name__}")
    known = {"K", "T_cam_lidar", "distortion", "image_size"}
    missing = [key for key in ("K", "T_cam_lidar") if key not in data]
    if missing:
        raise InputError(f"calibration: {path}: missing key(s) {', '.join(missing)} (keys present: "
                         f"{', '.join(map(str, data)) or 'none'})")
    unknown = sorted(str(key) for key in data if key not in known)
    if unknown:
        raise InputError(f"calibration: {path}: unknown key(s) {', '.join(unknown)}; expected "
                         f"K, T_cam_lidar, distortion, image_size")
    return RigCalibration(K=data["K"], T_cam_lidar=data["T_cam_lidar"], distortion=data.get("distortion"),
                          image_size=data.get("image_size"), source=str(path))


def load_any_calibration(path: PathLike, camera: int = 2) -> RigCalibration:
    """Read a rig YAML/JSON file or any KITTI calibration into a :class:`RigCalibration`.

    Args:
        path: ``.yaml`` / ``.yml`` / ``.json`` rig file (:func:`read_rig_calibration`); or
            a KITTI raw-data day folder, one of its ``calib_*.txt`` files, or an object
            benchmark ``calib/*.txt`` (:func:`crfdepth.io.kitti.load_calibration`).
        camera: KITTI camera index 0-3 (2 = left colour); ignored for rig files.

    Returns:
        :class:`RigCalibration`; for KITTI its ``kitti`` attribute holds the original
        calibration and :meth:`RigCalibration.project` reproduces ``project_velodyne``.
    """
    path = Path(path)
    if path.suffix.lower() in RIG_SUFFIXES:
        return read_rig_calibration(path)
    return RigCalibration.from_kitti(load_calibration(path, camera), source=str(path))
