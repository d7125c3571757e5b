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
looks inverted (unless ``trust_transform=True``, :func:`crfdepth.inputs.points_to_sparse`); the
checks and conversions of the inputs live in :mod:`crfdepth.inputs`.
"""

from __future__ import annotations

import contextlib
import copy
import logging
import math

import cv2
import numpy as np
import torch

from crfdepth.checkpoints import load_pretrained
from crfdepth.checks import check_flag, check_frames, check_has_data
from crfdepth.errors import InputError
from crfdepth.inputs import checked_points_to_sparse, image_to_numpy, prepare_points, sparse_to_numpy
from crfdepth.intrinsics import check_intrinsics
from crfdepth.io.calibration import Calibration, RigCalibration
from crfdepth.memory import check_frame_size, check_model_memory, estimate_bytes, is_out_of_memory, out_of_memory
from crfdepth.model import CRFDepth
from crfdepth.precision import autocast_off

__all__ = ["check_frame", "check_model", "complete_batch", "complete_checked", "complete_depth"]

logger = logging.getLogger(__name__)


def check_frame(image, sparse, K) -> None:
    """Refuse a frame that :func:`complete_depth` would refuse for ``image``, ``sparse`` and ``K``,
    with its checks, messages and order: RGB not (3, H, W) / (H, W, 3) in [0, 1]; K not the
    intrinsics of an image of this size (:func:`crfdepth.intrinsics.check_intrinsics`); sparse depth
    not finite, >= 0, with a return, or not plausibly metres of a LiDAR scene seen with this K
    (:func:`crfdepth.plausibility.check_sparse_plausible`: the hints say what to divide by)."""
    rgb, _, _ = image_to_numpy(image)
    check_frame_size("image", *rgb.shape[:2])
    Kn = check_intrinsics(K, "K", rgb.shape[:2])
    sparse_to_numpy(sparse, rgb.shape[:2], Kn)


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


def check_model(model) -> CRFDepth:
    """``model`` if it is a :class:`~crfdepth.model.CRFDepth` (or a ``torch.compile`` of one: its module is
    returned, the pipelines run it as they are), else an InputError naming ``model``."""
    model = getattr(model, "_orig_mod", model) if isinstance(model, torch.nn.Module) else model
    if not isinstance(model, CRFDepth):
        raise InputError(f"model: expected a crfdepth.CRFDepth (CRFDepth.from_pretrained(), crfdepth.load_model(), "
                         f"or None for the default), got {type(model).__name__}")
    return model


def _model_on(model, device: str | torch.device):
    device = _device(device)
    if model is None:
        return load_pretrained().to(device)
    model = check_model(model)
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
            e.g. intensity, are ignored), or a structured / record array with fields x, y, z
            (pypcd4, ROS); rows with NaN/inf are dropped with a warning giving the count.
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
            its inverse keeps it level; otherwise refused, :func:`crfdepth.inputs.points_to_sparse`).
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
    return_std, trust_transform, trust_units = (check_flag(name, value) for name, value in (
        ("return_std", return_std), ("trust_transform", trust_transform), ("trust_units", trust_units)))
    known = _image_size(image)
    if known is None:  # not an image of an accepted layout: refused here, naming image
        image_to_numpy(image)
    model = _model_on(model, device)
    # size and memory from the shape alone, before any conversion allocates
    check_frame_size("image", *known)
    check_model_memory(model, 1, *known, return_std)
    rgb, is_tensor, out_device = image_to_numpy(image)
    size = rgb.shape[:2]
    calibration = _calibration(calibration, K, T_cam_lidar, distortion, points, size)
    if (sparse is None) == (points is None):
        raise InputError(f"sparse / points: expected exactly one of them (a sparse depth map or a point cloud), "
                         f"got {'both' if sparse is not None else 'neither'}")
    if calibration.distortion is not None:
        rgb = cv2.undistort(rgb, calibration.K, calibration.distortion)
        if sparse is not None:
            logger.warning("distortion: the image is undistorted but a given sparse map is used as is; it must "
                           "already be projected with K and no distortion")
    if points is not None:
        sparse_np = checked_points_to_sparse(prepare_points(points), calibration, size, trust_transform)
    else:
        sparse_np = sparse_to_numpy(sparse, size, None if trust_units else calibration.K)

    # The checked arrays as a batch of one through the one door into the pipelines (not model.forward, which
    # would check the frame again).
    depth, std = _complete_on_model(model, rgb.transpose(2, 0, 1)[None], sparse_np[None, None], calibration.K[None],
                                    return_std)
    if is_tensor:  # the one conversion out: the image's kind and device
        return depth[0].to(out_device), (std[0].to(out_device) if std is not None else None)
    return depth[0].cpu().numpy(), (std[0].cpu().numpy() if std is not None else None)


def _calibration(calibration, K, T_cam_lidar, distortion, points, size: tuple[int, int]) -> RigCalibration:
    """The camera of :func:`complete_depth` as one checked :class:`RigCalibration`, from ``calibration`` or
    from ``K`` / ``T_cam_lidar`` / ``distortion``."""
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
        if calibration.image_size is None:  # K was checked without an image size when it was built
            check_intrinsics(calibration.K, calibration.name("K"), size)
        return calibration
    if K is None:
        raise InputError("K: required: expected the 3x3 intrinsics of the image (or calibration=), got None")
    if points is not None and T_cam_lidar is None:
        raise InputError("T_cam_lidar: required with points: expected the 4x4 LiDAR -> camera transform "
                         "(metres), got None")
    # checked once, as the calibration is built: K against the image's size, T rigid, distortion's length
    return RigCalibration(K=K, T_cam_lidar=np.eye(4) if T_cam_lidar is None else T_cam_lidar, distortion=distortion,
                          image_size=size, source="arguments")


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
    for name, value in (("image", image), ("sparse", sparse), ("K", K)):
        if not isinstance(value, torch.Tensor):
            raise InputError(f"{name}: expected a torch.Tensor, got {type(value).__name__}")
        check_has_data(name, value)
    if sparse.dim() == 4:  # the size from the shape alone, before the checks allocate per pixel
        check_frame_size("image", *sparse.shape[2:])
    per_frame = K.dim() == 3
    image, sparse, K = check_frames(*_on_model(model, image, sparse, K))
    from crfdepth.intrinsics import check_batch_intrinsics

    check_batch_intrinsics(K, tuple(sparse.shape[2:]), per_frame)
    return complete_checked(model, image, sparse, K, return_std=return_std)


def complete_checked(model, image: torch.Tensor, sparse: torch.Tensor, K: torch.Tensor, *, return_std: bool
                     ) -> tuple[torch.Tensor, torch.Tensor | None]:
    """:func:`complete_batch` of frames already checked (:func:`check_frame` on each, as the CLI's folder mode
    does in its DataLoader workers), in the layout :func:`crfdepth.checks.check_frames` returns: no input is
    checked again; the batch is refused up front when it would not fit in the memory
    (:class:`~crfdepth.memory.MemoryRefusal`). ``model`` is a :class:`~crfdepth.model.CRFDepth`; the
    tensors are moved to its device and dtype. Returns (B, H, W) float32 depth and std (None without
    ``return_std``), metres, on the model's device."""
    model = check_model(model)
    check_model_memory(model, sparse.shape[0], *sparse.shape[2:], bool(return_std))
    return _complete_on_model(model, image, sparse, K, return_std)


