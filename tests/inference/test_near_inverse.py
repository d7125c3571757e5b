"""The coarse solve's near pixels from the inverse-depth unknown (``Structure.near_inverse``, docs/design.md
section 17)."""

from __future__ import annotations

import math

import pytest
import torch

from crfdepth.errors import InputError
from crfdepth.fill.nearest import trusted_nearest_fill
from crfdepth.inference.coarse import coarse_frame, paint
from crfdepth.inference.pixel import coarse_solve, pixel_solve
from crfdepth.model import CRFDepth
from tests.scenes import table4_frames, table4_scores

NEAR = 10.0  # the shipped value (crfdepth/weights/files.py SPARSE_REGIMES)


def _street(h=60, w=120, count=120, seed=0):
    """A road seen in perspective (depth 1/(rows) from 4 m at the bottom to 60 m at the top) with a wall on the
    left at 8 m; ``count`` random returns."""
    g = torch.Generator().manual_seed(seed)
    rows = torch.arange(h, dtype=torch.float32)[:, None].expand(h, w)
    depth = 1.0 / (1.0 / 60.0 + (1.0 / 4.0 - 1.0 / 60.0) * rows / (h - 1))
    depth = depth.clone()
    depth[:, : w // 4] = 8.0
    image = torch.rand(1, 3, h, w, generator=g) * 0.05 + 0.3
    image[..., : w // 4] += 0.4
    sparse = torch.zeros(1, 1, h, w)
    pick = torch.randperm(h * w, generator=g)[:count]
    sparse.view(-1)[pick] = depth.reshape(-1)[pick]
    K = torch.tensor([[100.0, 0.0, w / 2], [0.0, 100.0, h / 2], [0.0, 0.0, 1.0]])[None]
    return image, sparse, K, depth[None, None]


@pytest.mark.parametrize("value", [-1.0, float("nan"), float("inf"), "x", 1001.0])
def test_near_inverse_must_be_a_depth(value):
    with pytest.raises(InputError, match="near_inverse"):
        CRFDepth(mode="pixel", coarse=6, near_inverse=value)


@pytest.mark.parametrize("options", [{"mode": "pixel"}, {"mode": "pixel", "coarse": 6, "variable": "log"},
                                     {"coarse": 6}])
def test_near_inverse_needs_the_depth_unknown_with_a_coarse_solve(options):
    with pytest.raises(InputError, match="near_inverse") as info:
        CRFDepth(**options, near_inverse=10.0)
    assert "coarse" in str(info.value) and "variable" in str(info.value)


def test_coarse_depth_takes_the_inverse_solution_near_and_the_depth_solution_far():
    image, sparse, K, _ = _street()
    block = (6, 6)
    with torch.no_grad():
        depth = coarse_solve(CRFDepth(mode="pixel", coarse=6), image, sparse, K, block, [])
        inverse = coarse_solve(CRFDepth(mode="pixel", coarse=6, variable="inverse"), image, sparse, K, block, [])
        near_all = coarse_solve(CRFDepth(mode="pixel", coarse=6, near_inverse=999.0), image, sparse, K, block, [])
        near_none = coarse_solve(CRFDepth(mode="pixel", coarse=6, near_inverse=1e-3), image, sparse, K, block, [])
        infos: list = []
        blended = coarse_solve(CRFDepth(mode="pixel", coarse=6, near_inverse=10.0), image, sparse, K, block, infos)
    assert not torch.allclose(depth, inverse, rtol=1e-3)  # the two unknowns interpolate differently
    # the second solve is the inverse unknown's on the same blocks with the same system (normals and distances
    # from the depth unknown's first pass): a solve of the inverse unknown with that geometry
    model = CRFDepth(mode="pixel", coarse=6)
    grid = coarse_frame(image, sparse, K, block, "depth")
    fill = trusted_nearest_fill(grid[1])
    first, _, _ = pixel_solve(CRFDepth(mode="pixel", coarse=6, potentials=("colour",)), *grid, fill,
                              model.scales()[4], [])  # the first pass alone
    second, _, _ = pixel_solve(model, *grid, fill, model.scales()[4], [], geometry=first, variable="inverse")
    torch.testing.assert_close(near_all, paint(second, block, tuple(sparse.shape[2:])), rtol=1e-4, atol=1e-4)
    torch.testing.assert_close(near_all, inverse, rtol=0.03, atol=0.0)  # its own normals: 1.5% apart here
    torch.testing.assert_close(near_none, depth, rtol=1e-5, atol=1e-5)
    assert len(infos) == 3  # two passes of the depth unknown, one of the inverse
    # between the two everywhere, and each alone where it should be (the painted blocks blend a little)
    low, high = torch.minimum(depth, near_all), torch.maximum(depth, near_all)
    assert bool(((blended >= low - 1e-4) & (blended <= high + 1e-4)).all())
    near, far = depth < 8.0, depth > 35.0
    assert near.any() and far.any()
    torch.testing.assert_close(blended[near], near_all[near], rtol=0.02, atol=0.0)
    torch.testing.assert_close(blended[far], depth[far], rtol=0.02, atol=0.0)


def test_near_inverse_has_gradients_for_the_weights():
    image, sparse, K, truth = _street(h=48, w=96, count=80)
    model = CRFDepth(mode="pixel", coarse=4, near_inverse=10.0)
    loss = ((model(image, sparse, K).depth - truth) ** 2).mean()
    loss.backward()
    grads = [p.grad for p in model.parameters() if p.grad is not None]
    assert grads and all(torch.isfinite(g).all() for g in grads) and any(float(g.abs().sum()) > 0 for g in grads)


def test_default_scattered_regime_reads_near_pixels_in_inverse_depth():
    regime = CRFDepth.from_pretrained().sparse_regime
    assert regime.settings.structure.near_inverse == pytest.approx(NEAR)
    assert CRFDepth.from_pretrained().line_regime.settings.structure.near_inverse == 0.0



def test_near_inverse_lowers_rel_at_500_kitti_samples_and_keeps_the_rmse(kitti_root):
    models = {"plain": CRFDepth(mode="pixel", coarse=6), "near": CRFDepth(mode="pixel", coarse=6, near_inverse=NEAR)}
    mean = table4_scores(models, table4_frames(kitti_root, 500, step=2))
    # measured on all 14 raw frames: RMSE +0.2%, REL -7% (docs/design.md section 17)
    assert mean["near"][1] < 0.96 * mean["plain"][1]
    assert mean["near"][0] < 1.01 * mean["plain"][0]
    assert all(math.isfinite(x) for v in mean.values() for x in v)
