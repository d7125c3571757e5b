"""From the user's arrays to the model's inputs: the image as RGB in [0, 1], a sparse depth map
checked as metres, and a point cloud projected into the image with its calibration (docs/design.md
section 1).

Every input is checked here, at the public boundary, and refused with an
:class:`~crfdepth.errors.InputError` naming the argument (docs/design.md section 8): besides
shapes and ranges, a ``K`` that does not fit the image, a sparse map that is not in metres
(:func:`crfdepth.plausibility.check_sparse_plausible`), points in centimetres or millimetres, returns nearer
than 1 mm or beyond 1000 m (:func:`crfdepth.checks.check_return_depths`), meta tensors and a
``T_cam_lidar`` that looks inverted (unless ``trust_transform=True``, :func:`points_to_sparse`).
"""

from __future__ import annotations

import warnings

import numpy as np
import torch

from crfdepth.checks import check_has_data, check_return_depths, nonfinite, to_numpy
from crfdepth.errors import InputError
from crfdepth.geometry.projection import ground_normal, ground_tilt_deg, project_points
from crfdepth.intrinsics import check_intrinsics
from crfdepth.io.calibration import Calibration, RigCalibration
from crfdepth.plausibility import (
    MAX_LIDAR_DEPTH_M,
    POINT_UNIT_HINTS,
    check_sparse_orientation,
    check_sparse_plausible,
    likely_units,
)

__all__ = [
    "InvertedTransform",
    "checked_points_to_sparse",
    "image_to_numpy",
    "no_points_message",
    "points_to_sparse",
    "prepare_points",
    "sparse_to_numpy",
    "structured_xyz",
]

# A projected LiDAR map whose median depth exceeds this is in the wrong unit (centimetres, millimetres).
MAX_PLAUSIBLE_MEDIAN_DEPTH_M = MAX_LIDAR_DEPTH_M
# Refuse T_cam_lidar as inverted when it tilts the LiDAR's ground more than INVERTED_MIN_TILT_DEG
# from level in the camera while its inverse keeps it within INVERTED_MAX_INVERSE_TILT_DEG.
INVERTED_MIN_TILT_DEG = 45.0
INVERTED_MAX_INVERSE_TILT_DEG = 30.0
# More columns than this is taken for a transposed (3|4, N) array rather than extra fields.
MAX_POINT_COLUMNS = 16


def image_to_numpy(image) -> tuple[np.ndarray, bool, torch.device | None]:
    """(H, W, 3) float32 RGB in [0, 1], whether the input was a tensor, and its device."""
    check_has_data("image", image)
    is_tensor = isinstance(image, torch.Tensor)
    device = image.device if is_tensor else None
    if is_tensor:
        array = image
        if array.ndim == 3 and array.shape[0] == 3 and array.shape[-1] != 3:
            array = array.permute(1, 2, 0)
        array = to_numpy(array)  # float16 / bfloat16 as float32, exactly
    elif isinstance(image, np.ndarray):
        array = image
    else:
        raise InputError(f"image: expected a numpy array (H, W, 3) or a tensor (3, H, W) / (H, W, 3), got "
                         f"{type(image).__name__}")
    if array.ndim != 3 or array.shape[2] != 3:
        expected = "(3, H, W) or (H, W, 3) tensor" if is_tensor else "(H, W, 3) RGB array"
        raise InputError(f"image: expected a {expected}, got shape {tuple(image.shape)}")
    if array.dtype == np.uint8:
        return array.astype(np.float32) / 255.0, is_tensor, device
    if not np.issubdtype(array.dtype, np.floating):
        raise InputError(f"image: expected uint8 (0-255) or float in [0, 1], got dtype {array.dtype}")
    bad = nonfinite(array, 2)
    if bad:  # NaN / inf: broken or missing pixels, not a scale to divide away
        raise InputError(f"image: expected float RGB in [0, 1] (finite values), got {bad}")
    if array.min() < 0 or array.max() > 1:
        raise InputError(f"image: expected float RGB in [0, 1], got values in [{array.min():.4g}, "
                         f"{array.max():.4g}]" + (" (divide a 0-255 float image by 255)" if array.max() > 1 else ""))
    return array.astype(np.float32), is_tensor, device


