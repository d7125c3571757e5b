"""What the inference stages read from the model: its settings and current weights, as a type.

:class:`crfdepth.model.CRFDepth` is the one implementation; the stages name this protocol
rather than the model class, so inference sits below the model with no import back up.
"""

from __future__ import annotations

from typing import Callable, Protocol

import torch

from crfdepth.linalg import SolverSettings
from crfdepth.potentials.energy import PotentialWeights, Variable


class ModelSettings(Protocol):
    """Structure, potentials, gate, solver and uncertainty settings of a CRF, with its weights."""

    # structure
    potentials: tuple[str, ...]
    variable: Variable
    aggregate: str
    refine: bool
    rounds: int
    prior: str
    head: torch.nn.Module | None
    # gate and robust reweighting
    gate: bool
    gate_window: int
    gate_threshold: torch.Tensor
    gate_softness: torch.Tensor
    irls: int
    irls_scale: torch.Tensor
    # potentials' weights
    confidence: torch.Tensor
    sigma_d: torch.Tensor
    sigma_n: torch.Tensor
    sigma_p: torch.Tensor
    refine_prior: torch.Tensor
    # solver and uncertainty
    solver: SolverSettings
    uncertainty: str
    std_head: torch.nn.Module | None
    std_scale: torch.Tensor
    std_samples: int
    progress: Callable[[str], None] | None

    def scales(self) -> tuple[torch.Tensor, ...]: ...

    def potential_weights(self) -> PotentialWeights: ...

    def segments_for(self, height: int, width: int) -> int: ...
