"""The coarse first solve of the pixel grid, and the statistic that tells a sparse input from a dense one
(docs/design.md section 17).

With few returns (500 samples of a frame, 16 beams) the pixel grid's membrane lets each return inform only
a small neighbourhood: between returns the solution falls back to the prior, the nearest fill, and its
Voronoi cells. Solving first on a grid of ``block`` x ``block`` pixel blocks (the mean colour of a block,
the mean of its returns) spreads each return over blocks as far as the next return in a few nodes; that
depth, painted back bilinearly, is the prior of the full-resolution solve, which restores the edges. It is
the paper's superpixel structure with square segments: on the shared frames it scores as SLIC's segments of
the same size do, at a fraction of the time (section 17 has the numbers).
"""

from __future__ import annotations

import torch
import torch.nn.functional as F

from crfdepth.geometry.nearest import nearest_valid

SPARSE_DISTANCE = 4.5
"""Median distance in pixels from a pixel to the nearest return above which an input is sparse (section 17):
a 64-beam scan at KITTI's resolution has 2.2-3.6 px on the shared frames, 16 beams 8-10, NYU's 500 samples
5.7-6.1, KITTI's 500 samples about 10."""


def median_return_distance(sparse: torch.Tensor) -> torch.Tensor:
    """(B,) the median over each frame's pixels of the distance in pixels to the nearest return of a
    (B, 1, H, W) depth map (0 = no return): half the typical gap between returns."""
    _, squared = nearest_valid(sparse[:, 0] > 0)
    return squared.flatten(1).to(torch.float32).median(dim=1).values.sqrt()


def coarse_frame(image: torch.Tensor, kept: torch.Tensor, K: torch.Tensor, block: int, variable: str
                 ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """``(image, sparse, K)`` of the block grid: each block's mean colour, the mean of its returns (geometric for
    ``variable="log"``, arithmetic otherwise; 0 without one) and the intrinsics of the coarse pixels. A frame
    whose size is not a multiple of ``block`` is padded on the right and bottom by its edge pixels (image) and
    by no returns (depth)."""
    h, w = kept.shape[2:]
    pad = (0, -w % block, 0, -h % block)
    image = F.avg_pool2d(F.pad(image, pad, mode="replicate"), block)
    kept = F.pad(kept, pad)
    has = kept > 0
    count = F.avg_pool2d(has.to(kept.dtype), block)
    values = torch.where(has, kept.clamp_min(1e-6).log(), torch.zeros_like(kept)) if variable == "log" else kept
    mean = F.avg_pool2d(values, block) / count.clamp_min(1e-12)
    mean = mean.exp() if variable == "log" else mean
    sparse = torch.where(count > 0, mean, torch.zeros_like(mean))
    coarse_K = K.clone()
    coarse_K[:, :2, :2] = K[:, :2, :2] / block
    coarse_K[:, :2, 2] = (K[:, :2, 2] + 0.5) / block - 0.5  # pixel centres: fine u -> coarse (u + 0.5) / b - 0.5
    return image, sparse, coarse_K


def paint(depth: torch.Tensor, block: int, size: tuple[int, int]) -> torch.Tensor:
    """The (B, 1, h, w) block depth back at full resolution ``size``, bilinear between block centres."""
    h, w = depth.shape[2:]
    return F.interpolate(depth, size=(h * block, w * block), mode="bilinear", align_corners=False)[
        ..., :size[0], :size[1]]


def usable_block(block: int, size: tuple[int, int]) -> int:
    """``block``, or 1 (no coarse solve) where the block grid would be smaller than 2 x 2."""
    return block if block > 1 and min(-(-size[0] // block), -(-size[1] // block)) >= 2 else 1