def _complete_on_model(model, image, sparse, K, return_std: bool) -> tuple[torch.Tensor, torch.Tensor | None]:
    """The one door into the pipelines (:meth:`CRFDepth.pipeline`, docs/design.md section 8), shared by
    :func:`complete_depth` and :func:`complete_checked`: a checked batch (``image`` (B, 3, H, W) in [0, 1],
    ``sparse`` (B, 1, H, W) metres with 0 = no point, ``K`` (B, 3, 3) or (3, 3) pixels; numpy or tensors) converted
    to the model's tensors once (:func:`_on_model`) and run by the model's pipeline in :class:`_ModelStep` (no
    autograd, full precision, an allocator failure as a :class:`~crfdepth.memory.MemoryRefusal`). Returns (B, H, W)
    float32 depth and std (None without ``return_std``), metres, on the model's device."""
    image, sparse, K = _on_model(model, image, sparse, K)
    with _ModelStep(model, sparse, return_std) as step:
        step.output = model.pipeline(image, sparse, K, return_std)
    return step.result()


def _on_model(model, *arrays) -> tuple[torch.Tensor, ...]:
    """``arrays`` (numpy or tensors) as tensors on the model's device in its dtype: the one conversion of a
    frame's values on its way in (a numpy array is shared, not copied, where its layout allows)."""
    param = next(model.parameters())
    return tuple((torch.from_numpy(np.require(a, a.dtype.newbyteorder("="), ("C", "W"))) if isinstance(a, np.ndarray)
                  else a).to(param.device, param.dtype) for a in arrays)


class _ModelStep:
    """The model's pipeline run inside ``with``: under ``no_grad`` and with autocast off (the CRF in full
    precision, :mod:`crfdepth.precision`), and with an allocator failure (the last line of defence behind the
    up-front memory estimate) held back and raised by :meth:`result` as a one-line
    :class:`~crfdepth.memory.MemoryRefusal`, once the failed forward's tensors are released."""

    def __init__(self, model, sparse: torch.Tensor, return_std: bool):
        self.model, self.size, self.return_std = model, (sparse.shape[0], *sparse.shape[-2:]), return_std
        self.output, self.failure = None, None
        self._contexts = contextlib.ExitStack()
        self._sparse = sparse  # its device: where autocast is turned off

    def __enter__(self) -> "_ModelStep":
        self._contexts.enter_context(torch.no_grad())
        self._contexts.enter_context(autocast_off(self._sparse))
        return self

    def __exit__(self, kind, exc, traceback) -> bool:
        self._contexts.__exit__(kind, exc, traceback)
        if exc is None or not isinstance(exc, (RuntimeError, MemoryError)) or not is_out_of_memory(exc):
            return False
        param = next(self.model.parameters())
        settings = self.model.settings
        estimate = estimate_bytes(settings.structure.mode, math.prod(self.size), self.return_std,
                                  settings.uncertainty.kind, torch.finfo(param.dtype).bits // 8)
        self.failure = out_of_memory(exc, self.size, param.device, estimate=estimate)
        return True

    def result(self) -> tuple[torch.Tensor, torch.Tensor | None]:
        """(B, H, W) float32 depth and std (None without ``return_std``) of the run, or its allocator failure."""
        if self.failure is not None:
            if next(self.model.parameters()).device.type == "cuda":
                torch.cuda.empty_cache()
            raise self.failure
        out = self.output
        return out.depth[:, 0].float(), (out.std[:, 0].float() if self.return_std else None)
