"""Input checks at the public boundary of crfdepth: one place, one message format.

Every check raises :class:`crfdepth.errors.InputError` with one line of the form
``<name>: expected <what>, got <what was received>``, where ``<name>`` is the name the
*user* knows the argument by (``image``, ``sparse``, ``K``, ``--intrinsics``, a
checkpoint's parameter name), never an internal variable. Public functions call these
once; the internals they call trust their inputs (docs/design.md section 8).
"""

from __future__ import annotations

import math

import numpy as np
import torch

from crfdepth.errors import InputError

__all__ = ["MAX_RETURN_DEPTH_M", "MIN_RETURN_DEPTH_M", "RIGID_TOLERANCE", "check_choice",
           "check_depth_frames", "check_depth_values", "check_flag", "check_frames", "check_has_data",
           "check_map", "check_number", "check_return_depths", "check_rigid", "check_scalar_tensor", "describe",
           "nonfinite", "to_numpy"]

# Largest deviation of R^T R from I (and of the last row from 0 0 0 1) of a rigid transform.
RIGID_TOLERANCE = 1e-3
# A LiDAR return's depth, metres (check_return_depths): none is nearer than 1 mm and none reaches 1 km
# (automotive LiDARs: 100-300 m); outside, the depth is in another unit or is not a measurement.
MIN_RETURN_DEPTH_M, MAX_RETURN_DEPTH_M = 1e-3, 1000.0


def describe(value: object) -> str:
    """A short description of a received value for messages: a tensor's shape, else its type."""
    if isinstance(value, torch.Tensor):
        return f"shape {tuple(value.shape)} {str(value.dtype).replace('torch.', '')}"
    shape = getattr(value, "shape", None)
    if shape is not None:
        return f"shape {tuple(shape)} {getattr(value, 'dtype', '')}".rstrip()
    return type(value).__name__


def to_numpy(t: torch.Tensor) -> np.ndarray:
    """A tensor's values as a numpy array on the host; float16 / bfloat16 (which numpy lacks) as float32,
    exactly."""
    t = t.detach().cpu()
    return (t.float() if t.dtype in (torch.float16, torch.bfloat16) else t).numpy()


def nonfinite(values, channel_axis: int | None = None) -> str | None:
    """Where a float array or tensor is not finite, for messages: ``NaN at 3 pixel(s)``, ``inf at 1 pixel(s)``
    or both joined by ``and``; None when every value is finite. With ``channel_axis`` a pixel counts once
    whatever its channels hold."""
    lib = torch if isinstance(values, torch.Tensor) else np
    v = values.detach() if isinstance(values, torch.Tensor) else np.asarray(values)
    if not (v.is_floating_point() if lib is torch else np.issubdtype(v.dtype, np.floating)):
        return None
    parts = []
    for word, mask in (("NaN", lib.isnan(v)), ("inf", lib.isinf(v))):
        if channel_axis is not None:
            mask = mask.any(channel_axis) if lib is torch else mask.any(axis=channel_axis)
        count = int(mask.sum())
        if count:
            parts.append(f"{word} at {count} pixel(s)")
    return " and ".join(parts) or None


def check_choice(name: str, value: object, choices) -> object:
    """``value`` if it is one of ``choices``; the message lists them quoted, in their order."""
    try:
        known = value in choices
    except (TypeError, ValueError):  # unhashable, or an array whose == is elementwise
        known = False
    if not known:
        raise InputError(f"{name}: expected one of {', '.join(map(repr, choices))}, got {value!r}")
    return value


def check_number(name: str, value: object, *, low: float | None = None, high: float | None = None,
                 low_open: bool = True, high_open: bool = True, integer: bool = False) -> float | int:
    """A finite real number (not a bool) within the given bounds.

    ``low`` / ``high`` are exclusive unless ``low_open`` / ``high_open`` is False.
    """
    kind = "an integer" if integer else "a number"
    if isinstance(value, bool) or not isinstance(value, (int, float) if not integer else int):
        raise InputError(f"{name}: expected {kind}{_bounds(low, high, low_open, high_open)}, got "
                         f"{type(value).__name__} {value!r}")
    if not math.isfinite(value) or (low is not None and (value <= low if low_open else value < low)) or \
            (high is not None and (value >= high if high_open else value > high)):
        raise InputError(f"{name}: expected {kind}{_bounds(low, high, low_open, high_open)}, got {value!r}")
    return value


def _bounds(low, high, low_open, high_open) -> str:
    if low is not None and high is not None:
        return f" in {'(' if low_open else '['}{low:g}, {high:g}{')' if high_open else ']'}"
    if low is not None:
        return f" {'>' if low_open else '>='} {low:g}"
    if high is not None:
        return f" {'<' if high_open else '<='} {high:g}"
    return ""


