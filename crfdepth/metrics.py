"""KITTI depth-completion metrics (docs/design.md section 7).

Computed over the pixels where the ground truth is > 0, **per image**, then averaged over
images (the official devkit's way). Units: RMSE and MAE in millimetres, iRMSE and iMAE in
1/km, REL unitless, ``delta1`` the fraction of pixels with ``max(p/g, g/p) < 1.25``.

Uncertainty quality (docs/design.md section 5): :func:`sparsification` curves and
:func:`ause`, the area between an uncertainty's curve and the oracle's.
"""

from __future__ import annotations

import numpy as np
import torch

from crfdepth.errors import InputError

METRICS = ("rmse", "mae", "irmse", "imae", "rel", "delta1")
UNITS = {"rmse": "mm", "mae": "mm", "irmse": "1/km", "imae": "1/km", "rel": "", "delta1": ""}


def _as_batch(name: str, t: torch.Tensor) -> torch.Tensor:
    if not isinstance(t, torch.Tensor):
        raise InputError(f"{name}: expected a torch.Tensor, got {type(t).__name__}")
    if t.dim() == 2:
        return t[None]
    if t.dim() == 4 and t.shape[1] == 1:
        return t[:, 0]
    if t.dim() == 3:
        return t
    raise InputError(f"{name}: expected shape (H, W), (B, H, W) or (B, 1, H, W), got {tuple(t.shape)}")


def depth_metrics(pred: torch.Tensor, target: torch.Tensor) -> dict[str, torch.Tensor]:
    """Per-image KITTI metrics.

    Args:
        pred: predicted z-depth in metres, (H, W), (B, H, W) or (B, 1, H, W); must be
            > 0 and finite wherever ``target`` > 0.
        target: ground-truth z-depth in metres, same shape; 0 = no ground truth.

    Returns:
        ``{name: (B,) float64 tensor}`` for ``rmse`` (mm), ``mae`` (mm), ``irmse`` (1/km),
        ``imae`` (1/km), ``rel`` and ``delta1``, plus ``pixels`` (B,) the number of
        ground-truth pixels of each image.

    Raises:
        InputError: shapes differ, an image has no ground-truth pixel, or the prediction
            is not positive and finite on ground-truth pixels.
    """
    p = _as_batch("pred", pred).detach().double()
    g = _as_batch("target", target).detach().double()
    if p.shape != g.shape:
        raise InputError(f"pred: expected the shape of target {tuple(g.shape)}, got {tuple(p.shape)}")
    valid = g > 0
    counts = valid.flatten(1).sum(1)
    if bool((counts == 0).any()):
        empty = torch.nonzero(counts == 0).flatten().tolist()
        raise InputError(f"target: image(s) {empty} have no ground-truth pixel (> 0); nothing to evaluate")
    p_valid = torch.where(valid, p, torch.ones_like(p))
    if not bool(torch.isfinite(p_valid).all()) or bool((p_valid <= 0).any()):
        bad = int(((p_valid <= 0) | ~torch.isfinite(p_valid)).sum())
        raise InputError(f"pred: expected finite depth > 0 at ground-truth pixels, got {bad} pixel(s) that are not")
    g_safe = torch.where(valid, g, torch.ones_like(g))
    n = counts.double()

    def mean(x: torch.Tensor) -> torch.Tensor:
        return torch.where(valid, x, torch.zeros_like(x)).flatten(1).sum(1) / n

    err = p_valid - g_safe
    inv_err = 1.0 / p_valid - 1.0 / g_safe
    ratio = torch.maximum(p_valid / g_safe, g_safe / p_valid)
    return {
        "rmse": mean(err ** 2).sqrt() * 1000.0,
        "mae": mean(err.abs()) * 1000.0,
        "irmse": mean(inv_err ** 2).sqrt() * 1000.0,
        "imae": mean(inv_err.abs()) * 1000.0,
        "rel": mean(err.abs() / g_safe),
        "delta1": mean((ratio < 1.25).double()),
        "pixels": counts,
    }


