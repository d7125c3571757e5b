"""One call from your own sensors to dense depth: :func:`complete_depth` (docs/design.md section 1).

Takes a camera image and either a sparse depth map or a raw LiDAR point cloud with its
calibration, projects the cloud (z-buffer, nearest point wins), runs
:class:`crfdepth.model.CRFDepth` and returns depth (and std) at the image's own
resolution. Any image size works: the superpixel count scales with the image area (the
model's ``scale_superpixels``), so a 640x480 phone frame gets superpixels of the same
pixel size as a KITTI frame.

With lens ``distortion`` the image is undistorted with ``cv2.undistort(image, K,
distortion)`` (new camera matrix = ``K``, so the undistorted image keeps the same
intrinsics; pixels that map from outside the raw image become black) and the points are
projected with that same ``K`` and no distortion.

Every input is checked here, at the public boundary, and refused with an
:class:`~crfdepth.errors.InputError` naming the argument (docs/design.md section 8):
besides shapes and ranges, a ``K`` that does not fit the image, a sparse map that is
not in metres (:func:`crfdepth.plausibility.check_sparse_plausible`) and a ``T_cam_lidar`` that
looks inverted (unless ``trust_transform=True``, :func:`points_to_sparse`).
"""

from __future__ import annotations

import copy
import logging
import warnings

import cv2
import numpy as np
import torch

from crfdepth.checkpoints import load_pretrained
from crfdepth.checks import check_intrinsics, check_rigid
from crfdepth.errors import InputError
from crfdepth.geometry.projection import ground_normal, ground_tilt_deg, project_points
from crfdepth.io.calibration import Calibration, RigCalibration
from crfdepth.memory import (
    check_frame_size,
    check_model_memory,
    estimate_bytes,
    is_out_of_memory,
    out_of_memory,
)
from crfdepth.plausibility import MAX_LIDAR_DEPTH_M, check_sparse_plausible

__all__ = ["check_frame", "complete_batch", "complete_depth", "no_points_message", "points_to_sparse", "prepare_points"]

logger = logging.getLogger(__name__)

# A projected LiDAR map whose median depth exceeds this is in the wrong unit (millimetres).
MAX_PLAUSIBLE_MEDIAN_DEPTH_M = MAX_LIDAR_DEPTH_M
# Refuse T_cam_lidar as inverted when it tilts the LiDAR's ground more than INVERTED_MIN_TILT_DEG
# from level in the camera while its inverse keeps it within INVERTED_MAX_INVERSE_TILT_DEG.
INVERTED_MIN_TILT_DEG = 45.0
INVERTED_MAX_INVERSE_TILT_DEG = 30.0
# More columns than this is taken for a transposed (3|4, N) array rather than extra fields.
MAX_POINT_COLUMNS = 16


# --------------------------------------------------------------------------- inputs


def _image_to_numpy(image) -> tuple[np.ndarray, bool, torch.device | None]:
    """(H, W, 3) float32 RGB in [0, 1], whether the input was a tensor, and its device."""
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


def _sparse_to_numpy(sparse, size: tuple[int, int], K=None) -> np.ndarray:
    """``sparse`` as an (H, W) float32 map in metres, checked (with ``K``, the image's intrinsics,
    for the plausibility check :func:`crfdepth.plausibility.check_sparse_plausible`)."""
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
    return array.astype(np.float32)


def check_frame(image, sparse, K) -> None:
    """Refuse a frame that :func:`complete_depth` would refuse for ``image``, ``sparse`` and ``K``,
    with its checks, messages and order: RGB not (3, H, W) / (H, W, 3) in [0, 1]; K not the
    intrinsics of an image of this size (:func:`crfdepth.checks.check_intrinsics`); sparse depth
    not finite, >= 0, with a return, or not plausibly metres of a LiDAR scene seen with this K
    (:func:`crfdepth.plausibility.check_sparse_plausible`: the hints say what to divide by)."""
    rgb, _, _ = _image_to_numpy(image)
    Kn = check_intrinsics(K, "K", rgb.shape[:2])
    _sparse_to_numpy(sparse, rgb.shape[:2], Kn)


