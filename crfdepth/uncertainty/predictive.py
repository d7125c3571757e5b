"""The predictive standard deviation: the posterior's local part plus what it cannot see (docs/design.md section 5).

The posterior of the Gaussian CRF, ``diag(A^-1)``, measures how far a pixel is from data
through the graph. The large errors are elsewhere: at depth edges (a boundary misplaced by
a pixel costs the whole step), at see-through returns and misaligned points (the data
themselves are wrong), and they grow with range. The predictive std therefore combines
per-pixel signals, each a map computed from the solution and the LiDAR without gradient:

============  ================================================================  ======
term          signal                                                             offset
============  ================================================================  ======
``depth``     the depth ``z`` (m): range noise and the relative unknown grow     0
``posterior`` conditional variance ``1 / A_ii`` of the last solve, in (log z)^2  1e-6
``distance``  distance to the nearest kept LiDAR return, pixels                  1
``edge``      local step of the solution: max - min of log z in a 5x5 window     0.01
``gate``      occlusion gate disagreement: max over a 15x15 window of            0.01
              ``(1 - g) * max(log z_return - log x, 0)`` (0 without the gate)
============  ================================================================  ======

through a log-linear model, ``log std = bias + sum_k c_k log(f_k + offset_k)``: a product
of powers of the signals, so every term scales the std multiplicatively and the weights
are comparable. The conditional variance ``1 / A_ii`` is the exact lower bound of the
posterior variance (the variance of a pixel given its neighbours) and costs nothing; the
sampled posterior (:mod:`crfdepth.uncertainty.posterior`) costs 40 solves and is the model's
``uncertainty="posterior"`` option. On the CPU the pixel grid's std is one compiled pass where the
kernels are built (:func:`grid_std_compiled`, :mod:`crfdepth.native`; about 4 ms at 1216x352 against
15-20 ms for these functions), with the same numbers; these functions are its reference.

The model's std adds, in quadrature, the range noise of the LiDAR itself
(:data:`RANGE_NOISE_M`, 2 cm, the 1-sigma accuracy automotive scanners state): on a return
the CRF is pinned to the return and every signal is small, but the truth differs from the
return by the sensor's noise. It is a constant, not fitted: the fit's targets (held-out
returns) never sit on an input return, so they cannot show it (docs/design.md section 5).

The six weights are fitted by :func:`fit_std_terms`: the Laplace negative log-likelihood
(convex in the weights for this model), then the bias is moved so that 68.3% of the fitted
errors lie within one std, as for a Gaussian (errors are heavier-tailed than Laplace's, so
the NLL optimum alone puts 83-95% inside one std: docs/design.md section 5).
"""

from __future__ import annotations

import math
from typing import Mapping, Sequence

import cv2
import numpy as np
import torch
from torch import nn

from crfdepth.config import DEFAULT_STD_TERMS, STD_TERMS, check_std_terms  # the names the configuration checks
from crfdepth.errors import InputError
from crfdepth.geometry.nearest import nearest_valid
from crfdepth.geometry.windows import window_max
from crfdepth.native import kernels

__all__ = ["DEFAULT_STD_TERMS", "RANGE_NOISE_M", "STD_TERMS", "PredictiveStd", "check_std_terms", "fit_std_terms",
           "grid_std_compiled", "predictive_std", "std_features"]

SIGNALS = STD_TERMS[1:]
OFFSETS = {"depth": 0.0, "posterior": 1e-6, "distance": 1.0, "edge": 0.01, "gate": 0.01}
"""Added to each signal before its log: the value below which a signal stops mattering."""
EDGE_WINDOW, LIDAR_WINDOW = 5, 15
COVERAGE = math.erf(1 / math.sqrt(2))  # 0.6827: a Gaussian's share within one std
RANGE_NOISE_M = 0.02
"""The LiDAR's own range noise, metres (1 sigma), added in quadrature by :class:`PredictiveStd`."""


def _log(x: torch.Tensor) -> torch.Tensor:
    return x.clamp_min(1e-3).log()


def _distance(missing: np.ndarray) -> np.ndarray:
    """Euclidean distance in pixels to the nearest ``False`` of an (H, W) mask (OpenCV's precise mask,
    within 1e-4 of exact); the image diagonal where there is none."""
    if missing.all():
        return np.full(missing.shape, float(np.hypot(*missing.shape)), dtype=np.float32)
    return cv2.distanceTransform(missing.astype(np.uint8), cv2.DIST_L2, cv2.DIST_MASK_PRECISE)


def return_distance(kept: torch.Tensor) -> torch.Tensor:
    """(B, 1, H, W) distance in pixels to the nearest return of ``kept`` (the image diagonal in a frame
    without one): OpenCV's precise transform on the CPU (within 1e-4 of the exact distance; 3 ms at 1216x352),
    :func:`crfdepth.geometry.nearest.nearest_valid` elsewhere. The compiled fill finds it exactly with the fill."""
    if kept.device.type == "cpu":
        missing = (kept[:, 0] <= 0).numpy()
        return torch.from_numpy(np.stack([_distance(m) for m in missing])[:, None]).to(kept.dtype)
    _, squared = nearest_valid(kept[:, 0] > 0)
    h, w = kept.shape[-2:]
    none = squared > (h + w) ** 2
    return torch.where(none, float(np.hypot(h, w)), squared.to(kept.dtype).sqrt())[:, None]


