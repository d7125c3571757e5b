"""KITTI depth-completion metrics (docs/design.md section 7).

Computed over the pixels where the ground truth is > 0, **per image**, then averaged over
images (the official devkit's way). Units: RMSE and MAE in millimetres, iRMSE and iMAE in
1/km, REL unitless, ``delta1`` the fraction of pixels with ``max(p/g, g/p) < 1.25``.

Uncertainty quality (docs/design.md section 5), per image over the evaluated pixels:
:func:`sparsification` curves and :func:`ause`, the area between an uncertainty's curve
and the oracle's; :func:`uncertainty_metrics`, every number of one image (AUSE and its
ratio to a random order, Spearman rank correlation with ``|error|``, and for a standard
deviation the coverage within 1 and 2 std and the Gaussian and Laplace negative
log-likelihoods); :func:`average_uncertainty`, their mean over images; and
:func:`reliability`, the observed against the Gaussian share within ``k`` std for a
reliability diagram.
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


UNCERTAINTY_METRICS = ("ause", "ause_random", "ause_ratio", "spearman", "coverage_1", "coverage_2", "nll",
                       "nll_laplace")
"""Keys of :func:`uncertainty_metrics` with ``is_std=True``, in order (the first four without)."""

_RATIO_ROUNDING = 1e-9
"""A random AUSE at most this fraction of the RMSE is 0 up to rounding (all ``|error|`` equal)."""


def _as_values(name: str, x) -> np.ndarray:
    """``x`` as a float64 numpy array (no copy when it already is one; never modified)."""
    try:
        return np.asarray(x, dtype=np.float64)
    except (TypeError, ValueError, RuntimeError) as exc:
        raise InputError(f"{name}: expected an array of real numbers, got {type(x).__name__} ({exc})") from None


def _check_error_std(error, std, is_std: bool) -> tuple[np.ndarray, np.ndarray]:
    """``error`` and ``std`` as (N,) float64 arrays, checked: one length N > 0, finite,
    ``std`` > 0 when ``is_std``."""
    e = _as_values("error", error)
    u = _as_values("std", std)
    if e.ndim != 1 or e.size == 0:
        raise InputError(f"error: expected a 1-D array (N,) with N > 0, got shape {e.shape}")
    if u.shape != e.shape:
        raise InputError(f"std: expected the shape of error {e.shape}, got {u.shape}")
    for name, values in (("error", e), ("std", u)):
        bad = int(np.count_nonzero(~np.isfinite(values)))
        if bad:
            raise InputError(f"{name}: expected finite values, got {bad} of {values.size} that are not (nan/inf)")
    if is_std:
        bad = int(np.count_nonzero(u <= 0))
        if bad:
            raise InputError(f"std: expected a standard deviation > 0 at every pixel, got {bad} of {u.size} "
                             f"pixel(s) <= 0")
    return e, u


def _spearman(a: np.ndarray, b: np.ndarray) -> float:
    """Spearman rank correlation (average ranks for ties); nan when either is constant."""
    if np.ptp(a) == 0 or np.ptp(b) == 0:
        return float("nan")
    from scipy.stats import spearmanr  # at first use: importing scipy.stats costs 0.5 s

    return float(spearmanr(a, b).statistic)


def uncertainty_metrics(error: np.ndarray, std: np.ndarray, *, steps: int = SPARSIFY_STEPS,
                        is_std: bool = True) -> dict[str, float]:
    """How well an uncertainty ranks and sizes the errors of one image (docs/design.md section 5).

    Args:
        error: (N,) prediction minus truth at the evaluated pixels (the ground-truth
            pixels), in any unit, e.g. metres; finite.
        std: (N,) the predicted standard deviation at the same pixels, in the unit of
            ``error``, > 0 and finite. With ``is_std=False``, any finite uncertainty score
            where larger means less certain and 0 is allowed (e.g. the paper's count
            map: a few levels, so many ties).
        steps: points of the sparsification curve (:func:`sparsification`), >= 2.
        is_std: whether ``std`` is a standard deviation in the unit of ``error``; only
            then are the coverage and likelihood metrics computed.

    Returns:
        Floats, in the order of :data:`UNCERTAINTY_METRICS`:

        - ``ause``, ``ause_random``: :func:`ause` of ``std`` and of a random order, in
          the unit of ``error``;
        - ``ause_ratio``: ``ause / ause_random``, 0 for a perfect ranking, about 1 for a
          random one; **nan** when ``ause_random`` is 0 (up to rounding: at most 1e-9 of
          the RMSE), i.e. every ``|error|`` is equal and no order beats another;
        - ``spearman``: Spearman rank correlation of ``std`` with ``|error|`` (ties get
          their average rank), in [-1, 1]; **nan** when ``std`` or ``|error|`` is constant;

        and with ``is_std`` only:

        - ``coverage_1``, ``coverage_2``: the share of pixels with ``|error| <= std`` and
          ``<= 2 std`` (0.683 and 0.954 for a calibrated Gaussian);
        - ``nll``: mean Gaussian negative log-likelihood per pixel,
          ``0.5 log(2 pi std^2) + error^2 / (2 std^2)``, in nats, for densities in the
          unit of ``error`` (it shifts by ``log 1000`` between metres and millimetres);
        - ``nll_laplace``: mean Laplace negative log-likelihood with the same std (scale
          ``b = std / sqrt(2)``), ``log(2 b) + |error| / b``, in nats, same unit.

    Raises:
        InputError: ``error`` not 1-D or empty, ``std`` of another shape, non-finite
            values, ``std`` <= 0 somewhere with ``is_std``, or ``steps`` < 2.
    """
    if not isinstance(is_std, bool):
        raise InputError(f"is_std: expected True or False, got {is_std!r}")
    if isinstance(steps, bool) or not isinstance(steps, (int, np.integer)) or steps < 2:
        raise InputError(f"steps: expected an integer >= 2, got {steps!r}")
    e, u = _check_error_std(error, std, is_std)
    a = ause(e, u, int(steps))
    rmse = float(np.sqrt(np.mean(e ** 2)))
    ratio = a["ause"] / a["ause_random"] if a["ause_random"] > _RATIO_ROUNDING * rmse else float("nan")
    out = {"ause": a["ause"], "ause_random": a["ause_random"], "ause_ratio": ratio,
           "spearman": _spearman(u, np.abs(e))}
    if is_std:
        z = np.abs(e) / u
        b = u / np.sqrt(2.0)
        out.update({
            "coverage_1": float(np.mean(np.abs(e) <= u)),
            "coverage_2": float(np.mean(np.abs(e) <= 2.0 * u)),
            "nll": float(np.mean(0.5 * np.log(2.0 * np.pi * u ** 2) + 0.5 * z ** 2)),
            "nll_laplace": float(np.mean(np.log(2.0 * b) + np.abs(e) / b)),
        })
    return out


def average_uncertainty(per_image: list[dict[str, float]]) -> dict[str, float]:
    """Mean over images of :func:`uncertainty_metrics` results.

    Every key is the plain mean over images (a nan of one image, e.g. the Spearman of a
    constant std, makes the mean nan), except ``ause_ratio``: it is recomputed from the
    averaged areas, ``mean(ause) / mean(ause_random)`` (nan when that is 0), the ratio a
    benchmark table reports, not the mean of the per-image ratios.

    Raises:
        InputError: ``per_image`` is empty or its dicts have different keys.
    """
    if len(per_image) == 0:
        raise InputError("per_image: expected at least one image's uncertainty_metrics, got an empty list")
    keys = list(per_image[0])
    for i, item in enumerate(per_image):
        if set(item) != set(keys):
            raise InputError(f"per_image: expected the keys of image 0 {sorted(keys)} in every image, "
                             f"got {sorted(item)} for image {i}")
    out = {k: float(np.mean([item[k] for item in per_image])) for k in keys}
    if "ause_ratio" in out:
        out["ause_ratio"] = out["ause"] / out["ause_random"] if out["ause_random"] > 0 else float("nan")
    return out


def reliability(error: np.ndarray, std: np.ndarray, ks=None) -> dict[str, np.ndarray]:
    """Observed against Gaussian share of ``|error| <= k std``, for a reliability diagram.

    Args:
        error: (N,) prediction minus truth at the evaluated pixels, any unit; finite.
        std: (N,) predicted standard deviation, same unit, > 0 and finite.
        ks: (K,) multiples of the std, finite and >= 0; None = 0, 0.1, ..., 3 (31 values).

    Returns:
        ``{"k": (K,), "observed": (K,), "expected": (K,)}`` float64 arrays: the share of
        pixels with ``|error| <= k std`` (at ``k = 1`` and 2 the ``coverage_1`` and
        ``coverage_2`` of :func:`uncertainty_metrics`), and ``erf(k / sqrt(2))``, the share
        for a calibrated Gaussian. A calibrated std puts ``observed`` on ``expected``;
        above it the std is too large, below it too small.

    Raises:
        InputError: bad ``error`` / ``std`` (as :func:`uncertainty_metrics`), or ``ks``
            not a 1-D array of finite values >= 0.
    """
    e, u = _check_error_std(error, std, is_std=True)
    k = np.linspace(0.0, 3.0, 31) if ks is None else np.array(_as_values("ks", ks), copy=True)
    if k.ndim != 1 or k.size == 0 or not np.all(np.isfinite(k)) or np.any(k < 0):
        raise InputError(f"ks: expected a non-empty 1-D array of finite multiples >= 0, got shape {k.shape}"
                         + (f" with values from {k.min()} to {k.max()}" if k.size else ""))
    abs_e = np.abs(e)
    observed = np.array([np.mean(abs_e <= kk * u) for kk in k])
    return {"k": k, "observed": observed, "expected": torch.special.erf(torch.from_numpy(k / np.sqrt(2.0))).numpy()}


# -- data --------------------------------------------------------------------------------
