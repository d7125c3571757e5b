"""Tests for crfdepth.geometry.normals and .node_normals: LiDAR plane-fit normals, dense-depth normals, per-node means."""

from __future__ import annotations

import math

import pytest
import torch

from crfdepth.errors import InputError
from crfdepth.geometry.node_normals import EIGH_CUDA_CHUNK, aggregate_normals, batched_eigh, graph_normals
from crfdepth.geometry.normals import dense_normals, lidar_normals, smallest_eigenvector

H, W = 352, 1216
# KITTI val_selection_cropped-like intrinsics (fx, fy, cx, cy in pixels).
K = torch.tensor([[721.5, 0.0, 596.5], [0.0, 721.5, 149.9], [0.0, 0.0, 1.0]])


def unit(*v: float) -> torch.Tensor:
    t = torch.tensor(v, dtype=torch.float64)
    return t / t.norm()


def plane_depth(normal: torch.Tensor, offset: float) -> torch.Tensor:
    """(H, W) z-depth of the plane ``normal . X = -offset`` along each pixel's ray (float64)."""
    v, u = torch.meshgrid(torch.arange(H, dtype=torch.float64), torch.arange(W, dtype=torch.float64), indexing="ij")
    ray = torch.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], torch.ones_like(u)], dim=-1)
    return -offset / (ray @ normal)


def ring_mask(generator: torch.Generator, spacing: int = 5, keep: float = 0.5) -> torch.Tensor:
    """Pixels hit by a simulated multi-beam LiDAR: gently curved scan lines ``spacing`` rows
    apart (like KITTI's 64 beams in the cropped image), with random drop-outs."""
    mask = torch.zeros(H, W, dtype=torch.bool)
    u = torch.arange(W)
    for first_row in range(3, H, spacing):
        v = (first_row + 2e-5 * (u - W / 2) ** 2).round().long()
        inside = v < H
        mask[v[inside], u[inside]] = True
    return mask & (torch.rand(H, W, generator=generator) < keep)


def simulate(normal: torch.Tensor, offset: float, noise: float = 0.0, seed: int = 0) -> torch.Tensor:
    """(1, H, W) float32 sparse depth of a plane seen by the simulated LiDAR (0 = no return)."""
    gen = torch.Generator().manual_seed(seed)
    z = plane_depth(normal, offset)
    hit = ring_mask(gen) & (z > 1.0) & (z < 80.0)
    z = z + noise * torch.randn(H, W, generator=gen, dtype=torch.float64)
    return torch.where(hit, z, torch.zeros_like(z)).float()[None]


def angle_deg(normals: torch.Tensor, valid: torch.Tensor, want: torch.Tensor) -> torch.Tensor:
    """Angles (degrees) between the valid normals of a (3, H, W) map and ``want``."""
    n = normals[:, valid.reshape(normals.shape[1:])].T.double()
    return torch.rad2deg(torch.acos((n @ want).clamp(-1.0, 1.0)))


def back_project(depth: torch.Tensor) -> torch.Tensor:
    """(3, H, W) camera points of an (H, W) depth map."""
    v, u = torch.meshgrid(torch.arange(H, dtype=depth.dtype), torch.arange(W, dtype=depth.dtype), indexing="ij")
    k = K.to(depth.dtype)
    return torch.stack([(u - k[0, 2]) / k[0, 0] * depth, (v - k[1, 2]) / k[1, 1] * depth, depth])


# --------------------------------------------------------------------------- lidar_normals


@pytest.mark.parametrize(
    "normal, offset",
    [
        (unit(0.3, -0.8, -0.5), 5.0),  # tilted plane, seen obliquely
        (unit(0.0, -1.0, 0.0), 1.65),  # the road under a level camera 1.65 m up
        (unit(-0.6, 0.0, -0.8), 12.0),  # a wall turned away to the right
    ],
)
def test_tilted_plane_with_noisy_lidar(normal, offset):
    sparse = simulate(normal, offset, noise=0.01)
    normals, valid = lidar_normals(sparse, K)
    assert normals.shape == (3, H, W) and valid.shape == (1, H, W) and valid.dtype == torch.bool
    hits = int((sparse > 0).sum())
    assert int(valid.sum()) > 0.85 * hits  # measured 0.91-1.0
    err = angle_deg(normals, valid, normal)
    assert err.mean().item() < 3.0  # measured 0.4-1.8 degrees with 1 cm depth noise
    assert torch.quantile(err, 0.9).item() < 6.0

    exact_normals, exact_valid = lidar_normals(simulate(normal, offset), K)
    assert angle_deg(exact_normals, exact_valid, normal).max().item() < 0.1


