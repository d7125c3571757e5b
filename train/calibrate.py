"""Fitting a trained model's std to real errors (docs/design.md section 5).

:func:`calibrate_std` runs the whole model over a data set and sets the weights of its std:
for the predictive std (the default), the six weights of :mod:`crfdepth.uncertainty.predictive` by
:func:`crfdepth.uncertainty.predictive.fit_std_terms`; for ``uncertainty="posterior"``, the scale
``s`` in closed form (:func:`calibrate_std_scale`). It lives with training, not in the
library's numerical code. ``python -m train.export --calibrate-std`` uses it; it needs no
Lightning. The depth is never changed.
"""

from __future__ import annotations

import math
from typing import Iterable

import torch

from crfdepth.errors import InputError
from crfdepth.uncertainty.predictive import fit_std_terms

__all__ = ["calibrate_std", "calibrate_std_scale", "fit_predictive_std"]


def calibrate_std(model, frames: Iterable, *, apply: bool = True) -> dict:
    """Fit the std of ``model`` (either kind) on ``frames``; returns what was set, before and after.

    ``{"uncertainty", "before", "after", "frames", "method"}``: the std terms (predictive) or
    the scale (posterior).
    """
    frames = list(frames)
    kind = model.settings.uncertainty.kind
    if kind == "posterior":
        before = float(model.std_scale.detach())
        after = calibrate_std_scale(model, frames, apply=apply)
        method = "closed-form Gaussian NLL optimum of the posterior std's scale (train.calibrate.calibrate_std_scale)"
    else:
        before = model.std_head.terms()
        after = fit_predictive_std(model, frames, apply=apply)
        method = ("Laplace NLL of the predictive std's weights, then 68.3% coverage "
                  "(crfdepth.uncertainty.predictive.fit_std_terms via train.calibrate.fit_predictive_std)")
    used = sum(1 for s in frames if bool((s.target > 0).any()))
    return {"uncertainty": kind, "before": before, "after": after, "frames": used, "method": method}


def fit_predictive_std(model, frames: Iterable, *, apply: bool = True) -> dict[str, float]:
    """The weights of the predictive std fitted to ``frames``' errors (:func:`fit_std_terms`).

    Runs ``model`` once per frame under ``no_grad``, keeps its error and std signals at the
    target pixels, fits, and (``apply``) sets ``model.std_head``. Frames without target
    pixels are skipped.

    Raises:
        InputError: no frame has a target pixel, or ``model`` does not compute the predictive std.
    """
    settings = getattr(model, "settings", None)  # a CRFDepth's configuration (crfdepth.config.CRFConfig)
    kind = getattr(getattr(settings, "uncertainty", None), "kind", None)
    if kind != "predictive":
        raise InputError(f"model: expected uncertainty='predictive', got {kind!r}")
    features, errors = [], []
    for out, target, valid in _outputs(model, frames):
        features.append(out.std_features.permute(0, 2, 3, 1)[valid[:, 0]])
        errors.append(out.depth[valid] - target[valid])
    if not errors:
        raise InputError("frames: expected at least one frame with target pixels (> 0), got none")
    terms = fit_std_terms(features, errors, start=model.std_head.terms())
    if apply:
        with torch.no_grad():
            model.std_head.weights.copy_(torch.tensor([terms[k] for k in model.std_head.terms()]))
    return terms


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
    ratios = []
    with torch.no_grad():
        scale = float(model.std_scale)
    for out, target, valid in _outputs(model, frames):
        sigma = (out.std / scale)[valid]
        ratios.append(float(((out.depth[valid] - target[valid]) / sigma).square().mean()))
    if not ratios:
        raise InputError("frames: expected at least one frame with target pixels (> 0), got none")
    calibrated = math.sqrt(sum(ratios) / len(ratios))
    if apply:
        with torch.no_grad():
            model.log_std_scale.fill_(math.log(calibrated))
    return calibrated


def _outputs(model, frames: Iterable):
    """``(output, target, valid)`` per frame with target pixels: ``model`` under ``no_grad`` with
    the std, on its device and dtype; target (1, 1, H, W) metres and its ``> 0`` mask."""
    param = next(model.parameters())
    for s in frames:
        target = s.target[None].to(param)
        valid = target > 0
        if bool(valid.any()):
            with torch.no_grad():
                out = model(s.image[None].to(param), s.sparse[None].to(param), s.K[None].to(param), return_std=True)
            yield out, target, valid