def sparse_to_numpy(sparse, size: tuple[int, int], K=None) -> np.ndarray:
    """``sparse`` as an (H, W) numpy map in metres, checked (with ``K``, the image's intrinsics, for the
    plausibility check :func:`crfdepth.plausibility.check_sparse_plausible`; then every return within
    [1 mm, 1000 m], :func:`crfdepth.checks.check_return_depths`; a map that looks upside down is warned about,
    :func:`crfdepth.plausibility.check_sparse_orientation`); its dtype is kept, the model's is applied
    where the frame becomes tensors (:mod:`crfdepth.api`)."""
    check_has_data("sparse", sparse)
    array = to_numpy(sparse) if isinstance(sparse, torch.Tensor) else np.asarray(sparse)
    if array.ndim == 3 and array.shape[0] == 1:
        array = array[0]
    if array.shape != size:
        raise InputError(f"sparse: expected an (H, W) = {size} depth map in metres (the image's size), got shape "
                         f"{array.shape}")
    if not np.issubdtype(array.dtype, np.floating) and not np.issubdtype(array.dtype, np.integer):
        raise InputError(f"sparse: expected depth in metres as numbers, got dtype {array.dtype}")
    bad = nonfinite(array)
    if bad or array.min() < 0:
        raise InputError(f"sparse: expected finite depth >= 0 metres (0 = no LiDAR point), got "
                         f"{bad or f'negative values (minimum {array.min():.4g} at {int((array < 0).sum())} pixel(s))'}")
    if not np.any(array > 0):
        raise InputError("sparse: every pixel is 0 (no LiDAR point); the CRF needs at least one depth measurement")
    check_sparse_plausible("sparse", array, K)
    check_return_depths("sparse", array)
    check_sparse_orientation("sparse", array)  # a warning: an upside-down map passes every check above
    return array


def prepare_points(points) -> np.ndarray:
    """(N, 3) float64 x y z of a point cloud, rows with NaN/inf dropped (with a warning).

    Args:
        points: (N, 3+) array or tensor, LiDAR frame, metres; columns after the third
            (intensity, ring, time...) are ignored. Not modified. More than
            ``MAX_POINT_COLUMNS`` (16) columns is refused as a probably transposed array. A
            structured or record array (pypcd4, ROS) gives its fields x, y, z (:func:`structured_xyz`).

    Raises:
        InputError: a meta tensor, not 2-D, fewer than 3 columns, not real numbers, or no finite row.
    """
    check_has_data("points", points)
    array = to_numpy(points) if isinstance(points, torch.Tensor) else np.asarray(points)
    if array.dtype.names is not None:
        array = structured_xyz(array)
    if array.ndim != 2 or not 3 <= array.shape[1] <= MAX_POINT_COLUMNS:
        raise InputError(f"points: expected an (N, 3) or (N, 4) array (x y z [intensity], metres; further "
                         f"columns, up to {MAX_POINT_COLUMNS} in all, are ignored), got shape {array.shape}"
                         + (" (transpose it: the points go in rows)" if array.ndim == 2 and array.shape[0] in (3, 4)
                            else ""))
    if not np.issubdtype(array.dtype, np.number) or np.issubdtype(array.dtype, np.complexfloating):
        raise InputError(f"points: expected real coordinates, got dtype {array.dtype}")
    xyz = array[:, :3].astype(np.float64)
    finite = np.isfinite(xyz).all(axis=1)
    dropped = int(xyz.shape[0] - finite.sum())
    if dropped:
        warnings.warn(f"points: dropped {dropped} of {xyz.shape[0]} point(s) with NaN or infinite coordinates "
                      f"(no-return placeholders of an organised cloud?)", UserWarning, stacklevel=3)
        xyz = xyz[finite]
    if xyz.shape[0] == 0:
        raise InputError(f"points: no point with finite coordinates (got {array.shape[0]} row(s))")
    return xyz


def structured_xyz(array: np.ndarray) -> np.ndarray:
    """The (N, 3) x y z columns of a structured (or record) point array, the layout of ``pypcd4`` and of
    ROS ``PointCloud2`` readers: fields ``x``, ``y``, ``z`` (any case) of real numbers, other fields
    (intensity, ring, time...) ignored; an organised (H, W) cloud is taken row by row.

    Raises:
        InputError: a field x, y or z is missing or not a single real number per point.
    """
    fields = {name.lower(): name for name in array.dtype.names}
    missing = [axis for axis in "xyz" if axis not in fields]
    how = "np.stack([a['x'], a['y'], a['z']], -1)"
    if missing:
        raise InputError(f"points: expected a structured array with fields x, y, z (metres) or an (N, 3) array, "
                         f"got fields {', '.join(array.dtype.names)} (no {', '.join(missing)}); build the (N, 3) "
                         f"array yourself, e.g. {how}")
    columns = [array[fields[axis]] for axis in "xyz"]
    for axis, column in zip("xyz", columns):
        if column.dtype.shape or not np.issubdtype(column.dtype, np.number) or \
                np.issubdtype(column.dtype, np.complexfloating):
            raise InputError(f"points: expected field {axis} of real numbers, one per point, got dtype "
                             f"{column.dtype}; build the (N, 3) array yourself, e.g. {how}")
    return np.stack([np.asarray(c, dtype=np.float64).reshape(-1) for c in columns], axis=-1)


