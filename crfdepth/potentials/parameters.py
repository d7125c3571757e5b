"""The model's learnable weights and their constraints (docs/design.md section 4).

Each weight is a free ``nn.Parameter`` underneath and a read-only property on top: the
weights in (0, 1) (``alpha``, ``beta``, ``gamma``, ``delta``, the paper's sigmoid) through a
logit, the positive ones through a log. Optimisers then move unconstrained numbers and a
weight can never leave its range. The gate's and IRLS's parameters exist only when those
parts are on. The posterior std's scale ``std_scale`` always exists (a predictive model
keeps it for ``uncertainty="posterior"``; the trainer freezes it there).
"""

from __future__ import annotations

import math

import torch
from torch import nn

__all__ = ["ConstrainedWeights"]

UNIT_INTERVAL = ("alpha", "beta", "gamma", "delta")
POSITIVE = ("sigma_d", "sigma_n", "sigma_p", "confidence", "refine_prior", "std_scale", "gate_threshold",
            "gate_softness", "irls_scale")
OPTIONAL = {"gate_threshold": "gate", "gate_softness": "gate", "irls_scale": "irls"}
"""Weights that exist only when the model's attribute named by the value is true."""


def _logit(p: float) -> float:
    return math.log(p / (1.0 - p))


def _constrained(raw: str, constraint) -> property:
    """A read-only property: ``constraint`` of the free parameter named ``raw``."""
    return property(lambda self: constraint(getattr(self, raw)), doc=f"``{constraint.__name__}({raw})``")


class ConstrainedWeights(nn.Module):
    """Base of :class:`crfdepth.model.CRFDepth`: registers and exposes its constrained scalars."""

    alpha = _constrained("raw_alpha", torch.sigmoid)
    beta = _constrained("raw_beta", torch.sigmoid)
    gamma = _constrained("raw_gamma", torch.sigmoid)
    delta = _constrained("raw_delta", torch.sigmoid)
    sigma_d = _constrained("log_sigma_d", torch.exp)
    sigma_n = _constrained("log_sigma_n", torch.exp)
    sigma_p = _constrained("log_sigma_p", torch.exp)
    confidence = _constrained("log_confidence", torch.exp)
    refine_prior = _constrained("log_refine_prior", torch.exp)
    std_scale = _constrained("log_std_scale", torch.exp)
    gate_threshold = _constrained("log_gate_threshold", torch.exp)
    gate_softness = _constrained("log_gate_softness", torch.exp)
    irls_scale = _constrained("log_irls_scale", torch.exp)

    def _register_weights(self, values: dict[str, float]) -> None:
        """Create the free parameters of ``values`` (checked by the caller; the attributes of
        :data:`OPTIONAL` say whether their weights exist)."""
        for name, value in values.items():
            if name in OPTIONAL and not getattr(self, OPTIONAL[name]):
                continue
            raw = f"raw_{name}" if name in UNIT_INTERVAL else f"log_{name}"
            free = _logit(value) if name in UNIT_INTERVAL else math.log(value)
            self.register_parameter(raw, nn.Parameter(torch.tensor(free)))

    def weights(self) -> dict[str, float]:
        """The constrained parameter values, for logging and reports."""
        names = [n for n in UNIT_INTERVAL + POSITIVE if n not in OPTIONAL or getattr(self, OPTIONAL[n])]
        return {n: float(getattr(self, n).detach()) for n in names}
