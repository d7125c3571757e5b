"""Surface normals of graph nodes for the CRF's normal term (docs/design.md sections 2 and 4).

- :func:`aggregate_normals`: per-node mean of pixel normals, renormalised (``nrm_i`` of
  section 2), from :func:`crfdepth.geometry.normals.lidar_normals` or
  :func:`~crfdepth.geometry.normals.dense_normals`.
- :func:`graph_normals`: for nodes without LiDAR normals, the plane fitted to a node's 3D
  point and its graph neighbours' points, differentiable where the fit is a clear plane
  (section 4).

Conventions as in :mod:`crfdepth.geometry.normals`: camera frame of ``K`` (x right, y down,
z forward, metres), unit normals facing the camera (``n . p < 0``), 0 where not defined.
"""

from __future__ import annotations

import torch

from crfdepth.checks import describe
from crfdepth.errors import InputError

__all__ = ["NORMAL_GAP", "aggregate_normals", "graph_normals"]


def aggregate_normals(
    normals: torch.Tensor,
    valid: torch.Tensor,
    labels: torch.Tensor,
    num_nodes: int,
    *,
    min_resultant: float = 0.1,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Per-node normal ``nrm_i``: mean of the valid pixel normals inside, renormalised.

    A node is valid when it holds at least one valid pixel normal and the mean vector is
    long enough, ``|mean| >= min_resultant`` (unit normals that nearly cancel have no
    meaningful mean direction; 1 = all equal). Invalid nodes get a 0 vector: for them
    docs/design.md section 2 takes the normal of the first-pass dense solution
    (:func:`crfdepth.geometry.normals.dense_normals` aggregated the same way).
    Differentiable with respect to ``normals``.

    Args:
        normals: (3, H, W) unit normals (0 where not valid), e.g. from
            :func:`crfdepth.geometry.normals.lidar_normals`.
        valid: (H, W) or (1, H, W) bool mask of the pixels to use.
        labels: (H, W) int64 node index ``0 .. num_nodes-1`` of each pixel.
        num_nodes: ``S``.
        min_resultant: least length of the mean normal, in [0, 1].

    Returns:
        ``node_normals`` (S, 3) unit vectors (0 where invalid) and ``node_valid`` (S,) bool.
    """
    if not isinstance(normals, torch.Tensor) or normals.ndim != 3 or normals.shape[0] != 3:
        raise InputError(f"normals: expected a (3, H, W) tensor, got {describe(normals)}")
    hw = tuple(normals.shape[1:])
    if isinstance(valid, torch.Tensor) and valid.ndim == 3 and valid.shape[0] == 1:
        valid = valid[0]
    if not isinstance(valid, torch.Tensor) or tuple(valid.shape) != hw or valid.dtype != torch.bool:
        raise InputError(f"valid: expected an {hw} or (1, {hw[0]}, {hw[1]}) bool tensor, got {describe(valid)}")
    if not isinstance(labels, torch.Tensor) or tuple(labels.shape) != hw or labels.dtype != torch.int64:
        raise InputError(f"labels: expected an {hw} int64 tensor, got {describe(labels)}")
    if labels.numel() and (int(labels.min()) < 0 or int(labels.max()) >= num_nodes):
        raise InputError(
            f"labels: expected values in [0, {num_nodes - 1}] (num_nodes={num_nodes}), "
            f"got range [{int(labels.min())}, {int(labels.max())}]"
        )
    use = valid.reshape(-1)
    node = labels.reshape(-1)[use]
    vectors = normals.reshape(3, -1)[:, use].T  # (N, 3)
    total = torch.zeros(num_nodes, 3, dtype=normals.dtype, device=normals.device).index_add(0, node, vectors)
    count = torch.bincount(node, minlength=num_nodes).to(normals.dtype)
    mean = total / count.clamp(min=1)[:, None]
    length = mean.norm(dim=1)
    node_valid = (count > 0) & (length >= min_resultant) & (length > 0)
    unit = mean / torch.where(node_valid, length, torch.ones_like(length))[:, None]
    return unit * node_valid[:, None].to(unit.dtype), node_valid


#: Least relative eigen-gap ``(lambda_1 - lambda_0) / lambda_2`` of a fitted plane whose
#: normal is differentiated (:func:`graph_normals`); at least 100 x the dtype's machine
#: epsilon. Measured on a 352x320 crop of a real frame: a floor of 1e-2 left a parameter's
#: gradient 10% off, 1e-6 every one within 0.15% (tests/test_gradients_real.py).
NORMAL_GAP = 1e-6


# cuSOLVER's batched symmetric eigensolver (what torch.linalg.eigh calls for a CUDA batch of 3 x 3
# matrices) fails with CUSOLVER_STATUS_INTERNAL_ERROR from 65,536 matrices on, and its workspace grows
# by about 270 kB per matrix (measured on an H200, torch 2.11 + CUDA 13.0: 65,535 pass, 65,536 fail,
# 10^6 ask for 253 GiB; the superpixel model's peak was 1.4 GB at 1216 x 352 with its 5,500 nodes in
# one call and 9.1 GB at 4000 x 3000 in pieces of 32,768). Pieces of 2,048 bound the workspace to
# about 0.55 GB (docs/design.md section 10).
EIGH_CUDA_CHUNK = 2048


def batched_eigh(matrices: torch.Tensor, chunk: int | None = None) -> tuple[torch.Tensor, torch.Tensor]:
    """:func:`torch.linalg.eigh` of a (B, n, n) batch, in pieces of ``chunk`` matrices.

    ``chunk`` defaults to :data:`EIGH_CUDA_CHUNK` on CUDA and to the whole batch elsewhere;
    the pieces' eigenvalues and eigenvectors are concatenated, so the result and its gradient
    are those of one call.
    """
    if chunk is None:
        chunk = EIGH_CUDA_CHUNK if matrices.is_cuda else max(1, matrices.shape[0])
    if matrices.shape[0] <= chunk:
        return torch.linalg.eigh(matrices)
    pieces = [torch.linalg.eigh(part) for part in matrices.split(chunk)]
    return torch.cat([v for v, _ in pieces]), torch.cat([w for _, w in pieces])


def graph_normals(points: torch.Tensor, edge_index: torch.Tensor, num_nodes: int) -> torch.Tensor:
    """(N, 3) unit normals of planes fitted to each node's 3D point and its neighbours' points.

    For nodes without LiDAR normals (docs/design.md section 2): the plane through node
    ``i``'s point ``points[i]`` and those of its graph neighbours (the eigenvector of the
    smallest eigenvalue of their covariance), facing the camera (``n . p < 0``). Nodes with
    fewer than three points in the fit, or a degenerate fit, get the viewing direction.

    Differentiable in ``points`` where the fit is a clear plane (relative eigen-gap above
    :data:`NORMAL_GAP`); elsewhere the normal is used without a gradient.

    Args:
        points: (N, 3) camera-frame points in metres; edge_index: (2, E) undirected edges.
    """
    src, dst = edge_index
    ones = torch.ones(num_nodes, dtype=points.dtype, device=points.device)
    cnt = ones.index_add(0, src, ones[dst]).index_add(0, dst, ones[src])
    total = points.index_add(0, src, points[dst]).index_add(0, dst, points[src])
    mean = total / cnt[:, None]
    outer = points[:, :, None] * points[:, None, :]
    second = outer.index_add(0, src, outer[dst]).index_add(0, dst, outer[src]) / cnt[:, None, None]
    cov = second - mean[:, :, None] * mean[:, None, :]
    cov = cov + 1e-9 * torch.eye(3, dtype=points.dtype, device=points.device)
    values, vecs = batched_eigh(cov.detach())
    n = vecs[:, :, 0]
    if points.requires_grad:
        # The eigenvector's derivative scales with 1 / (lambda_1 - lambda_0): exact where the
        # plane is well defined, unbounded where it is not (a line of points, an isotropic
        # blob, fewer than three points). Only fits with a clear gap enter the differentiated
        # eigh; the others keep their normal without a gradient (docs/design.md section 4).
        least = max(NORMAL_GAP, 100 * torch.finfo(cov.dtype).eps)  # float32: rounding sets the floor
        gap = (values[:, 1] - values[:, 0]) > least * values[:, 2].clamp_min(1e-12)
        good = torch.nonzero(gap & (cnt >= 3)).squeeze(1)
        n_good = batched_eigh(cov[good])[1][:, :, 0]
        n_good = torch.where((n_good * n[good]).sum(1, keepdim=True) < 0, -n_good, n_good)
        n = n.index_put((good,), n_good)
    view = points / points.norm(dim=1, keepdim=True).clamp_min(1e-9)
    n = torch.where(((n * points).sum(1, keepdim=True) > 0), -n, n)
    bad = (cnt < 3) | ~torch.isfinite(n).all(1)
    return torch.where(bad[:, None], -view, n)
