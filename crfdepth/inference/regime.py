"""The default model's second regime: frames with few returns go to another model (docs/design.md section 17).

:meth:`CRFDepth.from_pretrained <crfdepth.model.CRFDepth.from_pretrained>` gives the shipped weights a
``sparse_regime``: the hand-set weights on the pixel grid with a coarse first solve
(:mod:`crfdepth.inference.coarse`). A frame whose median distance to the nearest return exceeds
:data:`~crfdepth.inference.coarse.SPARSE_DISTANCE` pixels (:func:`~crfdepth.inference.coarse.few_returns`;
500 or 200 samples, 16 beams) is completed by it,
a denser one (a 64-beam scan, an RGB-D depth image) by the shipped weights. A batch that mixes both is split
and its outputs merged frame by frame (:func:`merge_outputs`).
"""

from __future__ import annotations

import torch

from crfdepth.output import CRFOutput


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
