"""The one linear system every CRF in crfdepth solves (docs/design.md sections 3 and 4).

A Gaussian CRF's energy ``sum_i d_i x_i^2 - 2 b_i x_i + sum_(i,j) w_ij (x_i - x_j)^2`` is
minimised by ``A x = rhs`` with ``A = diag(diagonal) + L(w)``. The potentials assemble a
:class:`System`; :func:`crfdepth.linalg.adjoint.solve_system` solves it and
:mod:`crfdepth.uncertainty.posterior` gives its variances. The same type holds both
structures, so the argument order is the same on every path:

- a batch of graphs: ``diagonal, rhs`` (N,), ``weights = (edge_weight (E,),)`` on
  ``edge_index`` (2, E), node offsets ``ptr`` (G + 1,);
- a batch of 4-connected pixel grids: ``diagonal, rhs`` (B, H, W),
  ``weights = (weight_h (B, H, W-1), weight_v (B, H-1, W))``; ``edge_index`` and ``ptr`` None.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch


@dataclass(frozen=True)
class System:
    """``A x = rhs``, ``A = diag(diagonal) + L(weights)`` on a graph batch or a pixel-grid batch."""

    diagonal: torch.Tensor
    rhs: torch.Tensor
    weights: tuple[torch.Tensor, ...]
    edge_index: torch.Tensor | None = None
    ptr: torch.Tensor | None = None

    @classmethod
    def graph(cls, diagonal: torch.Tensor, rhs: torch.Tensor, edge_index: torch.Tensor, edge_weight: torch.Tensor,
              ptr: torch.Tensor | None = None) -> System:
        """A batch of graphs as one block-diagonal system (``ptr`` None: one graph)."""
        if ptr is None:
            ptr = torch.tensor([0, diagonal.shape[0]], device=diagonal.device)
        return cls(diagonal, rhs, (edge_weight,), edge_index, ptr)

    @classmethod
    def grid(cls, diagonal: torch.Tensor, rhs: torch.Tensor, weight_h: torch.Tensor,
             weight_v: torch.Tensor) -> System:
        """A batch of 4-connected pixel grids."""
        return cls(diagonal, rhs, (weight_h, weight_v))

    @property
    def is_grid(self) -> bool:
        return self.edge_index is None

    def detached(self) -> System:
        """The same system without gradient (what the variance estimates take)."""
        return System(self.diagonal.detach(), self.rhs.detach(), tuple(w.detach() for w in self.weights),
                      self.edge_index, self.ptr)