def check_map(name: str, t: object, ref: torch.Tensor | None = None, channels: int | None = None, *,
              ref_name: str = "depth", nonneg: bool = False, low: float | None = None,
              high: float | None = None, same_dtype: bool = True) -> torch.Tensor:
    """A finite floating (B, C, H, W) tensor.

    Args:
        name: the user's name of the argument.
        t: the value received.
        ref: when given, ``t`` must have its batch size, height and width, device and
            (with ``same_dtype``) dtype; ``ref_name`` names it in messages.
        channels: required C, or None for any.
        nonneg: values must be >= 0; ``low`` / ``high``: inclusive bounds on the values.
    """
    want = f"(B, {channels}, H, W)" if channels else "(B, C, H, W)"
    if not isinstance(t, torch.Tensor) or t.dim() != 4:
        raise InputError(f"{name}: expected a {want} tensor, got {describe(t)}")
    if not t.is_floating_point():
        raise InputError(f"{name}: expected a floating-point tensor, got dtype {t.dtype}")
    if channels is not None and t.shape[1] != channels:
        raise InputError(f"{name}: expected {channels} channel(s), {want}, got {describe(t)}")
    if ref is not None:
        b, _, h, w = ref.shape
        if t.shape[0] != b or tuple(t.shape[2:]) != (h, w):
            raise InputError(f"{name}: expected batch {b} and size {h}x{w} (HxW) like {ref_name} "
                             f"{tuple(ref.shape)}, got {describe(t)}")
        if t.device != ref.device or (same_dtype and t.dtype != ref.dtype):
            raise InputError(f"{name}: expected {'dtype ' + str(ref.dtype) + ' ' if same_dtype else ''}on "
                             f"{ref.device} like {ref_name}, got {t.dtype} on {t.device}")
    v = t.detach()
    finite = torch.isfinite(v)
    if not bool(finite.all()):
        raise InputError(f"{name}: expected finite values, got {int((~finite).sum())} NaN/inf entries")
    if nonneg and bool((v < 0).any()):
        raise InputError(f"{name}: expected values >= 0, got minimum {float(v.min()):.4g} "
                         f"({int((v < 0).sum())} negative entries)")
    if (low is not None and float(v.min()) < low) or (high is not None and float(v.max()) > high):
        raise InputError(f"{name}: expected values in [{low if low is not None else '-inf'}, "
                         f"{high if high is not None else 'inf'}], got range [{float(v.min()):.4g}, "
                         f"{float(v.max()):.4g}]")
    return t


def check_scalar_tensor(name: str, value: object, ref: torch.Tensor, *, positive: bool,
                        ref_name: str = "depth") -> torch.Tensor:
    """A number or one-element tensor, > 0 (``positive``) or >= 0, as a 0-d tensor like ``ref``."""
    if isinstance(value, torch.Tensor):
        if value.numel() != 1:
            raise InputError(f"{name}: expected a scalar (one element), got {describe(value)}")
        if value.device != ref.device:
            raise InputError(f"{name}: expected device {ref.device} like {ref_name}, got {value.device}")
        t = value.reshape(()).to(ref.dtype)
    elif isinstance(value, (int, float)) and not isinstance(value, bool):
        t = torch.tensor(float(value), dtype=ref.dtype, device=ref.device)
    else:
        raise InputError(f"{name}: expected a number or a one-element tensor, got {type(value).__name__}")
    v = float(t.detach())
    if not math.isfinite(v) or (v <= 0 if positive else v < 0):
        raise InputError(f"{name}: expected a finite value {'> 0' if positive else '>= 0'}, got {v:g}")
    return t


def check_depth_values(name: str, depth: torch.Tensor, *, zero: str = "no LiDAR") -> None:
    """A depth tensor's values: floating dtype, finite, >= 0 metres (``zero``: what 0 means)."""
    if not depth.is_floating_point():
        raise InputError(f"{name}: expected floating-point depth in metres, got dtype {depth.dtype}")
    if not bool(torch.isfinite(depth).all()):
        raise InputError(f"{name}: expected finite depth in metres (0 = {zero}), got NaN or inf")
    if bool((depth < 0).any()):
        raise InputError(f"{name}: expected depth >= 0 metres (0 = {zero}), got minimum {float(depth.min()):.4g}")