def average_metrics(per_image: dict[str, torch.Tensor]) -> dict[str, float]:
    """Mean over images of :func:`depth_metrics` results (``pixels`` is summed)."""
    out = {k: float(v.double().mean()) for k, v in per_image.items() if k != "pixels"}
    if "pixels" in per_image:
        out["pixels"] = int(per_image["pixels"].sum())
    return out


def format_metrics(metrics: dict[str, float]) -> str:
    """One line, e.g. ``RMSE 1234.5 mm | MAE 321.0 mm | iRMSE 3.21 1/km | ...``."""
    names = {"rmse": "RMSE", "mae": "MAE", "irmse": "iRMSE", "imae": "iMAE", "rel": "REL", "delta1": "d<1.25"}
    parts = []
    for key in METRICS:
        if key in metrics:
            value = metrics[key]
            text = f"{value:.1f}" if key in ("rmse", "mae") else f"{value:.4f}" if key in ("rel", "delta1") else f"{value:.2f}"
            parts.append(f"{names[key]} {text}{(' ' + UNITS[key]) if UNITS[key] else ''}")
    return " | ".join(parts)


# --------------------------------------------------------------------------- uncertainty

SPARSIFY_STEPS = 100
"""Points of a sparsification curve: removed fractions 0, 0.01, ..., 0.99."""


def sparsification(error: np.ndarray, uncertainty: np.ndarray, steps: int = SPARSIFY_STEPS) -> np.ndarray:
    """RMSE (same unit as ``error``) of the pixels left after removing the most uncertain.

    Args:
        error: (N,) prediction minus truth at the evaluated pixels.
        uncertainty: (N,) predicted uncertainty (std, count map, ...); larger = removed first.
        steps: the curve is sampled at removed fractions ``0, 1/steps, ..., (steps-1)/steps``.

    Returns:
        (steps,) RMSE after removing ``floor(f N)`` pixels. Pixels of equal uncertainty are
        removed in random order *in expectation*: within a tie the removed squared error
        is interpolated linearly, so a coarse map (the 3-level count map) is neither
        favoured nor penalised by the sort order.
    """
    sq = np.asarray(error, dtype=np.float64) ** 2
    u = np.asarray(uncertainty, dtype=np.float64)
    if sq.shape != u.shape or sq.ndim != 1 or sq.size == 0:
        raise InputError(f"error, uncertainty: expected two (N,) arrays of one length N > 0, "
                         f"got shapes {sq.shape} and {u.shape}")
    order = np.argsort(-u, kind="stable")
    u_sorted, sq_sorted = u[order], sq[order]
    # Cumulative removed squared error at the end of every tie group.
    ends = np.flatnonzero(np.r_[u_sorted[1:] != u_sorted[:-1], True]) + 1
    positions = np.r_[0, ends]
    removed = np.r_[0.0, np.cumsum(sq_sorted)[ends - 1]]
    n = sq.size
    k = np.floor(np.arange(steps) / steps * n)
    kept = n - k
    left = np.maximum(sq.sum() - np.interp(k, positions, removed), 0.0)
    return np.sqrt(left / kept)


def ause(error: np.ndarray, uncertainty: np.ndarray, steps: int = SPARSIFY_STEPS) -> dict[str, float]:
    """Area under the sparsification error (docs/design.md section 5) of one image.

    ``ause``: area between the curve of ``uncertainty`` and the oracle curve (ordered by
    ``|error|``) over the removed fraction 0..(steps-1)/steps, trapezoid rule, in the unit
    of ``error``; 0 for an oracle-ordered uncertainty. ``ause_random``: the same for a
    random order (flat curve at the full RMSE), for scale.
    """
    curve = sparsification(error, uncertainty, steps)
    oracle = sparsification(error, np.abs(error), steps)
    f = np.arange(steps) / steps
    flat = np.full_like(oracle, oracle[0])
    return {"ause": float(np.trapezoid(curve - oracle, f)), "ause_random": float(np.trapezoid(flat - oracle, f)),
            "curve": curve, "oracle": oracle}


# -- data --------------------------------------------------------------------------------
