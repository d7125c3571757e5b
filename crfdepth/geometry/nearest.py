"""The nearest valid pixel of every pixel: exact Euclidean, in torch on any device (docs/design.md section 10).

The nearest-LiDAR fill (:mod:`crfdepth.fill.nearest`) and the predictive std's distance signal
(:mod:`crfdepth.uncertainty.predictive`) both need, for each pixel, the nearest pixel holding a
return. On the CPU SciPy's and OpenCV's distance transforms do this in C (12 ms and 2 ms
at 1216x352) and are used there. On other devices this module does it without leaving
the device, exactly, in two separable passes (the idea of the separable exact
distance transforms):

1. down each column, the nearest valid row (``g``: one running maximum of row indices
   from above and one from below, :func:`torch.cummax`);
2. along each row, ``d^2(x) = min_s s^2 + g^2(x + s)`` over shifts ``s``, both signs, with
   ``s`` growing until ``s^2`` exceeds every pixel's best ``d^2`` so far (no pixel can
   then improve).

The second pass takes the shifts in blocks. A block is a strided view of the padded rows
(:meth:`torch.Tensor.unfold`, no copy) that holds, for every pixel, the columns
``x + s .. x + s + S - 1`` (and as many to the left); one reduction over it finds the best.
A KITTI frame's largest distance (its empty sky) is about 130 pixels: two or three blocks
replace 130 steps of about 20 small kernels each, which left a GPU waiting on kernel
launches. A block holds at most ``_BLOCK_ENTRIES`` candidates per side, so a large frame or
batch takes narrower blocks rather than more memory. Distances are exact integers
(squared); among equally near pixels the choice can differ from SciPy's.
"""

from __future__ import annotations

import torch

__all__ = ["nearest_valid"]

_MAX_BLOCK = 64  # shifts per block at most
_BLOCK_ENTRIES = 1 << 25  # candidates per side of a block at most (128 MiB of int32)


def _column_pass(valid: torch.Tensor, big: int) -> tuple[torch.Tensor, torch.Tensor]:
    """(B, H, W) bool -> the squared row distance to the nearest valid pixel of the column
    (``big`` where the column has none) and that pixel's row, both int64."""
    _, h, _ = valid.shape
    rows = torch.arange(h, device=valid.device).view(1, h, 1).expand_as(valid)
    above = torch.where(valid, rows, -1).cummax(1).values  # last valid row at or above, -1: none
    below_flipped = torch.where(valid.flip(1), rows, -1).cummax(1).values
    below = torch.where(below_flipped >= 0, h - 1 - below_flipped, -1).flip(1)  # first valid row at or below
    up = torch.where(above >= 0, (rows - above) ** 2, big)
    down = torch.where(below >= 0, (below - rows) ** 2, big)
    take_up = up <= down
    return torch.where(take_up, up, down), torch.where(take_up, above, below)


def _pad_columns(x: torch.Tensor, width: int, value: int) -> torch.Tensor:
    """(B, H, W) -> (B, H, W + 2 width) with ``value`` on both sides."""
    out = x.new_full((*x.shape[:2], x.shape[2] + 2 * width), value)
    out[:, :, width:width + x.shape[2]] = x
    return out


def nearest_valid(valid: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """For each pixel, the nearest pixel (Euclidean, in pixels) where ``valid`` is True.

    Args:
        valid: (B, H, W) bool; a frame may have no valid pixel.

    Returns:
        ``index`` (B, H, W) int64 flat index ``row * W + col`` of that pixel within its
        frame (a valid pixel is its own), and ``squared`` (B, H, W) int64 squared distance
        in pixels^2; in a frame without any valid pixel ``index`` is -1 and ``squared``
        is ``(H + W)^2 + 1``.
    """
    b, h, w = valid.shape
    big = (h + w) ** 2 + 1  # beyond any squared distance in the image
    # candidates reach big + w^2: int32 holds them up to h + w of about 37,000 pixels
    dtype = torch.int32 if big + w * w < 2**31 else torch.int64
    best, best_row = _column_pass(valid, big)
    best, best_row = best.to(dtype), best_row.to(dtype)
    cols = torch.arange(w, device=valid.device, dtype=dtype).view(1, 1, w)
    best_col = cols.expand(b, h, w).clone()
    g = _pad_columns(best, w, big)  # column x of the image is column x + w here
    g_row = _pad_columns(best_row, w, -1)
    empty = ~valid.flatten(1).any(1).view(b, 1, 1)  # frames without a valid pixel: nothing to find
    block = max(1, min(_MAX_BLOCK, _BLOCK_ENTRIES // max(1, b * h * w)))
    shift = 1
    while shift < w:
        size = min(block, w - shift)
        steps = torch.arange(shift, shift + size, device=valid.device, dtype=dtype)
        # to the right: entry j of pixel x is column x + shift + j
        right = slice(w + shift, w + shift + w + size - 1)
        # to the left: entry j of pixel x is column x - shift - (size - 1 - j)
        left = slice(w - shift - size + 1, w - shift + w)
        for cut, square, sign in ((right, steps * steps, 1), (left, (steps * steps).flip(0), -1)):
            value, j = (g[:, :, cut].unfold(2, size, 1) + square).min(-1)
            better = value < best
            offset = shift + j if sign > 0 else -(shift + size - 1 - j)
            row = torch.gather(g_row[:, :, cut].unfold(2, size, 1), 3, j.unsqueeze(-1)).squeeze(-1)
            best = torch.where(better, value, best)
            best_row = torch.where(better, row, best_row)
            best_col = torch.where(better, cols + offset, best_col)
        shift += size
        if shift * shift > int(best.masked_fill(empty, 0).max()):
            break
    best, best_row, best_col = best.long(), best_row.long(), best_col.long()
    index = torch.where(best < big, best_row * w + best_col, -1)
    return index, torch.where(best < big, best, big)
