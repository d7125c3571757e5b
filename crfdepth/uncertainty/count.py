"""The paper's count-based uncertainty map (paper Sec. 3.3, docs/design.md section 5): 1 where a
node has no LiDAR return, 0.5 where it has one, 0 where it has more."""

from __future__ import annotations

import torch


def node_count_uncertainty(lidar_count: torch.Tensor, dtype: torch.dtype) -> torch.Tensor:
    """(N,) the map's value per superpixel node from its LiDAR count."""
    return torch.where(lidar_count == 0, 1.0, torch.where(lidar_count == 1, 0.5, 0.0)).to(dtype)


def pixel_count_uncertainty(sparse: torch.Tensor) -> torch.Tensor:
    """The map on the pixel grid, where a node is a pixel: 1 without a return, 0 with one."""
    return (sparse <= 0).to(sparse.dtype)
