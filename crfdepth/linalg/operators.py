"""Matrix-free operators for ``A = diag(d) + L(w)`` (docs/design.md sections 3 and 4).

``L(w)`` is the weighted graph Laplacian, ``(L x)_i = sum_j w_ij (x_i - x_j)``. Two
graph structures are supported, each as a small class that

- lays a batch of graphs out as a ``(G, n)`` tensor (one row per graph),
- builds the Jacobi-scaled operator ``M = D^-1/2 A D^-1/2 = I - W'`` with
  ``D = diag(A) = d + deg(w)`` and ``W'_ij = w_ij / sqrt(D_i D_j)``,
- turns an adjoint ``lam`` and a solution ``x`` into gradients for the edge weights,
  ``dL/dw_ij = -(lam_i - lam_j)(x_i - x_j)``.

:class:`EdgeGraph` takes any graph as an ``edge_index`` (2, E) and applies ``W'`` as a
CSR sparse matrix (measured faster than scatter/index_add on CPU by 10-100x).
:class:`PixelGrid` is the 4-connected ``H x W`` grid with horizontal and vertical weight
images; it applies ``W'`` with shifted slices (no index arrays at all), the fast path
for pixel-level CRFs.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass

import numpy as np
import torch

from crfdepth.checks import check_number


def grid_edge_index(height: int, width: int, device: torch.device | str | None = None) -> torch.Tensor:
    """Edge list of the 4-connected ``height x width`` pixel grid.

    Returns:
        (2, E) int64 with ``E = H (W - 1) + W (H - 1)``; node ``i = row * W + col``; first
        all horizontal edges ``(r, c) - (r, c + 1)`` in row-major order, then all vertical
        edges ``(r, c) - (r + 1, c)``, matching ``weight_h.flatten()`` and
        ``weight_v.flatten()`` of :class:`PixelGrid`.

    Raises:
        InputError: ``height`` or ``width`` not an integer >= 1.
    """
    check_number("height", height, low=1, low_open=False, integer=True)
    check_number("width", width, low=1, low_open=False, integer=True)
    idx = torch.arange(height * width, device=device).view(height, width)
    horizontal = torch.stack([idx[:, :-1].reshape(-1), idx[:, 1:].reshape(-1)])
    vertical = torch.stack([idx[:-1, :].reshape(-1), idx[1:, :].reshape(-1)])
    return torch.cat([horizontal, vertical], dim=1)


@dataclass
class EdgeGraph:
    """A batch of graphs given by an edge list, stored as one block-diagonal system.

    Attributes:
        edge_index: (2, E) int64 node indices into the concatenated node vector.
        ptr: (G + 1,) int64 node offsets: graph ``g`` owns nodes ``ptr[g]:ptr[g+1]``.
    """

    edge_index: torch.Tensor
    ptr: torch.Tensor

    def __post_init__(self) -> None:
        sizes = (self.ptr[1:] - self.ptr[:-1]).tolist()
        self.sizes = sizes
        self.num_graphs = len(sizes)
        self.num_nodes = int(self.ptr[-1])
        self.width = max(sizes) if sizes else 0
        self.uniform = all(s == self.width for s in sizes)
        if self.uniform:
            self._pad_index = None
        else:
            graph_of_node = torch.repeat_interleave(
                torch.arange(self.num_graphs, device=self.ptr.device), self.ptr[1:] - self.ptr[:-1])
            local = torch.arange(self.num_nodes, device=self.ptr.device) - self.ptr[graph_of_node]
            self._pad_index = graph_of_node * self.width + local

    # -- layout -----------------------------------------------------------------------
    def to_rows(self, v: torch.Tensor, fill: float = 0.0) -> torch.Tensor:
        """(N,) node vector -> (G, n) rows, padding with ``fill``."""
        if self._pad_index is None:
            return v.reshape(self.num_graphs, self.width)
        out = v.new_full((self.num_graphs * self.width,), fill)
        out[self._pad_index] = v
        return out.view(self.num_graphs, self.width)

    def from_rows(self, rows: torch.Tensor) -> torch.Tensor:
        """(G, n) rows -> (N,) node vector."""
        flat = rows.reshape(-1)
        return flat if self._pad_index is None else flat[self._pad_index]

    # -- operator ---------------------------------------------------------------------
    def degree(self, edge_weight: torch.Tensor) -> torch.Tensor:
        """(N,) weighted degree ``sum_j w_ij``."""
        src, dst = self.edge_index
        # bincount: an order of magnitude faster than index_add_ for float64 on CPU.
        deg = torch.bincount(src, weights=edge_weight, minlength=self.num_nodes)
        deg = deg + torch.bincount(dst, weights=edge_weight, minlength=self.num_nodes)
        return deg.to(edge_weight.dtype)

    def _csr_pattern(self):
        """Sorted CSR pattern of ``I - W'`` on the padded (G * n) layout, built once."""
        if getattr(self, "_pattern", None) is None:
            src, dst = self.edge_index
            size = self.num_graphs * self.width
            if self._pad_index is None:
                rows, cols = src, dst
            else:
                rows, cols = self._pad_index[src], self._pad_index[dst]
            diag = torch.arange(size, device=src.device)
            all_rows = torch.cat([rows, cols, diag])
            all_cols = torch.cat([cols, rows, diag])
            keys = all_rows * size + all_cols
            if keys.device.type == "cpu":  # NumPy's stable sort: ~10x faster than torch.argsort here
                order = torch.from_numpy(np.argsort(keys.numpy(), kind="stable"))
            else:
                order = torch.argsort(keys)
            crow = torch.zeros(size + 1, dtype=torch.int64, device=keys.device)
            crow[1:] = torch.cumsum(torch.bincount(all_rows, minlength=size), 0)
            self._pattern = (crow, all_cols[order], order, size)
        return self._pattern

    def scaled_matvec(self, edge_weight: torch.Tensor, inv_sqrt_diag: torch.Tensor):
        """Return ``y -> (I - W') y`` on (G, n) rows; ``inv_sqrt_diag`` is (N,)."""
        src, dst = self.edge_index
        crow, col, order, size = self._csr_pattern()
        neg_w = -(edge_weight * inv_sqrt_diag[src] * inv_sqrt_diag[dst])
        values = torch.cat([neg_w, neg_w, neg_w.new_ones(size)])[order]
        with warnings.catch_warnings():  # "CSR support is in beta": nothing to act on
            warnings.simplefilter("ignore", UserWarning)
            M = torch.sparse_csr_tensor(crow, col, values, (size, size), check_invariants=False)
        shape = (self.num_graphs, self.width)

        def matvec(y: torch.Tensor) -> torch.Tensor:
            return torch.mv(M, y.reshape(-1)).view(shape)

        matvec.flat = lambda v: torch.mv(M, v)  # (G * n,) -> (G * n,), no reshapes
        return matvec

    def weight_grad(self, lam: torch.Tensor, x: torch.Tensor) -> torch.Tensor:
        """(E,) ``-(lam_i - lam_j)(x_i - x_j)`` from (N,) node vectors."""
        src, dst = self.edge_index
        return -(lam[src] - lam[dst]) * (x[src] - x[dst])


