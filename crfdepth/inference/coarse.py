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
    (B, 1, H, W) depth map (0 = no return): half the typical gap between returns. Exact but slow (an exact
    distance transform in torch); the model decides with :func:`few_returns`."""
    _, squared = nearest_valid(sparse[:, 0] > 0)
    return squared.flatten(1).to(torch.float32).median(dim=1).values.sqrt()


# The disk of radius SPARSE_DISTANCE (offsets with dx^2 + dy^2 <= 4.5^2) as the union of three rectangles.
_DISK = ((9, 5), (7, 7), (5, 9))
LINE_WINDOW = 4
"""Half-length in pixels of the row and column segments that :func:`line_scan` looks along."""
LINE_RATIO = 1.5
"""Ratio of the two shares in :func:`line_scan` above which the returns lie on scan lines (section 17): 2.2-2.7
for 16 beams on the shared frames (2.2 for the 64-beam official input), 0.99-1.05 for random samples."""
LINE_STRETCH = 2
"""On a line scan the coarse blocks are this many times taller than wide (chosen by cross-validation, section 17)."""
_PAD = max(4, LINE_WINDOW)  # half the largest box asked of the integral image (the disk's 9 pixels, the segments)


class _Boxes:
    """Counts of returns in boxes around every ``stride``-th pixel of every ``stride``-th row of a (B, 1, H, W)
    depth map, each from four reads of one integral image of the returns."""

    def __init__(self, sparse: torch.Tensor, stride: int):
        h, w = sparse.shape[2:]
        counts = (sparse[:, 0] > 0).to(torch.int32).cumsum(1).cumsum(2)
        # integral[y, x]: the returns above and left of (y, x) in the frame padded by _PAD + 1 / _PAD, exclusive
        pad = _PAD
        integral = counts.new_zeros(sparse.shape[0], h + 2 * pad + 1, w + 2 * pad + 1)
        integral[:, pad + 1:pad + 1 + h, pad + 1:pad + 1 + w] = counts
        integral[:, pad + 1 + h:, pad + 1:pad + 1 + w] = counts[:, -1:, :]
        integral[:, pad + 1:, pad + 1 + w:] = integral[:, pad + 1:, pad + w:pad + 1 + w]
        self.integral, self.stride, self.first = integral, stride, stride // 2
        self.rows, self.cols = len(range(stride // 2, h, stride)), len(range(stride // 2, w, stride))

    def _at(self, y: int, x: int) -> torch.Tensor:  # the integral at (y + row, x + col) of every pixel asked
        s, f = self.stride, self.first
        return self.integral[:, y + f:y + f + s * (self.rows - 1) + 1:s, x + f:x + f + s * (self.cols - 1) + 1:s]

    def any_in(self, kh: int, kw: int) -> torch.Tensor:
        """(B, rows, cols) bool: is there a return in the kh x kw box centred on each pixel asked (odd sides)?"""
        top, left = _PAD - kh // 2, _PAD - kw // 2  # the box's corner in the padded frame
        return (self._at(top + kh, left + kw) - self._at(top, left + kw) - self._at(top + kh, left)
                + self._at(top, left)) > 0


def _share(near: torch.Tensor) -> torch.Tensor:
    return near.flatten(1).to(torch.float32).mean(1)


def few_returns(sparse: torch.Tensor, stride: int = 3) -> torch.Tensor:
    """(B,) bool: is the median distance from a pixel to its nearest return above :data:`SPARSE_DISTANCE`?

    ``median_return_distance(sparse) > SPARSE_DISTANCE`` estimated in about a millisecond: are fewer than half
    of the pixels within 4.5 px of a return? The pixels asked are every ``stride``-th of every ``stride``-th row
    (1 asks all of them). The disk of that radius is the union of 9x5, 7x7 and 5x9 rectangles, and the returns
    in each rectangle are counted from one integral image."""
    return _few(_Boxes(sparse, stride))


def line_scan(sparse: torch.Tensor, stride: int = 3) -> torch.Tensor:
    """(B,) bool: do the returns of a (B, 1, H, W) depth map lie along scan lines (a spinning LiDAR's rings)?

    The share of pixels with a return at most :data:`LINE_WINDOW` rows above or below in their column, against
    the share with one as near in their row: on rings a pixel finds the ring above or below it, and only the
    pixels on a ring find one beside them; scattered returns (random samples, a depth camera's holes) are
    found as often both ways. True where the first share is over :data:`LINE_RATIO` times the second. The
    pixels asked are as in :func:`few_returns`."""
    return _lines(_Boxes(sparse, stride))


def returns_layout(sparse: torch.Tensor, stride: int = 3) -> tuple[torch.Tensor, torch.Tensor]:
    """``(few_returns(sparse), line_scan(sparse))`` from one integral image (about a millisecond)."""
    boxes = _Boxes(sparse, stride)
    return _few(boxes), _lines(boxes)


def _few(boxes: _Boxes) -> torch.Tensor:
    near = boxes.any_in(*_DISK[0])
    for kh, kw in _DISK[1:]:
        near |= boxes.any_in(kh, kw)
    return _share(near) < 0.5


def _lines(boxes: _Boxes) -> torch.Tensor:
    span = 2 * LINE_WINDOW + 1
    return _share(boxes.any_in(span, 1)) > LINE_RATIO * _share(boxes.any_in(1, span))


Block = tuple[int, int]
"""A coarse block's (height, width) in pixels."""


def block_shape(side: int, sparse: torch.Tensor, lines: bool | None = None) -> Block:
    """The coarse blocks of ``Structure.coarse = side`` for a batch of depth maps: ``side`` square, or
    :data:`LINE_STRETCH` times as tall where every frame is a :func:`line_scan`, so that a block reaches across
    the gap between rings as far as along them; (1, 1), no coarse solve, where the block grid would be smaller
    than 2 x 2. ``lines``: whether every frame is a line scan, if the caller has read it already."""
    if side <= 1:
        return 1, 1
    if lines is None:
        lines = bool(line_scan(sparse).all())
    shape = (LINE_STRETCH * side, side) if lines else (side, side)
    if min(-(-size // b) for size, b in zip(sparse.shape[2:], shape)) >= 2:
        return shape
    return (side, side) if min(-(-size // side) for size in sparse.shape[2:]) >= 2 else (1, 1)


def coarse_frame(image: torch.Tensor, kept: torch.Tensor, K: torch.Tensor, block: Block, variable: str,
                 offset: tuple[int, int] = (0, 0)) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """``(image, sparse, K)`` of the grid of ``block`` = (height, width) blocks: each block's mean colour, the
    mean of its returns (geometric for ``variable="log"``, arithmetic otherwise; 0 without one) and the
    intrinsics of the coarse pixels. The grid starts ``offset`` = (rows, columns) above and left of the frame
    (:func:`block_mean`); where the frame does not fill a block, edge pixels stand in (image) and no returns
    (depth)."""
    pad = _grid_pad(kept.shape[2:], block, offset)
    kept = F.pad(kept, pad) if any(pad) else kept
    has = kept > 0
    count = F.avg_pool2d(has.to(kept.dtype), block)
    values = torch.where(has, kept.clamp_min(1e-6).log(), torch.zeros_like(kept)) if variable == "log" else kept
    mean = F.avg_pool2d(values, block) / count.clamp_min(1e-12)
    mean = mean.exp() if variable == "log" else mean
    sparse = torch.where(count > 0, mean, torch.zeros_like(mean))
    coarse_K = K.clone()
    for axis, b, o in ((0, block[1], offset[1]), (1, block[0], offset[0])):  # fine u -> coarse (u + o + 0.5) / b - 0.5
        coarse_K[:, axis, :2] = K[:, axis, :2] / b
        coarse_K[:, axis, 2] = (K[:, axis, 2] + o + 0.5) / b - 0.5
    return block_mean(image, block, offset), sparse, coarse_K


def coarse_frames(image: torch.Tensor, kept: torch.Tensor, K: torch.Tensor, block: Block, variable: str,
                  shifts: int) -> list[tuple[tuple[torch.Tensor, torch.Tensor, torch.Tensor], tuple[int, int]]]:
    """``(coarse_frame(..., offset), offset)`` of the grid and, with ``shifts`` = 2, of the grid that starts half
    a block up and left of the frame (cycle spinning, docs/design.md section 17)."""
    offsets = ((0, 0), (block[0] // 2, block[1] // 2))[:shifts]
    return [(coarse_frame(image, kept, K, block, variable, offset), offset) for offset in offsets]


def block_mean(values: torch.Tensor, block: Block, offset: tuple[int, int] = (0, 0)) -> torch.Tensor:
    """The mean of (B, C, H, W) ``values`` over each block of :func:`coarse_frame`'s grid, which starts ``offset`` =
    (rows, columns) above and left of the frame: the frame is padded by its edge pixels there and on the right
    and bottom up to a whole block."""
    pad = _grid_pad(values.shape[2:], block, offset)
    return F.avg_pool2d(F.pad(values, pad, mode="replicate") if any(pad) else values, block)


def _grid_pad(size: tuple[int, int], block: Block, offset: tuple[int, int]) -> tuple[int, int, int, int]:
    """``F.pad``'s (left, right, top, bottom) that puts a frame of ``size`` on a whole grid of ``block``s that
    starts ``offset`` above and left of it."""
    (h, w), (bh, bw), (dy, dx) = size, block, offset
    return dx, -(w + dx) % bw, dy, -(h + dy) % bh


def paint(depth: torch.Tensor, block: Block, size: tuple[int, int], offset: tuple[int, int] = (0, 0)
          ) -> torch.Tensor:
    """The (B, 1, h, w) depth of ``block`` = (height, width) blocks back at full resolution ``size``, bilinear
    between block centres; ``offset``: of the grid, as :func:`coarse_frame`'s."""
    h, w = depth.shape[2:]
    return F.interpolate(depth, size=(h * block[0], w * block[1]), mode="bilinear", align_corners=False)[
        ..., offset[0]:offset[0] + size[0], offset[1]:offset[1] + size[1]]