def std_features(depth: torch.Tensor, sparse: torch.Tensor, kept: torch.Tensor, gate: torch.Tensor | None,
                 conditional_variance: torch.Tensor) -> torch.Tensor:
    """The signals of the module docstring, (B, 5, H, W) in the order of ``STD_TERMS[1:]``, detached.

    Args:
        depth: (B, 1, H, W) the solution, metres > 0.
        sparse: (B, 1, H, W) LiDAR depth in metres, 0 = none; kept: the same without the
            returns the occlusion gate rejects.
        gate: (B, 1, H, W) the occlusion gate (1 off the returns) or None.
        conditional_variance: (B, 1, H, W) ``1 / A_ii`` of the last solve in (log depth)^2.
    """
    with torch.no_grad():
        log_x = _log(depth)
        edge = window_max(log_x, EDGE_WINDOW) + window_max(-log_x, EDGE_WINDOW)
        if gate is None:
            disagreement = torch.zeros_like(depth)
        else:
            behind = ((_log(sparse) - log_x).clamp_min(0) * (1 - gate.detach())) * (sparse > 0).to(depth.dtype)
            disagreement = window_max(behind, LIDAR_WINDOW)
        distance = return_distance(kept)
        return torch.cat([depth, conditional_variance.to(depth), distance, edge, disagreement], 1)


_POWER = {"depth": 0, "log": 1, "inverse": 2}  # std_in_metres: std_z = z^power std of the unknown


def grid_std_compiled(head: "PredictiveStd", depth: torch.Tensor, sparse: torch.Tensor, kept: torch.Tensor,
                      gate: torch.Tensor | None, distance: torch.Tensor | None, diagonal: torch.Tensor, weight_h: torch.Tensor,
                      weight_v: torch.Tensor, variable: str) -> tuple[torch.Tensor, torch.Tensor] | None:
    """``(head(features), features)`` of a pixel-grid solve in one compiled pass (:mod:`crfdepth.native`): the
    conditional variance ``1 / A_ii`` of the system ``diagonal``, ``weight_h``, ``weight_v`` (the unknown's
    units, ``variable``), :func:`std_features` and :class:`PredictiveStd`, the same numbers as those; None
    where it does not apply (not on the CPU, no kernels, the kernel failed): the caller runs them instead.

    ``kept``: ``sparse`` without the returns the gate rejects; ``distance``: (B, 1, H, W) pixels to the nearest
    of them if the fill found it, else None (searched here). With a gradient wanted for ``head``'s weights, the std is ``head(features)`` in torch.
    """
    native = kernels() if depth.device.type == "cpu" and depth.dtype in (torch.float32, torch.float64) else None
    if native is None:
        return None
    dtype = depth.dtype

    def plain(t: torch.Tensor) -> torch.Tensor:
        return t.detach().to(dtype).contiguous()

    if distance is None:
        found = native.nearest_fill(plain(kept[:, 0]))
        if found is None:
            return None
        distance = found[1][:, None]
    weights = [float(v) for v in head.weights.detach().double().tolist()]
    done = native.predictive_std(plain(depth), plain(sparse), torch.empty(0, dtype=dtype) if gate is None else plain(gate),
                                 plain(distance), plain(diagonal), plain(weight_h), plain(weight_v), _POWER[variable],
                                 weights, RANGE_NOISE_M, EDGE_WINDOW, LIDAR_WINDOW)
    if done is None:
        return None
    std, features = done
    if torch.is_grad_enabled() and head.weights.requires_grad:
        std = head(features)  # the weights' gradient; the signals carry none
    return std, features


def predictive_std(features: torch.Tensor, weights: torch.Tensor) -> torch.Tensor:
    """``exp(bias + sum_k c_k log(f_k + offset_k))``: (B, 5, H, W) or (N, 5) features -> (B, 1, H, W) or (N,).

    Differentiable in ``weights`` (6,) (order of :data:`STD_TERMS`), not in the features.
    """
    shape = (1, -1, 1, 1) if features.dim() == 4 else (1, -1)
    c = weights[1:].to(features).view(shape)
    out = weights[0].to(features) + (c * _log_signals(features)).sum(1, keepdim=features.dim() == 4)
    return out.exp()


def _log_signals(features: torch.Tensor) -> torch.Tensor:
    """``log(f_k + offset_k)`` of (B, 5, H, W) or (N, 5) signals."""
    shape = (1, -1, 1, 1) if features.dim() == 4 else (1, -1)
    return (features + features.new_tensor([OFFSETS[k] for k in SIGNALS]).view(shape)).clamp_min(1e-12).log()


