"""Small hand-made scenes that several test files share."""

from __future__ import annotations

import torch


def leaky_wall(leak_columns=((30, 32), (58, 60))):
    """A box at 8 m in front of a wall at 25 m, scan lines every 4 rows, with wall returns
    leaked into the box's columns ``[a, b)`` of ``leak_columns`` on every scan line through it
    (by default 2 px at both edges: the gate's default window, 5 px, sees a foreground
    return within 2 px)."""
    h, w = 48, 96
    K = torch.tensor([[720.0, 0, w / 2], [0, 720.0, h / 2], [0, 0, 1]])
    truth = torch.full((h, w), 25.0)
    truth[12:40, 30:60] = 8.0
    image = torch.full((1, 3, h, w), 0.8)
    image[:, :, 12:40, 30:60] = 0.2
    sparse = torch.zeros(h, w)
    sparse[2::4] = truth[2::4]  # scan lines every 4 rows, a return in every column
    leaked = torch.zeros(h, w, dtype=torch.bool)
    for a, b in leak_columns:
        leaked[14:38:4, a:b] = True
    sparse[leaked] = 25.0
    return image, sparse[None, None], K, truth, leaked