def _range_units(median_range: float) -> str:
    """Centimetres and millimetres, the likelier first for a point cloud of this median range (metres as
    read): the one that brings it closer to a typical 10 m."""
    words = {100.0: "centimetres (divide by 100)", 1000.0: "millimetres (divide by 1000)"}
    order = sorted(words, key=lambda factor: abs(np.log(median_range / factor / 10.0)))
    return " or ".join(words[f] for f in order)


def no_points_message(points: np.ndarray, calibration: RigCalibration, image_size: tuple[int, int]) -> str:
    """Explain why no point of ``points`` lands in the image, with the usual causes."""
    T = calibration.T_cam_lidar
    cam = points[:, :3] @ T[:3, :3].T + T[:3, 3]
    front = int(np.sum(cam[:, 2] > 0))
    median_range = float(np.median(np.linalg.norm(points[:, :3], axis=1)))
    causes = ["T_cam_lidar given in the opposite direction (it must map LiDAR points into the camera frame; "
              "try its inverse)",
              "point coordinates in centimetres or millimetres instead of metres" + (
                  f" (median range here {median_range:.4g}: that looks like "
                  f"{_range_units(median_range)})" if median_range > 500 else ""),
              "the calibration of another camera, or K for another image size",
              "camera axes not x right, y down, z forward (e.g. a ROS body-frame transform)"]
    height, width = image_size
    return (f"no point lands in the {width}x{height} (WxH) image: {points.shape[0]} point(s), {front} in front of "
            f"the camera (z > 0), 0 inside the image. Usual causes: " + "; ".join(f"({i + 1}) {c}" for i, c in
                                                                                enumerate(causes)))


def points_to_sparse(points, calibration: RigCalibration | Calibration, image_size: tuple[int, int], *,
                     trust_transform: bool = False) -> np.ndarray:
    """Project a point cloud into an (H, W) float32 sparse depth map (metres, 0 = no point).

    NaN rows are dropped with a warning (:func:`prepare_points`); KITTI calibrations use
    the exact KITTI projection (:func:`crfdepth.geometry.projection.project_points`).

    A 360-degree scan lands points in the image even with an inverted ``T_cam_lidar``
    (counts do not tell: on the docs/example rig the inverse lands 1.2x *more* points).
    What tells is the ground: the LiDAR's ground plane (:func:`crfdepth.geometry.projection.ground_normal`,
    the plane below the sensor with the most returns whose normal is within 30 degrees of
    the LiDAR's +z) must appear level under the camera. The rotation of ``T_cam_lidar``
    maps its up-normal into the camera (:func:`crfdepth.geometry.projection.ground_tilt_deg`: the
    angle to the camera's up, -y); the inverse transform's rotation is the transpose, which
    sends up to another camera axis (with the usual axes, LiDAR x forward / z up and camera z
    forward / y down: to camera x, a ground standing as a wall beside the camera). The
    transform is refused when it tilts the ground more than ``INVERTED_MIN_TILT_DEG`` (45)
    degrees while its inverse keeps it within ``INVERTED_MAX_INVERSE_TILT_DEG`` (30). A
    camera pitched or rolled by up to 45 degrees is accepted whatever its inverse does, and
    for any pitch or roll the inverse of such a rig tilts the ground by about 90 degrees,
    so a right transform is refused only for a camera tilted more than 45 degrees *and*
    turned about 90 degrees about another axis. Measured (the right transform / its
    inverse): shared KITTI raw scans of drives 0001 and 0060 and the 11 object frames, 64
    beams and every 4th ring (16 beams): 0.1-3.9 / 89.8-91.1 degrees; synthetic street
    seeds 0-5, 64 and 16 beams, and the docs/example rig: 0.4-0.8 / 89.8-90.3 degrees. No
    ground found (an indoor scan of walls, a LiDAR tilted over 30 degrees): nothing is
    refused. ``trust_transform=True`` skips the test.

    Args:
        points: (N, 3+) point cloud in the LiDAR frame, metres (see :func:`prepare_points`).
        calibration: :class:`~crfdepth.io.calibration.RigCalibration` (or a KITTI
            :class:`~crfdepth.io.calibration.Calibration`) of the camera.
        image_size: (height, width) of the image, pixels; K must fit it
            (:func:`crfdepth.intrinsics.check_intrinsics`).
        trust_transform: use ``T_cam_lidar`` even when it looks inverted (the ground test).

    Raises:
        InputError: ``K`` does not fit ``image_size``; no point lands in the image
            (:func:`no_points_message`); the median projected depth exceeds
            ``MAX_PLAUSIBLE_MEDIAN_DEPTH_M`` (300 m: points in centimetres or millimetres, the
            message names the likelier, :func:`crfdepth.plausibility.likely_units`); a projected
            depth below 1 mm or beyond 1000 m (:func:`crfdepth.checks.check_return_depths`); or
            ``T_cam_lidar`` looks inverted and ``trust_transform`` is False.
    """
    if not isinstance(trust_transform, bool):
        raise InputError(f"trust_transform: expected True or False, got {trust_transform!r}")
    if isinstance(calibration, Calibration):
        calibration = RigCalibration.from_kitti(calibration, source="calibration")
    if not isinstance(calibration, RigCalibration):
        raise InputError(f"calibration: expected a crfdepth.io.calibration.RigCalibration (load_any_calibration) "
                         f"or a KITTI Calibration, got {type(calibration).__name__}")
    check_intrinsics(calibration.K, calibration.name("K"), image_size)
    return checked_points_to_sparse(prepare_points(points), calibration, image_size, trust_transform)


