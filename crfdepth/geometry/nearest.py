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
   then improve); one batched tensor step per shift.

The second pass costs one step per pixel of the largest distance in the batch (about 130
shifts for a KITTI frame's empty sky), which is cheap on a GPU and slower than SciPy on a
CPU. Distances are exact integers (squared); among equally near pixels the choice can
differ from SciPy's.
"""

from __future__ import annotations

import torch

__all__ = ["nearest_valid"]

_CHECK_EVERY = 8  # shifts between the checks of the stopping rule (each check synchronises a GPU)


def _column_pass(valid: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """(B, H, W) bool -> the squared row distance to the nearest valid pixel of the column
    (``big`` where the column has none) and that pixel's row, both int64."""
    _, h, _ = valid.shape
    rows = torch.arange(h, device=valid.device).view(1, h, 1).expand_as(valid)
    above = torch.where(valid, rows, -1).cummax(1).values  # last valid row at or above, -1: none
    below_flipped = torch.where(valid.flip(1), rows, -1).cummax(1).values
    below = torch.where(below_flipped >= 0, h - 1 - below_flipped, -1).flip(1)  # first valid row at or below
    big = (h + valid.shape[2]) ** 2 + 1  # beyond any squared distance in the image
    up = torch.where(above >= 0, (rows - above) ** 2, big)
    down = torch.where(below >= 0, (below - rows) ** 2, big)
    take_up = up <= down
    return torch.where(take_up, up, down), torch.where(take_up, above, below)


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
    best, best_row = _column_pass(valid)
    cols = torch.arange(w, device=valid.device).view(1, 1, w).expand(b, h, w)
    best_col = cols.clone()
    g, g_row = best.clone(), best_row.clone()
    big = (h + w) ** 2 + 1
    empty = ~valid.flatten(1).any(1).view(b, 1, 1)  # frames without a valid pixel: nothing to find
    shift = 1
    while shift < w:
        for sign in (1, -1):
            # pixel x looks at column x + sign * shift
            if sign > 0:
                here, there = (slice(None), slice(None), slice(0, w - shift)), (slice(None), slice(None), slice(shift, w))
            else:
                here, there = (slice(None), slice(None), slice(shift, w)), (slice(None), slice(None), slice(0, w - shift))
            candidate = g[there] + shift * shift
            better = candidate < best[here]
            best[here] = torch.where(better, candidate, best[here])
            best_row[here] = torch.where(better, g_row[there], best_row[here])
            best_col[here] = torch.where(better, cols[there], best_col[here])
        shift += 1
        if shift % _CHECK_EVERY == 0 and shift * shift > int(best.masked_fill(empty, 0).max()):
            break
    index = torch.where(best < big, best_row * w + best_col, -1)
    return index, torch.where(best < big, best, big)