def check_depth_frames(sparse: object, *, above: float = 0.0, what: str = "the fill") -> torch.Tensor:
    """A (B, 1, H, W), (1, H, W) or (H, W) LiDAR depth map as a detached (B, 1, H, W) view.

    Checks a floating dtype, finite values >= 0 and, in every frame, at least one pixel
    deeper than ``above`` metres; the errors name ``sparse`` and say that ``what`` is
    undefined in an empty frame (named by its batch index).
    """
    if not isinstance(sparse, torch.Tensor) or not (
        sparse.ndim == 2 or (sparse.ndim == 3 and sparse.shape[0] == 1) or (sparse.ndim == 4 and sparse.shape[1] == 1)
    ):
        got = f"shape {tuple(sparse.shape)}" if isinstance(sparse, torch.Tensor) else type(sparse).__name__
        raise InputError(f"sparse: expected a (B, 1, H, W), (1, H, W) or (H, W) depth tensor, got {got}")
    check_depth_values("sparse", sparse)
    h, w = sparse.shape[-2:]
    frames = sparse.detach().reshape(-1, 1, h, w)
    has_return = (frames > above).flatten(1).any(dim=1)
    if not bool(has_return.all()):
        empty = torch.nonzero(~has_return).flatten().tolist()
        raise InputError(f"sparse: expected at least one pixel > {above:g}{' m' if above else ''} in every frame, "
                         f"got none in frame(s) {empty} (batch index); {what} is undefined there")
    return frames


def check_has_data(name: str, value: object) -> None:
    """Refuse a meta tensor (``device='meta'``: a shape without values) where values are needed."""
    if isinstance(value, torch.Tensor) and value.is_meta:
        raise InputError(f"{name}: expected a tensor holding values (on cpu, cuda or mps), got a meta tensor "
                         f"({describe(value)}, device 'meta': a shape without data)")


def check_return_depths(name: str, depth: object) -> None:
    """Every return (value > 0) of a finite depth array or tensor, metres, within [``MIN_RETURN_DEPTH_M``,
    ``MAX_RETURN_DEPTH_M``] = [1 mm, 1000 m]; the message counts those outside and gives the extreme."""
    v = depth.detach() if isinstance(depth, torch.Tensor) else np.asarray(depth)
    near, far = (v > 0) & (v < MIN_RETURN_DEPTH_M), v > MAX_RETURN_DEPTH_M
    parts = [f"{int(mask.sum())} {side} {bound:g} m ({word} {float(pick(v[mask])):.4g} m)"
             for mask, side, bound, word, pick in ((near, "below", MIN_RETURN_DEPTH_M, "smallest", lambda x: x.min()),
                                                   (far, "beyond", MAX_RETURN_DEPTH_M, "largest", lambda x: x.max()))
             if bool(mask.any())]
    if parts:
        raise InputError(f"{name}: expected LiDAR depths from {MIN_RETURN_DEPTH_M:g} to {MAX_RETURN_DEPTH_M:g} m "
                         f"(0 = no return), got {' and '.join(parts)}: another unit, or not measured depth")


