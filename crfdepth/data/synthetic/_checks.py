"""Argument checks of the synthetic scene's public functions (one-line InputError messages)."""

from __future__ import annotations

import math
from numbers import Integral, Real

from crfdepth.errors import InputError

__all__ = ["check_int", "check_real"]


def check_int(name: str, value, low: int, high: int | None) -> None:
    """``value`` is an integer (not a bool) in [low, high] (``high`` None: no upper bound)."""
    if isinstance(value, bool) or not isinstance(value, Integral):
        raise InputError(f"{name}: expected an integer, got {value!r} ({type(value).__name__})")
    if value < low or (high is not None and value > high):
        upper = "" if high is None else f" and <= {high}"
        raise InputError(f"{name}: expected an integer >= {low}{upper}, got {value}")


def check_real(name: str, value, low: float, high: float | None, *, low_open: bool = False,
               high_open: bool = False) -> None:
    """``value`` is a finite real number (not a bool) between ``low`` and ``high``, ends as flagged."""
    if isinstance(value, bool) or not isinstance(value, Real) or not math.isfinite(value):
        raise InputError(f"{name}: expected a finite number, got {value!r}")
    bad_low = value <= low if low_open else value < low
    bad_high = high is not None and (value >= high if high_open else value > high)
    if bad_low or bad_high:
        lo_b = "(" if low_open else "["
        hi_b = ")" if high_open or high is None else "]"
        hi_s = "inf" if high is None else f"{high:g}"
        raise InputError(f"{name}: expected a value in {lo_b}{low:g}, {hi_s}{hi_b}, got {value!r}")