class InvertedTransform(InputError):
    """The refusal of a ``T_cam_lidar`` that looks inverted (:func:`points_to_sparse`), with the fix in Python's
    words; :meth:`retold` gives it with another fix (the command line's ``--trust-transform``)."""

    PYTHON_FIX = "pass its inverse (np.linalg.inv), or trust_transform=True to use it as given"

    def __init__(self, finding: str, fix: str = PYTHON_FIX):
        super().__init__(f"{finding}; {fix}")
        self.finding = finding

    def retold(self, fix: str) -> InvertedTransform:
        """The same refusal with ``fix`` as its advice."""
        return InvertedTransform(self.finding, fix)


def checked_points_to_sparse(xyz: np.ndarray, calibration: RigCalibration, image_size: tuple[int, int],
                      trust_transform: bool) -> np.ndarray:
    """:func:`points_to_sparse` on checked inputs: (N, 3) float64 finite points."""
    sparse = project_points(xyz, calibration, image_size)
    if not np.any(sparse > 0):
        raise InputError(no_points_message(xyz, calibration, image_size))
    median = float(np.median(sparse[sparse > 0]))
    if median > MAX_PLAUSIBLE_MEDIAN_DEPTH_M:
        units = likely_units(sparse, calibration.K)  # 100x too deep: centimetres; 1000x: millimetres
        advice = ("the point coordinates look like " + "; or ".join(POINT_UNIT_HINTS[u] for u in units) if units
                  else "check the unit of the point coordinates (metres expected)")
        raise InputError(f"points: expected coordinates in metres (a median depth of at most "
                         f"{MAX_PLAUSIBLE_MEDIAN_DEPTH_M:g} m), got a median projected depth of {median:.4g} m; "
                         f"{advice}")
    check_return_depths("points", sparse)
    if not trust_transform:
        normal = ground_normal(xyz)
        if normal is not None:
            T = calibration.T_cam_lidar
            tilt, inverse = ground_tilt_deg(normal, T), ground_tilt_deg(normal, np.linalg.inv(T))
            if tilt > INVERTED_MIN_TILT_DEG and inverse < INVERTED_MAX_INVERSE_TILT_DEG:
                raise InvertedTransform(
                    f"{calibration.name('T_cam_lidar')}: expected the transform that maps LiDAR points "
                    f"into the camera frame (x right, y down, z forward), got one that looks inverted: it turns the "
                    f"scan's ground plane {tilt:.0f} degrees from level under the camera, its inverse {inverse:.0f} "
                    f"degrees")
    check_sparse_orientation(
        f"points / {calibration.name('T_cam_lidar')}", sparse,
        fix="T_cam_lidar must map into a camera frame with x right, y down, z forward (a camera frame with y up, "
            "as in OpenGL or a ROS body frame, turns the projection upside down: rotate it 180 degrees about z), or "
            "the image is upside down")
    return sparse
