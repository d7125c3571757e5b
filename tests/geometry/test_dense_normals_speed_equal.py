"""dense_normals (plane by plane, float masks, no cat) against the implementation it replaced.

``_reference_*`` below is that implementation, verbatim but for the names: (B, 3, H, W)
points, ``narrow`` on channel-strided views, ``torch.where`` and ``torch.cat``. The new one
must give the same normals, the same ``valid`` and the same gradients with respect to depth
(but a finite one where the reference's is NaN). Both do the same float operations in the
same order, so they agree to the bit on the CPU; the tolerances below leave room for a
reordered summation in the backward pass only.
"""

from __future__ import annotations

import pytest
import torch
import torch.nn.functional as F

from crfdepth.data.synthetic import make_scene
from crfdepth.fill.nearest import nearest_fill
from crfdepth.geometry.normals import _as_batch, _restore, camera_points, dense_normals

# (normals atol, gradient rtol, gradient atol as a fraction of the largest reference gradient)
TOL = {torch.float32: (1e-6, 1e-5, 1e-5), torch.float64: (1e-12, 1e-10, 1e-10)}


def _reference_camera_points(depth: torch.Tensor, K: torch.Tensor) -> torch.Tensor:
    _, h, w = depth.shape
    u = torch.arange(w, dtype=depth.dtype, device=depth.device)
    v = torch.arange(h, dtype=depth.dtype, device=depth.device)
    fx, fy, cx, cy, skew = (K[:, 0, 0, None], K[:, 1, 1, None], K[:, 0, 2, None], K[:, 1, 2, None], K[:, 0, 1, None])
    ray_y = (v - cy) / fy  # (B, H)
    ray_x = ((u - cx)[:, None, :] - (skew * ray_y)[:, :, None]) / fx[:, :, None]  # (B, H, W)
    return torch.stack([depth * ray_x, depth * ray_y[:, :, None], depth], 1)


def _reference_one_sided(points: torch.Tensor, dim: int) -> torch.Tensor:
    n = points.shape[dim]
    diff = points.narrow(dim, 1, n - 1) - points.narrow(dim, 0, n - 1)  # diff[k] = p[k+1] - p[k]
    if n == 2:
        return torch.cat([diff, diff], dim)
    fwd, bwd = diff.narrow(dim, 1, n - 2), diff.narrow(dim, 0, n - 2)  # the two sides of pixels 1 .. n-2
    inner = torch.where(fwd[:, 2:].abs() <= bwd[:, 2:].abs(), fwd, bwd)
    return torch.cat([diff.narrow(dim, 0, 1), inner, diff.narrow(dim, n - 2, 1)], dim)


