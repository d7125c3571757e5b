"""Input checks at the public boundary of crfdepth: one place, one message format.

Every check raises :class:`crfdepth.errors.InputError` with one line of the form
``<name>: expected <what>, got <what was received>``, where ``<name>`` is the name the
*user* knows the argument by (``image``, ``sparse``, ``K``, ``--intrinsics``, a
checkpoint's parameter name), never an internal variable. Public functions call these
once; the internals they call trust their inputs (docs/design.md section 8).
"""

from __future__ import annotations

import math

import torch

from crfdepth.errors import InputError

__all__ = [
    "check_map",
    "check_number",
    "check_scalar_tensor",
    "describe",
]


def describe(value: object) -> str:
    """A short description of a received value for messages: a tensor's shape, else its type."""
    if isinstance(value, torch.Tensor):
        return f"shape {tuple(value.shape)} {str(value.dtype).replace('torch.', '')}"
    shape = getattr(value, "shape", None)
    if shape is not None:
        return f"shape {tuple(shape)} {getattr(value, 'dtype', '')}".rstrip()
    return type(value).__name__


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