def prepare_points(points) -> np.ndarray:
    """(N, 3) float64 x y z of a point cloud, rows with NaN/inf dropped (with a warning).

    Args:
        points: (N, 3+) array or tensor, LiDAR frame, metres; columns after the third
            (intensity, ring, time...) are ignored. Not modified. More than
            ``MAX_POINT_COLUMNS`` (16) columns is refused as a probably transposed array.

    Raises:
        InputError: not 2-D, fewer than 3 columns, not real numbers, or no finite row.
    """
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
            (:func:`crfdepth.checks.check_intrinsics`).
        trust_transform: use ``T_cam_lidar`` even when it looks inverted (the ground test).

    Raises:
        InputError: ``K`` does not fit ``image_size``; no point lands in the image
            (:func:`no_points_message`); the median projected depth exceeds
            ``MAX_PLAUSIBLE_MEDIAN_DEPTH_M`` (300 m: points in millimetres); or
            ``T_cam_lidar`` looks inverted and ``trust_transform`` is False.
    """
    if not isinstance(trust_transform, bool):
        raise InputError(f"trust_transform: expected True or False, got {trust_transform!r}")
    if isinstance(calibration, Calibration):
        calibration = RigCalibration.from_kitti(calibration, source="calibration")
    if not isinstance(calibration, RigCalibration):
        raise InputError(f"calibration: expected a crfdepth.io.calibration.RigCalibration (load_any_calibration) "
                         f"or a KITTI Calibration, got {type(calibration).__name__}")
    check_intrinsics(calibration.K, _named("K", calibration), image_size)
    return _points_to_sparse(prepare_points(points), calibration, image_size, trust_transform)


def _named(key: str, calibration: RigCalibration) -> str:
    """The user's name of a calibration entry: ``T_cam_lidar`` (given as an argument),
    ``calibration.T_cam_lidar`` (of a calibration object) or ``T_cam_lidar (rig.yaml)`` (read from a file)."""
    if calibration.source == "arguments":
        return key
    return f"calibration.{key}" if calibration.source == "calibration" else f"{key} ({calibration.source})"


def _points_to_sparse(xyz: np.ndarray, calibration: RigCalibration, image_size: tuple[int, int],
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
    if not trust_transform:
        normal = ground_normal(xyz)
        if normal is not None:
            T = calibration.T_cam_lidar
            tilt, inverse = ground_tilt_deg(normal, T), ground_tilt_deg(normal, np.linalg.inv(T))
            if tilt > INVERTED_MIN_TILT_DEG and inverse < INVERTED_MAX_INVERSE_TILT_DEG:
                raise InputError(
                    f"{_named('T_cam_lidar', calibration)}: expected the transform that maps LiDAR points into the "
                    f"camera frame (x right, y down, z forward), got one that looks inverted: it turns the scan's "
                    f"ground plane {tilt:.0f} degrees from level under the camera, its inverse {inverse:.0f} "
                    f"degrees; pass its inverse (np.linalg.inv), or trust_transform=True to use it as given")
    return sparse


# --------------------------------------------------------------------------- model


DEVICE_TYPES = ("cpu", "cuda", "mps")  # the devices the model runs on


def _device(device) -> torch.device:
    """``device`` as a torch.device the model can run on here, else an InputError naming ``device``."""
    here = ["'cpu'"] + ([f"'cuda' / 'cuda:0'..'cuda:{torch.cuda.device_count() - 1}'"] if torch.cuda.is_available()
                        else []) + (["'mps'"] if torch.backends.mps.is_available() else [])
    expected = f"'cpu', 'cuda', 'cuda:N' or 'mps' (a str or torch.device; available here: {', '.join(here)})"
    try:
        parsed = torch.device(device)
    except (RuntimeError, TypeError, ValueError):
        raise InputError(f"device: expected {expected}, got {device!r}") from None
    if parsed.type not in DEVICE_TYPES:
        raise InputError(f"device: expected {expected}, got {device!r}")
    if parsed.type == "cuda" and not torch.cuda.is_available():
        raise InputError("device: CUDA is not available in this PyTorch installation/machine; use device='cpu'")
    if parsed.type == "cuda" and parsed.index is not None and parsed.index >= torch.cuda.device_count():
        raise InputError(f"device: expected {expected}, got {device!r}: this machine has "
                         f"{torch.cuda.device_count()} CUDA device(s)")
    if parsed.type == "mps" and not torch.backends.mps.is_available():
        raise InputError(f"device: MPS is not available in this PyTorch installation/machine; expected {expected}")
    return parsed


def _model_on(model, device: str | torch.device):
    device = _device(device)
    if model is None:
        return load_pretrained().to(device)
    if not isinstance(model, torch.nn.Module):
        raise InputError(f"model: expected a crfdepth.model.CRFDepth (or None for the default), got "
                         f"{type(model).__name__}")
    param = next(model.parameters(), None)
    if param is not None and param.device != device and not (device.index is None and param.device.type == device.type):
        model = copy.deepcopy(model).to(device)  # the caller's model is left where it is
    return model


def _image_size(image) -> tuple[int, int] | None:
    """(height, width) of an image of an accepted layout from its shape alone (no conversion); None otherwise."""
    shape = tuple(getattr(image, "shape", ()))
    if not isinstance(image, (np.ndarray, torch.Tensor)) or len(shape) != 3:
        return None
    if isinstance(image, torch.Tensor) and shape[0] == 3 and shape[-1] != 3:
        return shape[1], shape[2]
    return (shape[0], shape[1]) if shape[2] == 3 else None


def complete_depth(image, *, sparse=None, points=None, T_cam_lidar=None, K=None,
                   calibration: RigCalibration | Calibration | None = None, distortion=None, model=None,
                   device: str | torch.device = "cpu", return_std: bool = True, trust_transform: bool = False,
                   trust_units: bool = False):
    """Dense depth (and std) for one camera image from sparse LiDAR or a raw point cloud.

    Give the camera either as ``K`` (+ ``T_cam_lidar`` for points, + optional
    ``distortion``) or as one ``calibration`` (:func:`crfdepth.io.calibration.load_any_calibration`:
    a rig YAML/JSON or KITTI calibration; KITTI keeps the exact KITTI projection
    ``P_rect R_rect T_velo_to_cam``), not both. Give the LiDAR either as ``sparse`` or as
    ``points``, not both.

    Args:
        image: RGB as a numpy (H, W, 3) uint8 (0-255) or float array in [0, 1], or a
            tensor (3, H, W) / (H, W, 3) of the same kinds. Any size.
        sparse: (H, W) sparse z-depth in metres (0 = no point), numpy or tensor, any
            real dtype. A map that is not plausibly metres of a LiDAR scene seen with ``K``
            is refused with the likely unit (:func:`crfdepth.plausibility.check_sparse_plausible`):
            the raw codes of a KITTI PNG (``cv2.imread(path, -1)``, metres * 256; use
            :func:`crfdepth.io.kitti.read_depth_png`), millimetres, centimetres, or a
            millimetre / whole-metre PNG read as metres * 256.
        points: (N, 3) or (N, 4) point cloud in the LiDAR frame, metres (extra columns,
            e.g. intensity, are ignored); rows with NaN/inf are dropped with a warning
            giving the count.
        T_cam_lidar: (4, 4) rigid transform mapping LiDAR points into the camera frame
            (x right, y down, z forward), metres; required with ``points`` and ``K``.
        K: (3, 3) pinhole intrinsics of ``image`` (pixels), or 9 numbers row-major.
        calibration: a :class:`~crfdepth.io.calibration.RigCalibration` (or a KITTI
            :class:`~crfdepth.io.calibration.Calibration`) instead of ``K`` /
            ``T_cam_lidar`` / ``distortion``; its ``image_size``, when set, must equal the
            image's.
        distortion: OpenCV coefficients k1 k2 p1 p2 [k3 ...] of the raw image, or None.
            When given, the image is undistorted (module docstring) and the output is
            the depth of the undistorted image.
        model: a :class:`~crfdepth.model.CRFDepth` (e.g. from
            :func:`crfdepth.load_model`, or ``CRFDepth.from_pretrained("paper")``
            for the hand-set weights); None = ``CRFDepth.from_pretrained()``, the weights
            learned on KITTI. Used in its current train/eval mode, under ``no_grad``; a
            model on another device is copied there (the caller's model is not moved).
        device: "cpu", "cuda", "cuda:N", "mps" or a torch.device for the computation
            (another value, or one this machine lacks, is refused naming ``device``).
        return_std: also return the standard deviation (the model's: predictive by default,
            docs/design.md section 5).
        trust_transform: with ``points``, use ``T_cam_lidar`` as given even when it looks
            inverted (it tilts the scan's ground plane far from level under the camera while
            its inverse keeps it level; otherwise refused, :func:`points_to_sparse`).
        trust_units: with ``sparse``, skip the plausibility rule that guesses the rig (the
            ground at most 4 m below the camera where the median depth exceeds 20 m): for a
            camera on a mast or a drone. The rules of the LiDAR's reach still apply.

    Returns:
        ``(depth, std)``: (H, W) float32 z-depth in metres, > 0 everywhere, and the
        std in metres (None when ``return_std`` is False). numpy arrays for a
        numpy image; tensors on the image tensor's device for a tensor image.

    Raises:
        InputError: bad shapes/dtypes/values (message names the argument), a sparse
            map not in metres, a non-rigid or inverted ``T_cam_lidar``, a ``K`` that does
            not fit the image (principal point far outside it), an image size different
            from the calibration's, or no point landing in the image (the message gives
            the point counts and the usual causes). First of all, from the image's shape
            alone: an image smaller than 2x2 pixels, or (:class:`crfdepth.memory.MemoryRefusal`)
            one whose estimated peak memory exceeds the memory available on ``device`` (or
            the model's ``memory_limit_gb``), refused before anything is converted; an
            allocator failure in the forward is turned into the same kind of error.
    """
    known = _image_size(image)
    if known is not None:  # size and memory from the shape alone, before any conversion allocates
        model = _model_on(model, device)
        check_frame_size("image", *known)
        check_model_memory(model, 1, *known, bool(return_std))
    rgb, is_tensor, out_device = _image_to_numpy(image)
    size = rgb.shape[:2]
    if not isinstance(trust_transform, bool):
        raise InputError(f"trust_transform: expected True or False, got {trust_transform!r}")
    if not isinstance(trust_units, bool):
        raise InputError(f"trust_units: expected True or False, got {trust_units!r}")
    if calibration is not None:
        given = [name for name, value in (("K", K), ("T_cam_lidar", T_cam_lidar), ("distortion", distortion))
                 if value is not None]
        if given:
            raise InputError(f"calibration: expected either calibration or K / T_cam_lidar / distortion, got both "
                             f"(calibration and {', '.join(given)})")
        if isinstance(calibration, Calibration):
            calibration = RigCalibration.from_kitti(calibration, source="calibration")
        if not isinstance(calibration, RigCalibration):
            raise InputError(f"calibration: expected a crfdepth.io.calibration.RigCalibration (load_any_calibration) "
                             f"or a KITTI Calibration, got {type(calibration).__name__}")
        if calibration.image_size is not None and tuple(calibration.image_size) != size:
            raise InputError(f"image: expected the size of the calibration ({calibration.source}), "
                             f"{calibration.image_size[1]}x{calibration.image_size[0]} (WxH), got {size[1]}x{size[0]}; "
                             f"resize/crop the image back or use the calibration of this image size (K scales "
                             f"with the image)")
        check_intrinsics(calibration.K, _named("K", calibration), size)
    else:
        if K is None:
            raise InputError("K: required: expected the 3x3 intrinsics of the image (or calibration=), got None")
        Kn = check_intrinsics(K, "K", size)
        if points is not None and T_cam_lidar is None:
            raise InputError("T_cam_lidar: required with points: expected the 4x4 LiDAR -> camera transform "
                             "(metres), got None")
        T = np.eye(4) if T_cam_lidar is None else check_rigid(T_cam_lidar, "T_cam_lidar")
        calibration = RigCalibration(K=Kn, T_cam_lidar=T, distortion=distortion, image_size=size, source="arguments")
    if (sparse is None) == (points is None):
        raise InputError(f"sparse / points: expected exactly one of them (a sparse depth map or a point cloud), "
                         f"got {'both' if sparse is not None else 'neither'}")
    if calibration.distortion is not None:
        rgb = cv2.undistort(rgb, calibration.K, calibration.distortion)
        if sparse is not None:
            logger.warning("distortion: the image is undistorted but a given sparse map is used as is; it must "
                           "already be projected with K and no distortion")
    if points is not None:
        sparse_np = _points_to_sparse(prepare_points(points), calibration, size, trust_transform)
    else:
        sparse_np = _sparse_to_numpy(sparse, size, None if trust_units else calibration.K)

    image_t = torch.from_numpy(np.ascontiguousarray(rgb.transpose(2, 0, 1)))[None]
    depth, std = complete_batch(image_t, torch.from_numpy(sparse_np)[None, None], torch.from_numpy(calibration.K),
                                model=model, device=device, return_std=return_std)
    depth, std = depth[0], (std[0] if std is not None else None)
    if is_tensor:
        return depth.to(out_device), (std.to(out_device) if std is not None else None)
    return depth.cpu().numpy(), (std.cpu().numpy() if std is not None else None)


def complete_batch(image: torch.Tensor, sparse: torch.Tensor, K: torch.Tensor, *, model=None,
                   device: str | torch.device = "cpu", return_std: bool = True
                   ) -> tuple[torch.Tensor, torch.Tensor | None]:
    """Depth (and std) of a batch of frames of one size in one model call: the model step of
    :func:`complete_depth`, for frames already in the library's tensor layout (the
    ``--input-dir`` and ``evaluate`` commands read them with DataLoader workers).

    The model checks its inputs (:func:`crfdepth.checks.check_frames`, names ``image``,
    ``sparse``, ``K``) and refuses a batch too large for the memory up front
    (:mod:`crfdepth.memory`). In a batch the frames' CG solves run together, each frozen
    once it has converged, so a frame's depth differs from its batch-of-one depth within
    the solver tolerance; a batch of one is :func:`complete_depth` bit for bit. An allocator
    failure in the forward (``DefaultCPUAllocator: can't allocate memory``,
    ``torch.cuda.OutOfMemoryError``) is raised as a one-line
    :class:`~crfdepth.memory.MemoryRefusal` naming ``image``.

    Args:
        image: (B, 3, H, W) RGB in [0, 1]; sparse: (B, 1, H, W) z-depth in metres, 0 = no
            point; K: (3, 3) or (B, 3, 3) intrinsics in pixels. Any device and float dtype:
            they are moved to the model's.
        model, device, return_std: as for :func:`complete_depth`.

    Returns:
        ``(depth, std)``: (B, H, W) float32 metres on the model's device (std None when
        ``return_std`` is False).
    """
    model = _model_on(model, device)
    param = next(model.parameters())
    failure = None
    with torch.no_grad():
        try:
            out = model(*(t.to(param.device, param.dtype) for t in (image, sparse, K)), return_std=return_std)
        except (RuntimeError, MemoryError) as exc:  # the last line of defence behind the up-front estimate
            if not is_out_of_memory(exc):
                raise
            failure = _allocator_failure(exc, model, sparse, return_std)
    if failure is not None:  # raised here, once the failed forward's tensors are released
        if param.device.type == "cuda":
            torch.cuda.empty_cache()
        raise failure
    return out.depth[:, 0].float(), (out.std[:, 0].float() if return_std else None)


def _allocator_failure(exc: BaseException, model, sparse, return_std: bool) -> InputError:
    """The one-line error for an allocator failure in ``model``'s forward of ``sparse``'s frames."""
    shape = tuple(sparse.shape)
    size = (shape[0], shape[-2], shape[-1]) if len(shape) == 4 else (1, *shape[-2:])
    param = next(model.parameters())
    estimate = estimate_bytes(model.mode, size[0] * size[1] * size[2], bool(return_std), model.uncertainty,
                              torch.finfo(param.dtype).bits // 8)
    return out_of_memory(exc, size, param.device, estimate=estimate)
