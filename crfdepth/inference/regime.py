"""The default model's regimes for few returns: such frames go to other models (docs/design.md section 17).

:meth:`CRFDepth.from_pretrained <crfdepth.model.CRFDepth.from_pretrained>` gives the shipped weights three
models on the pixel grid with a coarse first solve (:mod:`crfdepth.inference.coarse`), two with hand-set weights
whose coarse solve runs on two grids half a block apart (``coarse_shifts``):

- ``sparse_regime``, the depth unknown with near blocks of the coarse solve in inverse depth (``near_inverse``):
  frames whose returns are few and scattered (500 or 200 samples);
- ``line_regime``, the log unknown: frames whose few returns lie on scan lines (16 beams;
  :func:`~crfdepth.inference.coarse.line_scan`);
- ``indoor_regime``, the indoor weights (``--weights nyu``, learned on NYU Depth v2 and synthetic rooms): frames
  whose few scattered returns are near (:func:`near_returns`): a depth camera's (Kinect, RealSense), or any
  sensor's in a room.

A frame has few returns when its median distance to the nearest return exceeds
:data:`~crfdepth.inference.coarse.SPARSE_DISTANCE` pixels (:func:`~crfdepth.inference.coarse.few_returns`); a
denser one (a 64-beam scan, an RGB-D depth image) is completed by the shipped weights. A batch that mixes
them is split and its outputs merged frame by frame (:func:`merge_outputs`).
"""

from __future__ import annotations

import math

import torch

from crfdepth.inference.coarse import returns_layout
from crfdepth.output import CRFOutput

REGIMES = ("sparse_regime", "line_regime", "indoor_regime")
"""The attributes of a model that hold its regimes for few returns (None: that regime is the model itself)."""
INDOOR_RANGE = 10.0
"""Metres: few scattered returns whose 90th percentile of depth is within this are a room's (docs/design.md
section 17). A depth camera reads up to about 10 m (NYU's Kinect depth stops there); outdoors a LiDAR's
returns reach further. On the shared frames the 90th percentile is 4.0-6.3 m on NYU's and 14.5-48.6 m on every
KITTI input."""
INDOOR_QUANTILE = 0.9
"""The quantile of a frame's return depths that :func:`near_returns` compares with :data:`INDOOR_RANGE`."""


def near_returns(sparse: torch.Tensor, rows: torch.Tensor) -> torch.Tensor:
    """(B,) bool: does ``rows`` hold the frame and are its returns near, their 90th percentile of depth at most
    :data:`INDOOR_RANGE`? Only the frames in ``rows`` ((B,) bool) are read."""
    near = torch.zeros_like(rows)
    for b in torch.nonzero(rows)[:, 0].tolist():
        depths = sparse[b][sparse[b] > 0]
        k = max(1, math.ceil(INDOOR_QUANTILE * depths.numel()))
        near[b] = bool(depths.kthvalue(k).values <= INDOOR_RANGE)
    return near


def assign(model: torch.nn.Module, sparse: torch.Tensor) -> list[tuple[torch.Tensor, torch.nn.Module, bool | None]]:
    """``(rows, m, lines)`` for each model ``m`` that completes some frames of a (B, 1, H, W) batch: ``rows`` the
    (K,) indices of its frames, ``lines`` whether all of them lie on scan lines (as
    :func:`~crfdepth.inference.coarse.block_shape` would read it; None for frames with many returns, not read).

    ``model`` takes a frame with many returns, else ``model.line_regime`` where its returns lie on scan lines,
    ``model.indoor_regime`` where they are scattered and near (:func:`near_returns`) and ``model.sparse_regime``
    where they are scattered and not near (a regime that is None: ``model``)."""
    few, read = returns_layout(sparse)
    lines = few & read if model.line_regime is not None else torch.zeros_like(few)
    near = near_returns(sparse, few & ~lines) if model.indoor_regime is not None else torch.zeros_like(few)
    choices = ((~few, model), (few & ~lines & ~near, model.sparse_regime), (near, model.indoor_regime),
               (lines, model.line_regime))
    parts = [(torch.nonzero(rows)[:, 0], model if m is None else m, bool(read[rows].all()) if i else None)
             for i, (rows, m) in enumerate(choices) if bool(rows.any())]
    for _, m, _ in parts:
        m.progress = model.progress
    return parts


def _take(parts: list[tuple[torch.Tensor, torch.Tensor | None]], batch: int) -> torch.Tensor | None:
    """The (B, ...) tensor whose frames ``rows`` come from each part's tensor; None if any part has none."""
    if any(t is None for _, t in parts):
        return None
    first = parts[0][1]
    out = first.new_empty((batch, *first.shape[1:]))
    for rows, t in parts:
        out[rows] = t
    return out


def merge_outputs(parts: list[tuple[torch.Tensor, CRFOutput]], batch: int) -> CRFOutput:
    """One :class:`~crfdepth.output.CRFOutput` of a batch of ``batch`` pixel-grid frames from the outputs of its
    parts: ``(rows, output)`` with ``rows`` the (K,) frame indices that ``output`` holds, in its order.

    Per-frame maps (depth, std, count, std features) are put back in batch order, ``node_depth`` /
    ``node_std`` are the merged maps flattened (a pixel grid's nodes are its pixels), the solves' ``info``
    and ``timings`` are those of all parts, and ``terms`` (one system per part, not one of the batch) is None.
    """
    depth = _take([(rows, out.depth) for rows, out in parts], batch)
    std = _take([(rows, out.std) for rows, out in parts], batch)
    h, w = depth.shape[2:]
    timings: dict[str, float] = {}
    for _, out in parts:
        for name, seconds in out.timings.items():
            timings[name] = timings.get(name, 0.0) + seconds
    return CRFOutput(depth, std, _take([(rows, out.count_uncertainty) for rows, out in parts], batch),
                     depth.reshape(-1), None if std is None else std.reshape(-1),
                     torch.arange(batch + 1, device=depth.device) * (h * w), None, None,
                     [info for _, out in parts for info in out.info], timings,
                     _take([(rows, out.std_features) for rows, out in parts], batch))
