"""Classical depth fill after Ku, Harakeh and Waslander 2018 (IP-Basic), written in torch.

Ku, Harakeh, Waslander, "In Defense of Classical Image Processing: Fast Depth Completion
on the CPU", CRV 2018, fills sparse LiDAR depth with a fixed chain of morphological
operations and blurs: no image, no training. docs/design.md section 3b plans it as the
classical prior of the CRF (``x0`` and warm start) and as a baseline. This module writes the
paper's steps with torch and kornia operations, so that it runs batched on any device.

All steps work on *inverted* depth ``d' = max_depth - d`` (0 = empty). A dilation (maximum
over a neighbourhood) then picks the *nearest* return around a pixel, so foreground edges
win over the background behind them, and empty pixels (0) never win over a return (> 0).
"""

from __future__ import annotations

from typing import Literal

import torch
import torch.nn.functional as F

from crfdepth.checks import check_choice, check_depth_frames, check_number
from crfdepth.errors import InputError
from crfdepth.fill.nearest import nearest_fill

__all__ = ["CONFIGS", "MIN_DEPTH_M", "Config", "ip_basic_fill"]

Config = Literal["fast", "multiscale"]
CONFIGS: tuple[str, ...] = ("fast", "multiscale")

MIN_DEPTH_M = 0.1
"""Depths (and inverted depths) at or below this many metres count as empty, as in the paper."""

# Multiscale dilation: (upper bound of the depth range in metres, width of the cross kernel).
# Near returns are further apart in the image and belong to larger objects: wider kernel.
_RANGE_KERNELS = ((15.0, 7), (30.0, 5), (float("inf"), 3))

_GAUSSIAN_SIGMA = 1.1
_BILATERAL_SIGMA_COLOR_M = 1.5
_BILATERAL_SIGMA_SPACE = 2.0


def ip_basic_fill(sparse: torch.Tensor, *, config: Config = "fast", max_depth: float = 100.0) -> torch.Tensor:
    """Dense depth from sparse LiDAR by the classical fill of Ku et al. 2018 (IP-Basic).

    docs/design.md section 3b. Steps of the ``"fast"`` configuration (the paper's
    algorithm with the Gaussian blur), each on inverted depth ``d' = max_depth - d``:

    1. invert the returns ``d > 0.1`` m (others stay 0 = empty);
    2. dilate with a 5x5 diamond kernel;
    3. close (dilate, then erode) with a 5x5 full kernel: small holes between returns;
    4. empty pixels take a 7x7 full-kernel dilation (small hole fill);
    5. every column's top-most filled value extends up to the top of the image;
    6. empty pixels take a 31x31 full-kernel dilation (large hole fill);
    7. 5x5 median blur (outliers), then 5x5 Gaussian blur (sigma 1.1 px);
    8. invert back.

    ``"multiscale"`` is not in the paper; it follows the idea of the multi-scale variant its
    authors added later: step 2 dilates each depth range with its own cross kernel, 7 px wide
    up to 15 m, 5 px from 15 to 30 m, 3 px beyond (near returns lie further apart in the
    image), nearer ranges winning where they overlap; a 5x5 median blur of the filled
    pixels follows step 3; step 7 ends with a 5x5 bilateral blur (sigma 1.5 m in depth,
    2 px in space) instead of the Gaussian.

    Morphological operations ignore the pixels outside the image; the blurs replicate the
    border pixels. **Deviation (paper):** pixels that steps 2 to 6 leave empty (more than
    15 px from every filled pixel below the top-most one of their column, or in a column
    without returns; none on the two official KITTI val frames) take, before step 7, the
    value of the nearest filled pixel (:func:`crfdepth.fill.nearest.nearest_fill`). The paper
    leaves them empty and blurs only the filled pixels, mixing the zeros of empty
    neighbours into them; here step 7 sees no empty pixel, and the output is > 0
    everywhere. LiDAR pixels do not keep their exact value (step 7 smooths them).

    About 0.1 s of CPU time per 1216x352 frame (``"multiscale"``: 0.2 s), half of it the median.

    Not differentiable (a fixed prior, like :func:`crfdepth.fill.nearest.nearest_fill`): the output
    is detached, on the input's device and dtype; the input is not modified.

    Args:
        sparse: (B, 1, H, W), (1, H, W) or (H, W) z-depth in metres, 0 = no LiDAR return.
            Returns at or below 0.1 m count as missing; every return must be below
            ``max_depth - 0.1``.
        config: ``"fast"`` (default) or ``"multiscale"``.
        max_depth: depth in metres the map is inverted about (default 100, as in the paper;
            KITTI's returns end near 90 m).

    Returns:
        Tensor of the shape of ``sparse``: depth > 0 at every pixel, in metres.

    Raises:
        InputError: ``sparse`` of the wrong shape or dtype, with NaN/inf or negative depth,
            or with a frame without any return above 0.1 m (named by its batch index);
            ``config`` unknown; ``max_depth`` not a number above the largest return plus 0.1 m.
    """
    frames = check_depth_frames(sparse, above=MIN_DEPTH_M)
    check_choice("config", config, CONFIGS)
    check_number("max_depth", max_depth, low=MIN_DEPTH_M)
    deepest = float(frames.max())
    if deepest >= max_depth - MIN_DEPTH_M:
        raise InputError(f"max_depth: expected a number > the largest sparse depth + {MIN_DEPTH_M:g} m "
                         f"({deepest + MIN_DEPTH_M:.4g}), got {max_depth!r}")

    work = frames.to(torch.float64 if frames.dtype == torch.float64 else torch.float32)
    returns = _invert(work, max_depth)
    inverted = _fast(returns) if config == "fast" else _multiscale(returns, max_depth)
    return _invert(inverted, max_depth).to(sparse.dtype).reshape(sparse.shape)