def _reference_dense_normals(depth: torch.Tensor, K: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    batch, K, shape = _as_batch(depth, K, "depth")
    points = _reference_camera_points(batch, K)  # (B, 3, H, W)
    ax, ay, az = _reference_one_sided(points, 3).unbind(1)  # along the row (du) ...
    bx, by, bz = _reference_one_sided(points, 2).unbind(1)  # ... and down the column (dv)
    nx, ny, nz = ay * bz - az * by, az * bx - ax * bz, ax * by - ay * bx
    length = (nx * nx + ny * ny + nz * nz).sqrt().clamp_min(1e-12)
    facing = nx * points[:, 0] + ny * points[:, 1] + nz * points[:, 2]
    missing = F.pad(batch <= 0, (1, 1, 1, 1))
    valid = ~(missing[:, 1:-1, 1:-1] | missing[:, :-2, 1:-1] | missing[:, 2:, 1:-1]
              | missing[:, 1:-1, :-2] | missing[:, 1:-1, 2:])  # (B, H, W): the pixel and its 4 neighbours
    scale = torch.where(facing > 0, -1.0, 1.0).to(batch.dtype) * valid.to(batch.dtype) / length
    normals = torch.stack([nx * scale, ny * scale, nz * scale], 1)
    return _restore(normals, valid, shape)


def assert_same(depth: torch.Tensor, K: torch.Tensor) -> None:
    """Same normals, valid and gradient (of a random weighting of the normals) as the reference."""
    atol, rtol, gtol = TOL[depth.dtype]
    ours_in, ref_in = depth.clone().requires_grad_(True), depth.clone().requires_grad_(True)
    normals, valid = dense_normals(ours_in, K)
    ref_normals, ref_valid = _reference_dense_normals(ref_in, K)
    assert normals.shape == ref_normals.shape and normals.dtype == ref_normals.dtype
    assert valid.shape == ref_valid.shape and valid.dtype == torch.bool
    assert torch.equal(valid, ref_valid)
    torch.testing.assert_close(normals, ref_normals, atol=atol, rtol=0)
    weights = torch.randn(normals.shape, generator=torch.Generator().manual_seed(7), dtype=depth.dtype)
    (normals * weights).sum().backward()
    (ref_normals * weights).sum().backward()
    # The reference's gradient is NaN near a zero normal (no depth around: the root's 0 / 0); the
    # new one clamps before the root and is finite there, and the same everywhere else.
    defined = ~ref_in.grad.isnan()
    assert bool(torch.isfinite(ours_in.grad).all())
    ours, ref = ours_in.grad[defined], ref_in.grad[defined]
    torch.testing.assert_close(ours, ref, rtol=rtol, atol=gtol * max(float(ref.abs().max()), 1.0))


def test_real_kitti_frame_nearest_filled(kitti_root):
    from crfdepth.data.kitti import KittiValSelection

    path = kitti_root / "depth_selection" / "val_selection_cropped"
    if not path.is_dir():
        pytest.skip(f"no KITTI val_selection_cropped at {path}")
    sample = KittiValSelection(path)[0]
    depth = nearest_fill(sample.sparse)  # (1, H, W), > 0 everywhere
    assert_same(depth, sample.K)
    holes = depth.clone()
    holes[:, 100:140, 300:420] = 0.0  # invalid pixels, and the reference's NaN gradients
    assert_same(holes, sample.K)


@pytest.mark.parametrize("seed", [0, 1])
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_synthetic_scenes(seed, dtype):
    frame = make_scene(seed, height=96, width=320).to_tensors()
    K = frame["K"].to(dtype)
    assert_same(frame["depth"].to(dtype), K)  # 0 = sky: invalid pixels
    assert_same(nearest_fill(frame["sparse"]).to(dtype), K)


def test_full_size_synthetic_scene_with_zeros():
    frame = make_scene(3).to_tensors()  # 1216 x 352
    assert bool((frame["depth"] == 0).any())
    assert_same(frame["depth"], frame["K"])


@pytest.mark.parametrize("shape", [(2, 2), (2, 9), (9, 2), (3, 3), (1, 2, 5), (1, 1, 6, 2)])
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_tiny_frames_and_layouts(shape, dtype):
    g = torch.Generator().manual_seed(sum(shape))
    depth = (torch.rand(shape, generator=g, dtype=torch.float64) * 9 + 1).to(dtype)
    K = torch.tensor([[3.0, 0.0, 1.2], [0.0, 2.5, 0.7], [0.0, 0.0, 1.0]], dtype=dtype)
    assert_same(depth, K)
    if depth.numel() > 4:
        depth.view(-1)[depth.numel() // 2] = 0.0  # a missing pixel
        assert_same(depth, K)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_batch_of_two_with_different_intrinsics_and_skew(dtype):
    g = torch.Generator().manual_seed(5)
    depth = (torch.rand(2, 1, 13, 17, generator=g, dtype=torch.float64) * 20 + 2).to(dtype)
    depth[1, 0, 4:7, 5:9] = 0.0
    K = torch.tensor([[[12.0, 0.0, 8.0], [0.0, 11.0, 6.0], [0.0, 0.0, 1.0]],
                      [[15.0, 2.5, 7.0], [0.0, 14.0, 5.5], [0.0, 0.0, 1.0]]], dtype=dtype)
    assert K[1, 0, 1] != 0  # skew
    assert_same(depth, K)
    assert_same(depth, K[1])  # one (3, 3) K with skew for both frames
    normals, valid = dense_normals(depth, K)
    assert normals.shape == (2, 3, 13, 17) and valid.shape == (2, 1, 13, 17)


def test_camera_points_unchanged_with_and_without_skew():
    depth = torch.rand(2, 7, 9, dtype=torch.float64) * 10
    for skew in (0.0, 1.5):
        K = torch.tensor([[8.0, skew, 4.0], [0.0, 9.0, 3.0], [0.0, 0.0, 1.0]], dtype=torch.float64).expand(2, 3, 3)
        assert torch.equal(camera_points(depth, K), _reference_camera_points(depth, K))
        K_grad, K_ref = K.clone().requires_grad_(True), K.clone().requires_grad_(True)
        camera_points(depth, K_grad).square().sum().backward()
        _reference_camera_points(depth, K_ref).square().sum().backward()
        torch.testing.assert_close(K_grad.grad, K_ref.grad, rtol=1e-12, atol=1e-12)


def test_gradcheck_float64():
    depth = (torch.rand(5, 6, generator=torch.Generator().manual_seed(11), dtype=torch.float64) * 4 + 1)
    K = torch.tensor([[6.0, 0.3, 2.5], [0.0, 5.0, 2.0], [0.0, 0.0, 1.0]], dtype=torch.float64)
    assert torch.autograd.gradcheck(lambda d: dense_normals(d, K)[0], (depth.requires_grad_(True),))