class PredictiveStd(nn.Module):
    """The learnable weights of :func:`predictive_std` (``weights``, (6,), order of :data:`STD_TERMS`).

    Args:
        terms: initial weights by name (all of :data:`STD_TERMS`), or None for
            :data:`DEFAULT_STD_TERMS`.
    """

    def __init__(self, terms: Mapping[str, float] | None = None) -> None:
        super().__init__()
        values = check_std_terms(terms)
        self.weights = nn.Parameter(torch.tensor([values[k] for k in STD_TERMS]))

    def terms(self) -> dict[str, float]:
        """The current weights by name (JSON-friendly)."""
        return {k: float(v) for k, v in zip(STD_TERMS, self.weights.detach().double().tolist())}

    def forward(self, features: torch.Tensor) -> torch.Tensor:
        """``sqrt(predictive_std^2 + RANGE_NOISE_M^2)``, metres: (B, 5, H, W) -> (B, 1, H, W)."""
        return torch.sqrt(predictive_std(features, self.weights) ** 2 + RANGE_NOISE_M ** 2)


def fit_std_terms(features: Sequence[torch.Tensor], errors: Sequence[torch.Tensor], *,
                  start: Mapping[str, float] | None = None, max_iter: int = 50) -> dict[str, float]:
    """Weights of :func:`predictive_std` fitted to errors by Laplace NLL, then set to 68.3% coverage.

    Minimises the mean over frames of the per-pixel Laplace NLL ``log(2 b) + |e| / b`` with
    ``b = std / sqrt(2)`` (convex: ``log std`` is linear in the weights) by Newton's method in float64,
    then adds to ``bias`` the log of the ratio ``|e| / std`` below which 68.3% of the pixels
    lie (each frame weighted equally), so one std covers what it covers for a Gaussian.

    Args:
        features: per frame an (N_i, 5) tensor of :func:`std_features` at its target pixels.
        errors: per frame (N_i,) prediction minus target in metres.
        start: initial weights (None: :data:`DEFAULT_STD_TERMS`).
        max_iter: most Newton steps (it stops earlier once a step gains < 1e-12).

    Returns:
        The weights by name.

    Raises:
        InputError: no frame with a target pixel, mismatched lengths, non-finite values.
    """
    if len(features) != len(errors):
        raise InputError(f"features, errors: expected one entry per frame each, got {len(features)} and {len(errors)}")
    pairs = [(f.detach().double().cpu(), e.detach().double().cpu().reshape(-1)) for f, e in zip(features, errors)
             if e.numel()]
    if not pairs:
        raise InputError("errors: expected at least one frame with target pixels, got none")
    for i, (f, e) in enumerate(pairs):
        if f.dim() != 2 or f.shape != (e.numel(), len(SIGNALS)):
            raise InputError(f"features: expected ({e.numel()}, {len(SIGNALS)}) for frame {i}, got {tuple(f.shape)}")
        if not (torch.isfinite(f).all() and torch.isfinite(e).all()):
            raise InputError(f"features, errors: frame {i} has non-finite values")
    x = torch.cat([f for f, _ in pairs])
    err = torch.cat([e for _, e in pairs]).abs()
    frame_weight = torch.cat([torch.full((e.numel(),), 1.0 / (e.numel() * len(pairs)), dtype=torch.float64)
                              for _, e in pairs])
    init = check_std_terms(start, "start")
    w = torch.tensor([init[k] for k in STD_TERMS], dtype=torch.float64)
    design = torch.cat([torch.ones(len(x), 1, dtype=torch.float64), _log_signals(x)], 1)
    scaled = math.sqrt(2) * err

    def objective(w: torch.Tensor) -> torch.Tensor:
        s = design @ w
        return (frame_weight * (s + scaled * torch.exp(-s))).sum()

    # Newton's method: the objective is convex in w (s is linear in w, s + c exp(-s) convex in s).
    value = objective(w)
    for _ in range(max_iter):
        s = design @ w
        tail = scaled * torch.exp(-s)
        grad = design.T @ (frame_weight * (1 - tail))
        hess = design.T @ (design * (frame_weight * tail)[:, None])
        step = torch.linalg.solve(hess + 1e-9 * torch.eye(len(w), dtype=torch.float64), grad)
        t = 1.0
        while t > 1e-6:  # backtracking: take the longest halving step that lowers the objective
            trial = objective(w - t * step)
            if trial <= value:
                break
            t /= 2
        else:
            break
        w, done = w - t * step, float(value - trial) < 1e-12
        value = trial
        if done:
            break
    with torch.no_grad():
        ratio = err / torch.exp(design @ w)
        order = torch.argsort(ratio)
        cum = torch.cumsum(frame_weight[order], 0)
        q = ratio[order][int(torch.searchsorted(cum, torch.tensor(COVERAGE, dtype=torch.float64)).clamp_max(len(cum) - 1))]
        w[0] += torch.log(q.clamp_min(1e-12))
    return {k: float(v) for k, v in zip(STD_TERMS, w.detach().tolist())}
