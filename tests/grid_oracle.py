"""The dense oracle of the pixel-grid solves: numpy's solve of ``(diag(d) + L) x = b`` (tests/linalg)."""

import numpy as np
import torch


def dense_grid_solution(b: torch.Tensor, d: torch.Tensor, wh: torch.Tensor, wv: torch.Tensor) -> torch.Tensor:
    """(B, H, W) float64 solution of each image's system, weights ``wh`` (B, H, W-1) and ``wv`` (B, H-1, W)."""
    out = []
    for k in range(b.shape[0]):
        h, w = b.shape[1:]
        n = h * w
        a = np.diag(d[k].reshape(-1).double().numpy())
        idx = np.arange(n).reshape(h, w)
        for src, dst, weight in ((idx[:, :-1].ravel(), idx[:, 1:].ravel(), wh[k].reshape(-1)),
                                 (idx[:-1, :].ravel(), idx[1:, :].ravel(), wv[k].reshape(-1))):
            weight = weight.double().numpy()
            np.add.at(a, (src, src), weight)
            np.add.at(a, (dst, dst), weight)
            np.add.at(a, (src, dst), -weight)
            np.add.at(a, (dst, src), -weight)
        out.append(np.linalg.solve(a, b[k].reshape(-1).double().numpy()).reshape(h, w))
    return torch.from_numpy(np.stack(out))
