"""The closed-form std-scale calibration of a trained model (docs/design.md section 5).

It runs the whole model over a data set and sets one of its parameters, so it lives with
training, not in the library's numerical code. ``python -m train.export --calibrate-std``
uses it; it needs no Lightning.
"""

from __future__ import annotations

import math
from typing import Iterable

import torch

from crfdepth.errors import InputError

__all__ = ["calibrate_std_scale"]


def calibrate_std_scale(model, frames: Iterable, *, apply: bool = True) -> float:
    """The std scale ``s`` that minimises the Gaussian NLL of ``frames``' targets, in closed form.

    The predictive std is ``s * sigma`` with ``sigma = sqrt(diag(A^-1))`` (docs/design.md
    section 5). The per-image mean NLL averaged over images, ``log s + mean(log sigma) +
    M / (2 s^2)`` with ``M`` the mean over images of ``mean((x - t)^2 / sigma^2)`` over
    the target pixels, is minimal at ``s = sqrt(M)``: the same objective as the trainer's
    NLL term, solved exactly instead of by gradient steps. The depth is not changed.

    Args:
        model: a :class:`~crfdepth.model.CRFDepth` (any mode); run under ``no_grad`` in
            its current train/eval mode, on its device and dtype.
        frames: iterable of :class:`~crfdepth.data.sample.Sample` (image, sparse, K and
            a target depth in metres, 0 = no target), e.g. a crfdepth dataset. Frames
            without target pixels are skipped.
        apply: also set the model's scale to the result.

    Returns:
        The calibrated ``s`` (> 0).

    Raises:
        InputError: no frame has a target pixel.
    """
    param = next(model.parameters())
    ratios = []
    with torch.no_grad():
        scale = float(model.std_scale)
        for s in frames:
            target = s.target[None].to(param)
            valid = target > 0
            if not bool(valid.any()):
                continue
            out = model(s.image[None].to(param), s.sparse[None].to(param), s.K[None].to(param), return_std=True)
            sigma = (out.std / scale)[valid]
            ratios.append(float(((out.depth[valid] - target[valid]) / sigma).square().mean()))
        if not ratios:
            raise InputError("frames: expected at least one frame with target pixels (> 0), got none")
        calibrated = math.sqrt(sum(ratios) / len(ratios))
        if apply:
            model.log_std_scale.fill_(math.log(calibrated))
    return calibrated