# --------------------------------------------------------------------------- the two configurations


def _fast(returns: torch.Tensor) -> torch.Tensor:
    """Steps 2 to 7 of the fast configuration on inverted depth (B, 1, H, W), 0 = empty."""
    x = _close(_dilate_diamond5(returns), 5)
    return _gaussian(_median(_fill_holes(x, returns), 5))


def _multiscale(returns: torch.Tensor, max_depth: float) -> torch.Tensor:
    """Steps 2 to 7 of the multiscale configuration on inverted depth (B, 1, H, W), 0 = empty."""
    x = _median_filled(_close(_dilate_by_range(returns, max_depth), 5), 5)
    return _bilateral(_median(_fill_holes(x, returns), 5))


def _fill_holes(x: torch.Tensor, returns: torch.Tensor) -> torch.Tensor:
    """Steps 4 to 6 and the fill of the pixels they leave empty, the same in both configurations."""
    x = _fill_empty(x, 7)
    x = _extend_to_top(x)
    x = _fill_empty(x, 31)
    return _fill_unreached(x, returns)


# --------------------------------------------------------------------------- the steps
# Every step takes and returns inverted depth (B, 1, H, W) with 0 = empty.


def _invert(x: torch.Tensor, max_depth: float) -> torch.Tensor:
    """``max_depth - x`` where ``x > 0.1``, else 0 (its own inverse on maps inside (0.1, max_depth - 0.1))."""
    return torch.where(x > MIN_DEPTH_M, max_depth - x, torch.zeros_like(x))


def _dilate_diamond5(x: torch.Tensor) -> torch.Tensor:
    """Dilation with the 5x5 diamond (pixels at city-block distance <= 2); outside the image ignored.

    The diamond is the union of the 3x3 square and the 5-wide cross, so its maximum is the
    maximum of the three full-rectangle maxima (exact, and cheaper than a 25-cell window).
    """
    return torch.maximum(_max_filter(x, 3), _dilate_cross(x, 5))


def _dilate_cross(x: torch.Tensor, width: int) -> torch.Tensor:
    """Dilation with a cross (plus sign) ``width`` pixels wide and high; outside the image ignored."""
    return torch.maximum(_running_max(x, width, dim=-2), _running_max(x, width, dim=-1))


def _max_filter(x: torch.Tensor, size: int) -> torch.Tensor:
    """Dilation with a full ``size`` x ``size`` kernel; pixels outside the image are ignored.

    A maximum over a rectangle is separable: columns, then rows.
    """
    return _running_max(_running_max(x, size, dim=-2), size, dim=-1)