@dataclass
class PixelGrid:
    """A batch of ``B`` 4-connected ``H x W`` pixel grids (node ``i = row * W + col``).

    Edge weights come as two images: ``weight_h`` (B, H, W-1) between ``(r, c)`` and
    ``(r, c+1)``, ``weight_v`` (B, H-1, W) between ``(r, c)`` and ``(r+1, c)``.
    """

    batch: int
    height: int
    width: int

    @property
    def num_graphs(self) -> int:
        return self.batch

    def to_rows(self, v: torch.Tensor, fill: float = 0.0) -> torch.Tensor:
        """(B, H, W) -> (B, H*W)."""
        return v.reshape(self.batch, self.height * self.width)

    def from_rows(self, rows: torch.Tensor) -> torch.Tensor:
        """(B, H*W) -> (B, H, W)."""
        return rows.reshape(self.batch, self.height, self.width)

    @staticmethod
    def degree(weight_h: torch.Tensor, weight_v: torch.Tensor) -> torch.Tensor:
        """(B, H, W) weighted degree."""
        b, h, w1 = weight_h.shape
        deg = weight_h.new_zeros(b, h, w1 + 1)
        deg[:, :, :-1] += weight_h
        deg[:, :, 1:] += weight_h
        deg[:, :-1, :] += weight_v
        deg[:, 1:, :] += weight_v
        return deg

    def scaled_matvec(self, weight_h: torch.Tensor, weight_v: torch.Tensor, inv_sqrt_diag: torch.Tensor):
        """Return ``y -> (I - W') y`` on (B, H*W) rows; ``inv_sqrt_diag`` is (B, H, W)."""
        s = inv_sqrt_diag
        wh = weight_h * s[:, :, :-1] * s[:, :, 1:]
        wv = weight_v * s[:, :-1, :] * s[:, 1:, :]
        shape = (self.batch, self.height, self.width)

        def matvec(y: torch.Tensor) -> torch.Tensor:
            y = y.view(shape)
            out = y.clone()
            out[:, :, :-1].addcmul_(wh, y[:, :, 1:], value=-1.0)
            out[:, :, 1:].addcmul_(wh, y[:, :, :-1], value=-1.0)
            out[:, :-1, :].addcmul_(wv, y[:, 1:, :], value=-1.0)
            out[:, 1:, :].addcmul_(wv, y[:, :-1, :], value=-1.0)
            return out.view(self.batch, -1)

        matvec.grid_weights = (wh, wv)  # the scaled weights, for the fused CG passes (crfdepth.native)
        return matvec

    @staticmethod
    def weight_grad(lam: torch.Tensor, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Gradients for (weight_h, weight_v) from (B, H, W) adjoint and solution."""
        gh = -(lam[:, :, :-1] - lam[:, :, 1:]) * (x[:, :, :-1] - x[:, :, 1:])
        gv = -(lam[:, :-1, :] - lam[:, 1:, :]) * (x[:, :-1, :] - x[:, 1:, :])
        return gh, gv
