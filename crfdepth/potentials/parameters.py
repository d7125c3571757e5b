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


def _logit(p: float) -> float:
    return math.log(p / (1.0 - p))


def _free_name(name: str) -> str:
    """The free parameter under weight ``name``: ``raw_<name>`` (a logit) in (0, 1), else ``log_<name>``."""
    return f"raw_{name}" if name in UNIT_INTERVAL else f"log_{name}"


def _constrained(name: str) -> property:
    """A read-only property: weight ``name``, the sigmoid or exp of its free parameter."""
    raw = _free_name(name)
    constraint = torch.sigmoid if name in UNIT_INTERVAL else torch.exp
    return property(lambda self: constraint(getattr(self, raw)), doc=f"``{constraint.__name__}({raw})``")


def _weight_properties(cls: type) -> type:
    """Class decorator: a read-only property (:func:`_constrained`) per weight of :data:`UNIT_INTERVAL`
    and :data:`POSITIVE`, so the tables are the one list of the weights."""
    for name in UNIT_INTERVAL + POSITIVE:
        setattr(cls, name, _constrained(name))
    return cls


@_weight_properties
class ConstrainedWeights(nn.Module):
    """Base of :class:`crfdepth.model.CRFDepth`: registers and exposes its constrained scalars
    (``alpha``, ..., ``irls_scale``: the properties :func:`_weight_properties` adds)."""

    def _register_weights(self, values: dict[str, float]) -> None:
        """Create the free parameters of ``values``, weight name -> initial value (checked by the caller,
        who leaves out the weights of parts that are off: those weights then do not exist)."""
        for name, value in values.items():
            free = _logit(value) if name in UNIT_INTERVAL else math.log(value)
            self.register_parameter(_free_name(name), nn.Parameter(torch.tensor(free)))

    def weights(self) -> dict[str, float]:
        """The constrained parameter values, for logging and reports."""
        names = [n for n in UNIT_INTERVAL + POSITIVE if _free_name(n) in self._parameters]
        return {n: float(getattr(self, n).detach()) for n in names}