def _running_max(x: torch.Tensor, size: int, dim: int) -> torch.Tensor:
    """Maximum over the centred window of odd ``size`` along ``dim`` (-2 or -1), outside ignored.

    Doubling: after k rounds ``m[i]`` is the maximum over ``[i, i + 2**k)`` of the map padded
    with -inf; a window of ``size`` is the union of two such spans. About log2(size)
    elementwise maxima instead of ``size`` comparisons per pixel (torch's ``max_pool2d`` on
    the CPU is 10 to 30 times slower here).
    """
    r = size // 2
    n = x.shape[dim]
    m = F.pad(x, (r, r, 0, 0) if dim == -1 else (0, 0, r, r), value=float("-inf"))
    span = 1
    while 2 * span <= size:
        length = m.shape[dim] - span
        m = torch.maximum(m.narrow(dim, 0, length), m.narrow(dim, span, length))
        span *= 2
    return torch.maximum(m.narrow(dim, 0, n), m.narrow(dim, size - span, n))


def _min_filter(x: torch.Tensor, size: int) -> torch.Tensor:
    """Erosion with a full ``size`` x ``size`` kernel; pixels outside the image are ignored."""
    return -_max_filter(-x, size)


def _close(x: torch.Tensor, size: int) -> torch.Tensor:
    """Morphological closing (dilation, then erosion) with a full kernel."""
    return _min_filter(_max_filter(x, size), size)


def _fill_empty(x: torch.Tensor, size: int) -> torch.Tensor:
    """Empty pixels take the full-kernel dilation; filled pixels keep their value."""
    return torch.where(x > MIN_DEPTH_M, x, _max_filter(x, size))


def _extend_to_top(x: torch.Tensor) -> torch.Tensor:
    """Each column's top-most filled value fills every pixel above it (columns without one stay)."""
    filled = (x > MIN_DEPTH_M).to(torch.uint8)
    top = filled.argmax(dim=-2, keepdim=True)  # (B, 1, 1, W): first filled row; 0 if none
    top_value = x.gather(-2, top)
    rows = torch.arange(x.shape[-2], device=x.device).view(-1, 1)
    return torch.where(rows < top, top_value, x)


def _median(x: torch.Tensor, size: int) -> torch.Tensor:
    """Median over the ``size`` x ``size`` window, border pixels replicated; empty pixels count as 0."""
    r = size // 2
    from kornia.filters import median_blur  # kornia at first use: its import costs 0.2 s

    return median_blur(F.pad(x, (r, r, r, r), mode="replicate"), size)[..., r:-r, r:-r]


def _median_filled(x: torch.Tensor, size: int) -> torch.Tensor:
    """:func:`_median` on the filled pixels only; empty pixels stay empty."""
    return torch.where(x > MIN_DEPTH_M, _median(x, size), x)


def _gaussian(x: torch.Tensor) -> torch.Tensor:
    """5x5 Gaussian blur, sigma 1.1 px (the sigma of a 5-tap kernel given by its size alone)."""
    from kornia.filters import gaussian_blur2d

    return gaussian_blur2d(x, (5, 5), (_GAUSSIAN_SIGMA, _GAUSSIAN_SIGMA), border_type="replicate")


def _bilateral(x: torch.Tensor) -> torch.Tensor:
    """5x5 bilateral blur: sigma 1.5 m in (inverted) depth, 2 px in space."""
    space = (_BILATERAL_SIGMA_SPACE, _BILATERAL_SIGMA_SPACE)
    from kornia.filters import bilateral_blur

    return bilateral_blur(x, (5, 5), _BILATERAL_SIGMA_COLOR_M, space, border_type="replicate")


def _dilate_by_range(x: torch.Tensor, max_depth: float) -> torch.Tensor:
    """Each depth range dilated with its own cross kernel; nearer ranges win where they overlap.

    On inverted depth nearer means larger, so "nearer wins" is the pixelwise maximum.
    """
    out = torch.zeros_like(x)
    lower = MIN_DEPTH_M
    for upper, width in _RANGE_KERNELS:
        # Inverted depth d' = max_depth - d: the range (lower, upper] in d is [max_depth - upper, max_depth - lower).
        in_range = (x >= max_depth - upper) & (x < max_depth - lower) & (x > MIN_DEPTH_M)
        out = torch.maximum(out, _dilate_cross(torch.where(in_range, x, torch.zeros_like(x)), width))
        lower = upper
    return out


# --------------------------------------------------------------------------- the fallback


def _fill_unreached(x: torch.Tensor, returns: torch.Tensor) -> torch.Tensor:
    """Empty pixels take the value of the nearest filled pixel (or LiDAR return, if the steps emptied it)."""
    empty = ~(x > MIN_DEPTH_M)
    if not bool(empty.any()):
        return x
    known = torch.where(empty, returns, x)  # every frame has a return, so nearest_fill never raises
    return torch.where(empty, nearest_fill(known), x)
