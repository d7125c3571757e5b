"""From the user's arrays to the model's inputs: the image as RGB in [0, 1], a sparse depth map
checked as metres, and a point cloud projected into the image with its calibration (docs/design.md
section 1).

Every input is checked here, at the public boundary, and refused with an
:class:`~crfdepth.errors.InputError` naming the argument (docs/design.md section 8): besides
shapes and ranges, a ``K`` that does not fit the image, a sparse map that is not in metres
(:func:`crfdepth.plausibility.check_sparse_plausible`), points in millimetres, returns nearer
than 1 mm or beyond 1000 m (:func:`crfdepth.checks.check_return_depths`), meta tensors and a
``T_cam_lidar`` that looks inverted (unless ``trust_transform=True``, :func:`points_to_sparse`).
"""

from __future__ import annotations

import warnings

import numpy as np
import torch

from crfdepth.checks import check_has_data, check_return_depths
from crfdepth.errors import InputError
from crfdepth.geometry.projection import ground_normal, ground_tilt_deg, project_points
from crfdepth.intrinsics import check_intrinsics
from crfdepth.io.calibration import Calibration, RigCalibration
from crfdepth.plausibility import MAX_LIDAR_DEPTH_M, check_sparse_plausible

__all__ = [
    "InvertedTransform",
    "checked_points_to_sparse",
    "image_to_numpy",
    "no_points_message",
    "points_to_sparse",
    "prepare_points",
    "sparse_to_numpy",
]

# A projected LiDAR map whose median depth exceeds this is in the wrong unit (millimetres).
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
        array = image.detach().cpu()
        if array.ndim == 3 and array.shape[0] == 3 and array.shape[-1] != 3:
            array = array.permute(1, 2, 0)
        array = array.numpy()
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
    if not np.all(np.isfinite(array)) or array.min() < 0 or array.max() > 1:
        raise InputError(f"image: expected float RGB in [0, 1], got values in [{np.nanmin(array):.4g}, "
                         f"{np.nanmax(array):.4g}]{' with NaN/inf' if not np.all(np.isfinite(array)) else ''} "
                         f"(divide a 0-255 float image by 255)")
    return array.astype(np.float32), is_tensor, device


def sparse_to_numpy(sparse, size: tuple[int, int], K=None) -> np.ndarray:
    """``sparse`` as an (H, W) numpy map in metres, checked (with ``K``, the image's intrinsics, for the
    plausibility check :func:`crfdepth.plausibility.check_sparse_plausible`; then every return within
    [1 mm, 1000 m], :func:`crfdepth.checks.check_return_depths`); its dtype is kept, the model's is applied
    where the frame becomes tensors (:mod:`crfdepth.api`)."""
    check_has_data("sparse", sparse)
    array = sparse.detach().cpu().numpy() if isinstance(sparse, torch.Tensor) else np.asarray(sparse)
    if array.ndim == 3 and array.shape[0] == 1:
        array = array[0]
    if array.shape != size:
        raise InputError(f"sparse: expected an (H, W) = {size} depth map in metres (the image's size), got shape "
                         f"{array.shape}")
    if not np.issubdtype(array.dtype, np.floating) and not np.issubdtype(array.dtype, np.integer):
        raise InputError(f"sparse: expected depth in metres as numbers, got dtype {array.dtype}")
    if not np.all(np.isfinite(array)) or array.min() < 0:
        raise InputError("sparse: expected finite depth >= 0 metres (0 = no LiDAR point), got NaN, inf or "
                         "negative values")
    if not np.any(array > 0):
        raise InputError("sparse: every pixel is 0 (no LiDAR point); the CRF needs at least one depth measurement")
    check_sparse_plausible("sparse", array, K)
    check_return_depths("sparse", array)
    return array


def prepare_points(points) -> np.ndarray:
    """(N, 3) float64 x y z of a point cloud, rows with NaN/inf dropped (with a warning).

    Args:
        points: (N, 3+) array or tensor, LiDAR frame, metres; columns after the third
            (intensity, ring, time...) are ignored. Not modified. More than
            ``MAX_POINT_COLUMNS`` (16) columns is refused as a probably transposed array.

    Raises:
        InputError: a meta tensor, not 2-D, fewer than 3 columns, not real numbers, or no finite row.
    """
    check_has_data("points", points)
    array = points.detach().cpu().numpy() if isinstance(points, torch.Tensor) else np.asarray(points)
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


def no_points_message(points: np.ndarray, calibration: RigCalibration, image_size: tuple[int, int]) -> str:
    """Explain why no point of ``points`` lands in the image, with the usual causes."""
    T = calibration.T_cam_lidar
    cam = points[:, :3] @ T[:3, :3].T + T[:3, 3]
    front = int(np.sum(cam[:, 2] > 0))
    median_range = float(np.median(np.linalg.norm(points[:, :3], axis=1)))
    causes = ["T_cam_lidar given in the opposite direction (it must map LiDAR points into the camera frame; "
              "try its inverse)",
              "point coordinates in millimetres instead of metres" + (
                  f" (median range here {median_range:.4g}: that looks like millimetres)"
                  if median_range > 500 else ""),
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
            ``MAX_PLAUSIBLE_MEDIAN_DEPTH_M`` (300 m: points in millimetres); a projected
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
        raise InputError(f"points: expected coordinates in metres (a median depth of at most "
                         f"{MAX_PLAUSIBLE_MEDIAN_DEPTH_M:g} m), got a median projected depth of {median:.4g} m; the "
                         f"point coordinates look like millimetres: divide them by 1000")
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
    return sparse