def test_normals_face_the_camera_and_are_unit():
    normal = unit(0.3, -0.8, -0.5)
    sparse = simulate(normal, 5.0, noise=0.01)
    normals, valid = lidar_normals(sparse, K)
    v = valid[0]
    points = back_project(sparse[0].double())
    assert bool(((normals.double() * points).sum(0)[v] < 0).all())
    assert torch.allclose(normals[:, v].norm(dim=0), torch.ones(int(v.sum())), atol=1e-5)
    # Zero vectors exactly where invalid (including every pixel without LiDAR).
    assert bool((normals[:, ~v] == 0).all())
    assert not bool(valid[sparse == 0].any())


def test_fronto_parallel_plane_gives_minus_z():
    sparse = simulate(unit(0.0, 0.0, -1.0), 10.0)
    assert torch.allclose(sparse[sparse > 0], torch.tensor(10.0))
    normals, valid = lidar_normals(sparse[0], K)
    assert valid.shape == (H, W) and int(valid.sum()) > 0.95 * int((sparse > 0).sum())
    want = torch.tensor([0.0, 0.0, -1.0])[:, None].expand(3, int(valid.sum()))
    assert torch.allclose(normals[:, valid], want, atol=1e-6)


def test_neighbours_across_a_depth_step_are_ignored():
    # Two fronto-parallel planes, 10 m on the left half, 30 m on the right half.
    sparse = simulate(unit(0.0, 0.0, -1.0), 10.0)
    sparse[..., W // 2:] *= 3.0
    normals, valid = lidar_normals(sparse, K)
    near_step = torch.zeros(H, W, dtype=torch.bool)
    near_step[:, W // 2 - 7:W // 2 + 7] = True
    v = valid[0] & near_step
    assert int(v.sum()) > 50
    assert angle_deg(normals, v, unit(0.0, 0.0, -1.0)).max().item() < 0.1


def test_single_scan_line_and_isolated_points_are_invalid():
    sparse = torch.zeros(H, W)
    sparse[100, 200:400] = 8.0  # one scan line: collinear points, no plane
    sparse[250, 600] = 8.0  # an isolated point
    sparse[250:253, 900] = 8.0  # three points: too few
    normals, valid = lidar_normals(sparse, K)
    assert not bool(valid.any())
    assert bool((normals == 0).all())


def test_batch_layout_matches_single_frames():
    a = simulate(unit(0.3, -0.8, -0.5), 5.0, noise=0.01, seed=1)
    b = simulate(unit(0.0, -1.0, 0.0), 1.65, noise=0.01, seed=2)
    k_b = K.clone()
    k_b[0, 0] = 700.0  # a different camera for the second frame
    normals, valid = lidar_normals(torch.stack([a, b]), torch.stack([K, k_b]))
    assert normals.shape == (2, 3, H, W) and valid.shape == (2, 1, H, W)
    for i, (frame, k) in enumerate(((a, K), (b, k_b))):
        n1, v1 = lidar_normals(frame, k)
        assert torch.equal(valid[i], v1)
        assert torch.allclose(normals[i], n1, atol=1e-6)
    shared_k, _ = lidar_normals(torch.stack([a, b]), K)  # one (3, 3) K for the whole batch
    assert torch.allclose(shared_k[0], normals[0], atol=1e-6)
    assert not torch.allclose(shared_k[1], normals[1], atol=1e-6)


@pytest.mark.parametrize(
    "sparse, k, kwargs, name",
    [
        (torch.zeros(2, 3, 8, 8), K, {}, "sparse"),
        (torch.full((8, 8), -1.0), K, {}, "sparse"),
        (torch.full((8, 8), float("nan")), K, {}, "sparse"),
        (torch.zeros(8, 8), torch.eye(4), {}, "K"),
        (torch.zeros(8, 8), torch.zeros(3, 3), {}, "K"),
        (torch.zeros(1, 8, 8), K, {"window": (4, 5)}, "window"),
    ],
)
def test_lidar_normals_bad_input(sparse, k, kwargs, name):
    with pytest.raises(InputError, match=rf"^{name}: expected"):
        lidar_normals(sparse, k, **kwargs)


# --------------------------------------------------------------------------- dense_normals


def test_dense_normals_on_an_exact_plane():
    for normal, offset in ((unit(0.3, -0.8, -0.5), 5.0), (unit(-0.6, 0.2, -0.8), 12.0)):
        depth = plane_depth(normal, offset)
        assert bool((depth > 0).all())
        normals, valid = dense_normals(depth.float()[None], K)
        assert normals.shape == (3, H, W) and bool(valid.all())
        assert angle_deg(normals, valid, normal).max().item() < 1.0  # measured < 0.03
        assert bool(((normals.double() * back_project(depth)).sum(0) < 0).all())  # faces the camera

    flat, flat_valid = dense_normals(torch.full((2, 1, 20, 30), 7.0), K)
    assert flat.shape == (2, 3, 20, 30) and flat_valid.shape == (2, 1, 20, 30)
    assert torch.allclose(flat, torch.tensor([0.0, 0.0, -1.0])[None, :, None, None].expand_as(flat), atol=1e-6)


def test_dense_normals_invalid_next_to_missing_depth_and_differentiable():
    depth = torch.full((20, 30), 5.0)
    depth[10, 15] = 0.0
    normals, valid = dense_normals(depth, K)
    # one-sided differences reach the 4 neighbours: the pixel and its 4-neighbourhood are invalid
    invalid = {tuple(p) for p in torch.nonzero(~valid).tolist()}
    assert invalid == {(10, 15), (9, 15), (11, 15), (10, 14), (10, 16)}
    assert bool((normals[:, ~valid] == 0).all())

    d = plane_depth(unit(0.3, -0.8, -0.5), 5.0)[100:120, 500:530].clone().requires_grad_(True)
    n, _ = dense_normals(d, K)
    n[0].sum().backward()
    assert d.grad is not None and bool(torch.isfinite(d.grad).all())


# --------------------------------------------------------------------------- aggregate_normals


def test_aggregate_normals_means_and_flags():
    labels = torch.tensor([[0, 0, 1, 1, 2], [0, 0, 1, 1, 3]])
    z, y = torch.tensor([0.0, 0.0, -1.0]), torch.tensor([0.0, -1.0, 0.0])
    normals = torch.zeros(3, 2, 5)
    valid = torch.zeros(2, 5, dtype=torch.bool)
    normals[:, 0, 0], normals[:, 0, 1], normals[:, 1, 0] = z, z, y  # node 0: two z, one y
    normals[:, 1, 1] = torch.tensor([5.0, 5.0, 5.0])  # invalid pixel: must be ignored
    valid[0, 0] = valid[0, 1] = valid[1, 0] = True
    normals[:, 0, 2], normals[:, 0, 3] = z, -z  # node 1: opposite normals cancel
    valid[0, 2] = valid[0, 3] = True
    normals[:, 0, 4] = y  # node 2: one valid normal; node 3: none
    valid[0, 4] = True

    node_normals, node_valid = aggregate_normals(normals, valid, labels, 4)
    assert node_valid.tolist() == [True, False, True, False]
    assert torch.allclose(node_normals[0], (2 * z + y) / math.sqrt(5.0))
    assert torch.allclose(node_normals[2], y)
    assert bool((node_normals[[1, 3]] == 0).all())
    with pytest.raises(InputError, match="labels"):
        aggregate_normals(normals, valid, labels, 3)


# --------------------------------------------------------------------------- real frame


@pytest.mark.kitti
def test_real_frame_road_normals_point_up(kitti_root):
    from crfdepth.data.kitti import KittiValSelection

    sample = KittiValSelection(kitti_root / "depth_selection" / "val_selection_cropped")[0]
    normals, valid = lidar_normals(sample.sparse, sample.K)
    hits = sample.sparse > 0
    assert int(valid.sum()) > 0.9 * int(hits.sum())  # measured 0.97
    road = torch.zeros(H, W, dtype=torch.bool)
    road[300:, 450:750] = True  # the lane in front of the car
    sel = valid[0] & road
    err = angle_deg(normals, sel, unit(0.0, -1.0, 0.0))
    assert int(sel.sum()) > 500
    assert err.median().item() < 5.0  # measured 2.4 (includes the camera's pitch)
    points = back_project(sample.sparse[0].double())
    assert bool(((normals.double() * points).sum(0)[valid[0]] < 0).all())


# --------------------------------------------------------------------------- graph_normals


def _ring_graph(n: int) -> torch.Tensor:
    """Each node linked to the next three (a connected graph with 3n edges)."""
    i = torch.arange(n)
    return torch.cat([torch.stack([i, (i + k) % n]) for k in (1, 2, 3)], 1)


def test_graph_normals_gradient_matches_finite_differences_on_a_tilted_plane():
    gen = torch.Generator().manual_seed(0)
    uv = torch.rand(30, 2, generator=gen, dtype=torch.float64) * 4 - 2
    noise = 0.05 * torch.randn(30, generator=gen, dtype=torch.float64)
    points = torch.stack([uv[:, 0], uv[:, 1], 10 + 0.3 * uv[:, 0] - 0.2 * uv[:, 1] + noise], 1)
    edges, weights = _ring_graph(30), torch.randn(30, 3, generator=gen, dtype=torch.float64)
    points.requires_grad_(True)
    (graph_normals(points, edges, 30) * weights).sum().backward()
    direction = torch.randn(30, 3, generator=gen, dtype=torch.float64)
    h = 1e-6
    with torch.no_grad():
        plus = (graph_normals(points + h * direction, edges, 30) * weights).sum()
        minus = (graph_normals(points - h * direction, edges, 30) * weights).sum()
    fd = float((plus - minus) / (2 * h))
    assert float((points.grad * direction).sum()) == pytest.approx(fd, rel=1e-5)
    assert fd != 0.0


def test_graph_normals_of_collinear_points_have_a_finite_zero_gradient():
    # A line of points has no plane: lambda_0 == lambda_1, the eigenvector derivative is
    # unbounded. Such fits are kept out of the differentiated eigh.
    points = torch.zeros(6, 3, dtype=torch.float64)
    points[:, 0], points[:, 2] = torch.arange(6.0), 10.0
    points.requires_grad_(True)
    edges = torch.tensor([[0, 1, 2, 3, 4], [1, 2, 3, 4, 5]])
    normals = graph_normals(points, edges, 6)
    normals[1:5].sum().backward()
    assert torch.isfinite(normals).all() and torch.equal(points.grad, torch.zeros_like(points))


def test_batched_eigh_in_pieces_equals_one_call_with_its_gradient():
    # CUDA batches are cut below cuSOLVER's 65,536-matrix limit; the pieces must give one call's
    # eigenvalues, eigenvectors (up to sign) and gradient. Cut here on the CPU with a small chunk.
    assert EIGH_CUDA_CHUNK < 65536
    generator = torch.Generator().manual_seed(0)
    a = torch.randn(50, 3, 5, dtype=torch.float64, generator=generator)
    cov = (a @ a.transpose(1, 2)).requires_grad_(True)
    values, vectors = torch.linalg.eigh(cov)
    (values.sum() + vectors[:, :, 0].abs().sum()).backward()
    whole = cov.grad.clone()
    cov.grad = None
    got_values, got_vectors = batched_eigh(cov, chunk=7)  # 8 pieces, the last of 1
    (got_values.sum() + got_vectors[:, :, 0].abs().sum()).backward()
    assert torch.allclose(got_values, values, atol=1e-12)
    assert torch.allclose(got_vectors.abs(), vectors.abs(), atol=1e-10)
    assert torch.allclose(cov.grad, whole, atol=1e-10)


def test_closed_form_smallest_eigenvector_matches_eigh():
    generator = torch.Generator().manual_seed(0)
    # plane-like point sets (one thin direction) in random orientations, and generic covariances
    points = torch.randn(500, 20, 3, dtype=torch.float64, generator=generator)
    points = points * torch.tensor([1.0, 0.4, 0.01], dtype=torch.float64)
    rotation, _ = torch.linalg.qr(torch.randn(500, 3, 3, dtype=torch.float64, generator=generator))
    points = points @ rotation
    planes = torch.einsum("nki,nkj->nij", points, points) / 20
    a = torch.randn(500, 3, 3, dtype=torch.float64, generator=generator)
    for cov in (planes, a @ a.transpose(1, 2)):
        values, vectors = torch.linalg.eigh(cov)
        got = smallest_eigenvector(cov)
        assert torch.allclose(got.norm(dim=1), torch.ones(500, dtype=torch.float64))
        separated = (values[:, 1] - values[:, 0]) > 1e-6 * values[:, 2]
        cosine = (got * vectors[:, :, 0]).sum(1).abs()
        assert float((1 - cosine[separated]).max()) < 1e-10
    # isotropic (every vector an eigenvector) and diagonal inputs
    assert torch.equal(smallest_eigenvector(2 * torch.eye(3, dtype=torch.float64)[None]),
                       torch.tensor([[0.0, 0.0, 1.0]], dtype=torch.float64))
    diagonal = smallest_eigenvector(torch.diag(torch.tensor([3.0, 1.0, 2.0], dtype=torch.float64))[None])
    assert torch.allclose(diagonal.abs(), torch.tensor([[0.0, 1.0, 0.0]], dtype=torch.float64))
