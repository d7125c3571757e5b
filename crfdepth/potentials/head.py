"""The small learned part of the CRF: per-pixel data confidence and edge-weight corrections.

Ten scalars weight the potentials the same everywhere. :class:`PotentialHead` is a three-layer
convolutional network (about 3,400 parameters) that looks at the image and the sparse
depth and returns, per pixel,

- a factor on the data weight ``w_i`` (how far to trust the LiDAR return there: a return
  next to a depth edge or in a cluster of disagreeing returns deserves less), and
- a factor on every pairwise weight of the two edges leaving the pixel to the right and
  downwards (how strongly to join the pixel to its neighbours, beyond what the colour,
  normal and distance affinities say).

Both factors are ``exp(limit * tanh(o / limit))`` of the network's outputs ``o``, so they
are positive (the system stays SPD), bounded in ``[exp(-limit), exp(limit)]``, and the
head starts as the identity: its last layer is zero-initialised, so a model with a fresh
head gives the same depth as one without (docs/design.md section 3b). It is trained
through the implicit solve like every other weight.
"""

from __future__ import annotations

import torch
from torch import nn

__all__ = ["PotentialHead", "head_features"]

FEATURES = 7
"""Input channels of :func:`head_features`."""


def head_features(image: torch.Tensor, sparse: torch.Tensor, prior: torch.Tensor) -> torch.Tensor:
    """(B, 7, H, W) inputs of the head: centred RGB, LiDAR mask, scaled inverse LiDAR depth,
    scaled inverse prior depth, and the LiDAR residual against the prior (inverse depth).

    Inverse depth in units of 1/(10 m) keeps the values near 1 on KITTI; no gradient flows
    into the depths (they are data, not learned quantities).
    """
    sparse, prior = sparse.detach(), prior.detach()
    mask = (sparse > 0).to(sparse.dtype)
    inv_sparse = torch.where(sparse > 0, 10.0 / sparse.clamp_min(1e-3), torch.zeros_like(sparse))
    inv_prior = 10.0 / prior.clamp_min(1e-3)
    residual = mask * (inv_sparse - inv_prior)
    return torch.cat([image - 0.5, mask, inv_sparse, inv_prior, residual], 1)


class PotentialHead(nn.Module):
    """A small CNN giving ``(data_factor (B, 1, H, W), edge_factor (B, 2, H, W))``.

    ``edge_factor[:, 0]`` multiplies the weight between pixel ``(r, c)`` and ``(r, c+1)``
    (its last column is unused), ``edge_factor[:, 1]`` the weight between ``(r, c)`` and
    ``(r+1, c)`` (last row unused).

    Args:
        hidden: channels of the two hidden 3x3 layers.
        limit: the factors lie in ``[exp(-limit), exp(limit)]``.
    """

    def __init__(self, hidden: int = 16, limit: float = 3.0) -> None:
        super().__init__()
        self.limit = float(limit)
        self.net = nn.Sequential(
            nn.Conv2d(FEATURES, hidden, 3, padding=1, padding_mode="replicate"), nn.ReLU(inplace=True),
            nn.Conv2d(hidden, hidden, 3, padding=1, padding_mode="replicate"), nn.ReLU(inplace=True),
            nn.Conv2d(hidden, 3, 1),
        )
        nn.init.zeros_(self.net[-1].weight)
        nn.init.zeros_(self.net[-1].bias)

    def forward(self, image: torch.Tensor, sparse: torch.Tensor, prior: torch.Tensor
                ) -> tuple[torch.Tensor, torch.Tensor]:
        # channels-last: the 3x3 convolutions' fast CPU path (oneDNN), about 2x at 1216 x 352; same values
        features = head_features(image, sparse, prior).contiguous(memory_format=torch.channels_last)
        out = self.net(features).contiguous()
        factor = torch.exp(self.limit * torch.tanh(out / self.limit))
        return factor[:, :1], factor[:, 1:]
