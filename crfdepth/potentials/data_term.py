"""What the LiDAR tells the CRF: gated returns, the prior fill and per-node aggregates.

Shared by both graphs of :class:`crfdepth.model.CRFDepth` (docs/design.md sections 3 and 3b):
the occlusion gate of :mod:`crfdepth.potentials.occlusion` scales each return's data weight, the
returns it rejects (gate < 1/2) are left out of everything that takes hard evidence (the
prior fill, LiDAR normals, the learned head's inputs), and a superpixel's LiDAR value is
the gate-weighted mean of its returns.
"""

from __future__ import annotations

from typing import Literal

import torch

from crfdepth.config import PRIORS
from crfdepth.fill.ip_basic import ip_basic_fill
from crfdepth.fill.nearest import trusted_nearest_fill
from crfdepth.potentials.energy import Variable, to_unknown
from crfdepth.potentials.occlusion import trusted_gate

__all__ = ["PRIORS", "lidar_evidence", "lidar_gate", "node_lidar", "prior_fill"]

"""The prior fills ``x0``: nearest LiDAR return (:mod:`crfdepth.fill.nearest`) or IP-Basic (:mod:`crfdepth.fill.ip_basic`)."""


def lidar_evidence(sparse: torch.Tensor, gate: tuple[torch.Tensor, torch.Tensor] | None, window: int,
                   prior: Literal["nearest", "ip_basic"], *, with_distance: bool = False) -> tuple:
    """``(gate, kept, fill)`` of a checked (B, 1, H, W) LiDAR map.

    Args:
        sparse: LiDAR depth in metres, 0 = none.
        gate: ``(threshold, softness)`` of the occlusion gate, or None for no gate.
        window: the gate's window (pixels).
        prior: which fill is ``x0``.
        with_distance: also return the exact distance in pixels from each pixel to the nearest kept
            return, where the compiled nearest search found it with the fill (else None).

    Returns:
        The (B, 1, H, W) gate (None without one; all ones in a frame it would empty, with a
        warning), ``sparse`` without the returns the gate rejects, and the prior fill of those
        (then the distance, with ``with_distance``).
    """
    g, kept = lidar_gate(sparse, gate, window)
    fill, distance = prior_fill(kept, prior)
    return (g, kept, fill, distance) if with_distance else (g, kept, fill)


def lidar_gate(sparse: torch.Tensor, gate: tuple[torch.Tensor, torch.Tensor] | None, window: int
               ) -> tuple[torch.Tensor | None, torch.Tensor]:
    """``(gate, kept)`` of :func:`lidar_evidence`: the gate (None without one) and the returns it keeps."""
    if gate is None:
        return None, sparse
    g = trusted_gate(sparse, gate[0], gate[1], window).gate  # sparse checked by the model
    return g, torch.where(g.detach() >= 0.5, sparse, torch.zeros_like(sparse))


def prior_fill(kept: torch.Tensor, prior: Literal["nearest", "ip_basic"]
               ) -> tuple[torch.Tensor, torch.Tensor | None]:
    """The prior fill of the kept returns of :func:`lidar_evidence`, and the distance in pixels from each pixel
    to the nearest of them where the nearest search found it (else None)."""
    if prior == "nearest":
        return trusted_nearest_fill(kept, with_distance=True)
    return ip_basic_fill(kept), None


def node_lidar(sparse: torch.Tensor, gate: torch.Tensor, labels: torch.Tensor, num_nodes: int,
               variable: Variable) -> tuple[torch.Tensor, torch.Tensor]:
    """``(z, n)`` per superpixel: the gate-weighted mean of its returns in the CRF's unknown
    and the sum of their gates, both (S,), differentiable in the gate (0 where none).

    Args:
        sparse, gate: (H, W) one frame's LiDAR depth and gate; labels: (H, W) node of each pixel.
    """
    s = sparse.reshape(-1)
    flat = labels.reshape(-1)
    weight = gate.reshape(-1) * (s > 0).to(s.dtype)
    n = s.new_zeros(num_nodes).index_add(0, flat, weight)
    total = s.new_zeros(num_nodes).index_add(0, flat, weight * to_unknown(s, variable))
    return torch.where(n > 0, total / n.clamp_min(1e-12), torch.zeros_like(n)), n