def check_frames(image, sparse, K) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Check a batch of frames for the model; returns them with K expanded to (B, 3, 3).

    ``image`` (B, 3, H, W) finite RGB in [0, 1]; ``sparse`` (B, 1, H, W) floating, finite
    depth >= 0 in metres, returns in [1 mm, 1000 m] (:func:`check_return_depths`), at least one
    per frame; ``K`` (3, 3) or (B, 3, 3) finite with focal lengths > 0; all on one device, none meta.
    """
    for name, t in (("image", image), ("sparse", sparse), ("K", K)):
        if not isinstance(t, torch.Tensor):
            raise InputError(f"{name}: expected a torch.Tensor, got {type(t).__name__}")
        check_has_data(name, t)
    if sparse.dim() != 4 or sparse.shape[1] != 1:
        raise InputError(f"sparse: expected shape (B, 1, H, W), got {tuple(sparse.shape)}")
    bsz, _, h, w = sparse.shape
    if sparse.numel() == 0:
        raise InputError(f"sparse: expected at least one frame of at least one pixel, got shape {tuple(sparse.shape)}")
    if image.dim() != 4 or image.shape[1] != 3:
        raise InputError(f"image: expected shape (B, 3, H, W) (RGB), got {tuple(image.shape)}")
    if tuple(image.shape[2:]) != (h, w) or image.shape[0] != bsz:
        raise InputError(f"image: expected batch and size {(bsz, h, w)} like sparse, got "
                         f"{(image.shape[0], *image.shape[2:])}")
    if image.device != sparse.device or K.device != sparse.device:
        raise InputError(f"image, K: expected the device of sparse ({sparse.device}), got {image.device} and {K.device}")
    if not sparse.is_floating_point():
        raise InputError(f"sparse: expected floating-point depth in metres, got {sparse.dtype}")
    # One pass per tensor: min and max propagate NaN, and a NaN fails every comparison.
    low, high = (float(v) for v in torch.aminmax(sparse.detach()))
    if not (low >= 0 and high < math.inf):
        bad = nonfinite(sparse, 1)
        raise InputError(f"sparse: expected finite depth >= 0 in metres (0 = no LiDAR), got "
                         f"{bad or f'negative values (minimum {low:.4g})'}")
    check_return_depths("sparse", sparse)
    if not image.is_floating_point():
        raise InputError(f"image: expected floating-point RGB in [0, 1], got dtype {image.dtype}")
    low, high = (float(v) for v in torch.aminmax(image.detach()))
    if not (low >= 0 and high <= 1):
        bad = nonfinite(image, 1)
        if bad:
            raise InputError(f"image: expected finite RGB values in [0, 1], got {bad}")
        raise InputError(f"image: expected finite RGB values in [0, 1], got range [{low:.3g}, {high:.3g}]")
    if tuple(K.shape) == (3, 3):
        K = K[None].expand(bsz, 3, 3)
    if tuple(K.shape) != (bsz, 3, 3):
        raise InputError(f"K: expected shape (3, 3) or ({bsz}, 3, 3), got {tuple(K.shape)}")
    if not K.is_floating_point():
        raise InputError(f"K: expected floating-point intrinsics (pixels), got dtype {K.dtype}")
    if not bool(torch.isfinite(K).all()) or bool((K[:, 0, 0] <= 0).any()) or bool((K[:, 1, 1] <= 0).any()):
        raise InputError(f"K: expected finite intrinsics with focal lengths > 0, got fx {K[:, 0, 0].tolist()}, "
                         f"fy {K[:, 1, 1].tolist()}")
    empty = (sparse.flatten(1) > 0).sum(1) == 0
    if bool(empty.any()):
        raise InputError(f"sparse: frame(s) {torch.nonzero(empty).flatten().tolist()} have no LiDAR pixel; "
                         f"the CRF needs at least one depth measurement per frame")
    return image, sparse, K


# --------------------------------------------------------------------------- camera and LiDAR


def as_matrix(value: object, shape: tuple[int, int], name: str, allow_flat: bool) -> np.ndarray:
    """``value`` as a finite float64 array of ``shape`` (or of its row-major flat length)."""
    check_has_data(name, value)
    if isinstance(value, torch.Tensor):
        value = to_numpy(value)
    try:
        array = np.array(value, dtype=np.float64)
    except (TypeError, ValueError):
        raise InputError(f"{name}: expected a {shape[0]}x{shape[1]} matrix of numbers, got {value!r:.80}") from None
    if allow_flat and array.shape == (shape[0] * shape[1],):
        array = array.reshape(shape)
    if array.shape != shape:
        flat = f" or {shape[0] * shape[1]} numbers (row-major)" if allow_flat else ""
        raise InputError(f"{name}: expected a {shape[0]}x{shape[1]} matrix{flat}, got shape {array.shape}")
    if not np.all(np.isfinite(array)):
        raise InputError(f"{name}: expected finite numbers, got {array.ravel().tolist()}")
    return array


def check_rigid(T: object, what: str = "T_cam_lidar", tolerance: float = RIGID_TOLERANCE) -> np.ndarray:
    """(4, 4) float64 copy of ``T`` after checking it is a rigid transform (metres).

    Requires finite values, last row 0 0 0 1, ``R^T R = I`` (max abs deviation <=
    ``tolerance``) and ``det R > 0`` (a rotation, not a reflection). A scaled rotation
    (e.g. a transform meant for millimetre points) fails the orthonormality test; the
    direction of the transform is not checked here (see :func:`crfdepth.inputs.points_to_sparse`).
    """
    T = as_matrix(T, (4, 4), what, allow_flat=False)
    if np.max(np.abs(T[3] - (0.0, 0.0, 0.0, 1.0))) > tolerance:
        raise InputError(f"{what}: expected the last row of a rigid 4x4 transform to be 0 0 0 1, got "
                         f"{' '.join(f'{v:g}' for v in T[3])}")
    R = T[:3, :3]
    deviation = float(np.max(np.abs(R.T @ R - np.eye(3))))
    if deviation > tolerance:
        raise InputError(f"{what}: expected a rigid transform (rotation + translation in metres) whose rotation "
                         f"part T[:3, :3] is orthonormal within {tolerance:g}, got max |R^T R - I| = "
                         f"{deviation:.3g}: not orthonormal (a projection, a scaled or a hand-typed rotation? "
                         f"check for typos and for too few digits)")
    if np.linalg.det(R) < 0:
        raise InputError(f"{what}: expected a rotation part with determinant +1, got {np.linalg.det(R):.3g} (a "
                         f"reflection): an axis is flipped; check the axis conventions of both frames")
    return T


def check_flag(name: str, value: object) -> bool:
    """A yes/no argument: a ``bool`` (numpy's too), never a string or a number read as true (``"no"`` is truthy)."""
    if not isinstance(value, (bool, np.bool_)):
        raise InputError(f"{name}: expected True or False, got {value!r}")
    return bool(value)
