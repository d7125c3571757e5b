"""IP-Basic's original fast fill, in OpenCV: the reference that ``benchmarks/speed.py`` times crfdepth against.

Ku, Harakeh, Waslander, "In Defense of Classical Image Processing: Fast Depth Completion on
the CPU", CRV 2018. Their published code (``depth_map_utils.fill_in_fast``) is a chain of
OpenCV calls on one float32 map; this module follows it step for step, with the options
of the paper's KITTI submission (``extrapolate=True``, ``blur_type='gaussian'``), so that
the timing is the original algorithm's, not crfdepth's torch port of it
(:func:`crfdepth.fill.ip_basic.ip_basic_fill`, docs/design.md section 3b). Written from the
paper and the published steps; OpenCV's own defaults (borders, the Gaussian's weights) are
kept, since they are part of what the original computes:

1. invert the returns ``d > 0.1`` m: ``d' = max_depth - d`` (others stay 0 = empty);
2. ``cv2.dilate`` with the 5x5 diamond kernel;
3. ``cv2.morphologyEx(MORPH_CLOSE)`` with a 5x5 full kernel;
4. pixels below 0.1 take a 7x7 full-kernel dilation;
5. every column's top-most value above 0.1 fills the pixels above it;
6. pixels below 0.1 take a 31x31 full-kernel dilation;
7. ``cv2.medianBlur`` 5 (border pixels replicated), then ``cv2.GaussianBlur`` 5x5 with sigma
   0: OpenCV's fixed 5-tap kernel (1, 4, 6, 4, 1) / 16, borders reflected without repeating
   the edge pixel (``BORDER_REFLECT_101``); only pixels above 0.1 take the blurred value;
8. invert back the pixels above 0.1.

Morphology ignores pixels outside the image (OpenCV's default border for dilate and erode).
Pixels the steps leave empty stay 0, and the blur of their neighbours mixes those zeros in
(crfdepth's port fills them from the nearest filled pixel first: the deviation its docstring
states).
"""

from __future__ import annotations

import cv2
import numpy as np
import torch

from crfdepth.checks import check_depth_frames, check_number
from crfdepth.errors import InputError

__all__ = ["fill_in_fast", "ip_basic_opencv_fill"]

MIN_DEPTH_M = 0.1
"""Depths (and inverted depths) at or below this many metres count as empty, as in the original."""

FULL_KERNEL_5 = np.ones((5, 5), np.uint8)
FULL_KERNEL_7 = np.ones((7, 7), np.uint8)
FULL_KERNEL_31 = np.ones((31, 31), np.uint8)
# Pixels at city-block distance <= 2 from the centre.
DIAMOND_KERNEL_5 = (np.add.outer(np.abs(np.arange(-2, 3)), np.abs(np.arange(-2, 3))) <= 2).astype(np.uint8)


def fill_in_fast(depth: np.ndarray, max_depth: float = 100.0) -> np.ndarray:
    """Dense depth from one sparse LiDAR map by IP-Basic's original fast fill (steps in the module docstring).

    Args:
        depth: (H, W) float32 z-depth in metres, 0 = no LiDAR return; not modified.
        max_depth: depth in metres the map is inverted about (100, as in the original).

    Returns:
        (H, W) float32 depth in metres; 0 where the steps reach no return (none on KITTI frames).
    """
    if not isinstance(depth, np.ndarray) or depth.ndim != 2 or depth.dtype != np.float32:
        got = f"{depth.dtype} array of shape {depth.shape}" if isinstance(depth, np.ndarray) else type(depth).__name__
        raise InputError(f"depth: expected an (H, W) float32 array, got {got}")
    d = depth.copy()  # the original works in place on its argument
    valid = d > MIN_DEPTH_M
    d[valid] = max_depth - d[valid]  # 1

    d = cv2.dilate(d, DIAMOND_KERNEL_5)  # 2
    d = cv2.morphologyEx(d, cv2.MORPH_CLOSE, FULL_KERNEL_5)  # 3

    empty = d < MIN_DEPTH_M  # 4
    d[empty] = cv2.dilate(d, FULL_KERNEL_7)[empty]

    filled = d > MIN_DEPTH_M  # 5: argmax gives 0 in a column without any value, which fills nothing
    top = np.argmax(filled, axis=0)
    above = np.arange(d.shape[0])[:, None] < top[None, :]
    d = np.where(above, d[top, np.arange(d.shape[1])][None, :], d)

    empty = d < MIN_DEPTH_M  # 6
    d[empty] = cv2.dilate(d, FULL_KERNEL_31)[empty]

    d = cv2.medianBlur(d, 5)  # 7
    valid = d > MIN_DEPTH_M
    d[valid] = cv2.GaussianBlur(d, (5, 5), 0)[valid]

    valid = d > MIN_DEPTH_M  # 8
    d[valid] = max_depth - d[valid]
    return d


def ip_basic_opencv_fill(sparse: torch.Tensor, *, max_depth: float = 100.0) -> torch.Tensor:
    """:func:`fill_in_fast` on each frame of a CPU tensor, for the benchmark's rows.

    Args:
        sparse: (B, 1, H, W), (1, H, W) or (H, W) z-depth in metres, 0 = no LiDAR return,
            on the CPU (OpenCV's functions run there); every return below ``max_depth - 0.1``.
        max_depth: depth in metres the map is inverted about.

    Returns:
        float32 tensor of the shape of ``sparse``: depth in metres, 0 where the fill reaches no return.

    Raises:
        InputError: ``sparse`` not a depth map as above, or not on the CPU; ``max_depth`` not above
            the largest return plus 0.1 m.
    """
    frames = check_depth_frames(sparse, above=MIN_DEPTH_M, what="the fill")
    if frames.device.type != "cpu":
        raise InputError(f"sparse: expected a tensor on the CPU (OpenCV runs there), got one on {frames.device}")
    check_number("max_depth", max_depth, low=MIN_DEPTH_M)
    deepest = float(frames.max())
    if deepest >= max_depth - MIN_DEPTH_M:
        raise InputError(f"max_depth: expected a number > the largest sparse depth + {MIN_DEPTH_M:g} m "
                         f"({deepest + MIN_DEPTH_M:.4g}), got {max_depth!r}")
    maps = frames.to(torch.float32).numpy()
    out = np.stack([fill_in_fast(np.ascontiguousarray(m[0]), max_depth)[None] for m in maps])
    return torch.from_numpy(out).reshape(sparse.shape)
