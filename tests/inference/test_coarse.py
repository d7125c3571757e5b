"""The pixel grid's coarse first solve and the default model's sparse regime (docs/design.md section 17)."""

from __future__ import annotations

import pytest
import torch

from crfdepth.data.nyu.layouts import build_nyu_dataset
from crfdepth.errors import InputError
from crfdepth.inference.coarse import (
    LINE_STRETCH,
    SPARSE_DISTANCE,
    block_shape,
    coarse_frame,
    few_returns,
    line_scan,
    median_return_distance,
    paint,
)
from crfdepth.model import CRFDepth


def _scene(h=48, w=64, every=None, count=None, seed=0, depths=(4.0, 8.0)):
    """A tilted plane (depth ``depths``, metres) with a vertical colour edge; returns on a regular grid
    (``every``) or at ``count`` random pixels."""
    g = torch.Generator().manual_seed(seed)
    rows = torch.linspace(*depths, h)[:, None].expand(h, w)
    image = torch.rand(1, 3, h, w, generator=g) * 0.05 + 0.4
    image[..., w // 2:] += 0.3
    sparse = torch.zeros(1, 1, h, w)
    if every:
        sparse[..., ::every, ::every] = rows[::every, ::every]
    else:
        pick = torch.randperm(h * w, generator=g)[:count]
        sparse.view(-1)[pick] = rows.reshape(-1)[pick]
    K = torch.tensor([[60.0, 0.0, w / 2], [0.0, 60.0, h / 2], [0.0, 0.0, 1.0]])[None]
    return image, sparse, K, rows[None, None]


def test_coarse_frame_averages_blocks_and_keeps_pixel_centres():
    image, sparse, K, _ = _scene(h=12, w=12)
    sparse.zero_()
    sparse[0, 0, 0, 0], sparse[0, 0, 1, 1] = 2.0, 8.0  # one block, two returns
    sparse[0, 0, 5, 7] = 3.0  # block (1, 1) of 4-pixel blocks: one return
    img, coarse, cK = coarse_frame(image, sparse, K, (4, 4), "log")
    assert coarse.shape == (1, 1, 3, 3) and img.shape == (1, 3, 3, 3)
    assert coarse[0, 0, 0, 0] == pytest.approx(4.0, rel=1e-5)  # geometric mean of 2 and 8
    assert coarse[0, 0, 1, 1] == pytest.approx(3.0, rel=1e-5) and int((coarse > 0).sum()) == 2
    assert coarse_frame(image, sparse, K, (4, 4), "depth")[1][0, 0, 0, 0] == pytest.approx(5.0, rel=1e-5)
    assert img[0, :, 2, 1] == pytest.approx(image[0, :, 8:12, 4:8].mean((1, 2)), abs=1e-6)
    # a point at the centre of fine pixels 4..7 (u = 5.5) is at the centre of coarse pixel 1
    fine_u = K[0, 0, 0] * 0.3 + K[0, 0, 2]
    coarse_u = cK[0, 0, 0] * 0.3 + cK[0, 0, 2]
    assert float(coarse_u) == pytest.approx((float(fine_u) + 0.5) / 4 - 0.5, abs=1e-5)


def test_coarse_frame_pads_sizes_that_are_not_a_multiple_of_the_block():
    image, sparse, K, _ = _scene(h=13, w=17, every=2)
    img, coarse, _ = coarse_frame(image, sparse, K, (6, 6), "depth")
    assert img.shape[2:] == coarse.shape[2:] == (3, 3)
    assert paint(coarse, (6, 6), (13, 17)).shape == (1, 1, 13, 17)
    assert block_shape(6, sparse) == (6, 6) and block_shape(1, sparse) == (1, 1)
    assert block_shape(6, sparse[..., :6, :]) == (1, 1)  # a block grid of 1 x 3: no coarse solve


def test_tall_blocks_scale_each_axis_of_the_intrinsics():
    image, sparse, K, _ = _scene(h=24, w=24, every=2)
    img, coarse, cK = coarse_frame(image, sparse, K, (8, 4), "depth")
    assert img.shape[2:] == coarse.shape[2:] == (3, 6)
    for axis, b in ((0, 4), (1, 8)):  # a point's coarse coordinate is (fine + 0.5) / b - 0.5 on each axis
        fine = K[0, axis, axis] * 0.2 + K[0, axis, 2]
        coarse_at = cK[0, axis, axis] * 0.2 + cK[0, axis, 2]
        assert float(coarse_at) == pytest.approx((float(fine) + 0.5) / b - 0.5, abs=1e-5)
    assert paint(coarse, (8, 4), (24, 24)).shape == (1, 1, 24, 24)


def _rings(h=120, w=200, every=8, seed=0):
    """Returns on every ``every``-th row, each ring a little wavy and with gaps, as a spinning LiDAR's."""
    g = torch.Generator().manual_seed(seed)
    sparse = torch.zeros(1, 1, h, w)
    cols = torch.arange(w)
    for row in range(every // 2, h, every):
        rows = (row + 1.5 * torch.sin(cols / 30.0 + row)).round().long().clamp(0, h - 1)
        keep = torch.rand(w, generator=g) < 0.6
        sparse[0, 0, rows[keep], cols[keep]] = 10.0
    return sparse


def test_line_scan_tells_rings_from_scattered_returns():
    rings = _rings()
    scattered = torch.zeros_like(rings)
    scattered.view(-1)[torch.randperm(rings.numel(), generator=torch.Generator().manual_seed(1))[:500]] = 10.0
    holes = torch.full_like(rings, 3.0)  # a depth image with a square hole
    holes[..., 40:80, 60:120] = 0.0
    assert line_scan(torch.cat([rings, scattered, holes])).tolist() == [True, False, False]
    assert line_scan(rings.transpose(2, 3)).tolist() == [False]  # vertical lines are not a LiDAR's rings
    assert block_shape(6, rings) == (LINE_STRETCH * 6, 6) and block_shape(6, scattered) == (6, 6)
    assert block_shape(6, torch.cat([rings, scattered])) == (6, 6)  # a mixed batch keeps square blocks
    # a caller that has read the layout says so, and it is not read again
    assert block_shape(6, scattered, lines=True) == (LINE_STRETCH * 6, 6) and block_shape(6, rings, lines=False) == (6, 6)


@pytest.mark.parametrize("every", [2, 4, 8, 16])
def test_median_return_distance_grows_with_the_spacing_of_the_returns(every):
    _, sparse, _, _ = _scene(h=96, w=128, every=every)
    d = float(median_return_distance(sparse)[0])
    assert 0.25 * every <= d <= 0.6 * every  # about half the gap between returns


def test_coarse_solve_has_gradients_for_the_weights():
    image, sparse, K, truth = _scene(h=48, w=64, count=40)
    model = CRFDepth(mode="pixel", coarse=4)
    loss = ((model(image, sparse, K).depth - truth) ** 2).mean()
    loss.backward()
    grads = [p.grad for p in (model._raw_alpha, model._raw_beta)] if hasattr(model, "_raw_alpha") else \
        [p.grad for p in model.parameters() if p.grad is not None]
    assert grads and all(torch.isfinite(g).all() for g in grads) and any(float(g.abs().sum()) > 0 for g in grads)


@pytest.mark.parametrize("value", [0, -2, 1.5, True, 65])
def test_coarse_must_be_a_block_side(value):
    with pytest.raises(InputError, match="coarse"):
        CRFDepth(mode="pixel", coarse=value)


def test_default_model_sends_only_frames_with_few_returns_to_its_sparse_regime():
    model = CRFDepth.from_pretrained()
    assert model.sparse_regime is not None and model.sparse_regime.settings.structure.coarse == 6
    assert CRFDepth.from_pretrained(adaptive=False).sparse_regime is None
    assert CRFDepth.from_pretrained(mode="superpixel").sparse_regime is None
    assert CRFDepth.from_pretrained(potentials=("colour",)).sparse_regime is None
    assert CRFDepth.from_pretrained(structure={"variable": "inverse"}).sparse_regime is None
    assert CRFDepth.from_pretrained(gate=False, rtol=1e-4).sparse_regime is not None  # what complete --depth asks
    assert CRFDepth.from_pretrained("paper").sparse_regime is None
    with pytest.raises(InputError, match="adaptive"):
        CRFDepth.from_pretrained(adaptive="yes")
    fixed, regime = CRFDepth.from_pretrained(adaptive=False), model.sparse_regime
    dense, sparse_frame = _scene(h=64, w=96, every=2), _scene(h=64, w=96, count=40, depths=(12.0, 40.0))
    assert float(median_return_distance(dense[1])) <= SPARSE_DISTANCE < float(median_return_distance(sparse_frame[1]))
    with torch.no_grad():
        assert torch.equal(model(*dense[:3]).depth, fixed(*dense[:3]).depth)
        assert torch.equal(model(*sparse_frame[:3]).depth, regime(*sparse_frame[:3]).depth)
        both = [torch.cat([a, b]) for a, b in zip(dense[:3], sparse_frame[:3])]
        out = model(*both, return_std=True)
        alone = [model(*frame[:3], return_std=True) for frame in (dense, sparse_frame)]
    for i, one in enumerate(alone):
        assert torch.allclose(out.depth[i], one.depth[0], rtol=1e-5, atol=1e-5)
        assert torch.allclose(out.std[i], one.std[0], rtol=1e-5, atol=1e-5)
    assert out.node_depth.numel() == out.depth.numel() and out.terms is None


def test_default_model_sends_few_returns_on_scan_lines_to_its_line_regime():
    model = CRFDepth.from_pretrained()
    lines, scattered = model.line_regime, model.sparse_regime
    assert lines.settings.structure.variable == "log" and scattered.settings.structure.variable == "depth"
    assert lines.settings.structure.coarse == scattered.settings.structure.coarse == 6
    image, _, K, _ = _scene(h=120, w=200)
    rings = _rings(every=24)
    assert bool(few_returns(rings)) and bool(line_scan(rings))
    with torch.no_grad():
        assert torch.equal(model(image, rings, K).depth, lines(image, rings, K).depth)
        # a ring frame and a scattered frame in one batch: each gets its own regime
        sparse = _scene(h=120, w=200, count=150, depths=(12.0, 40.0))[1]
        assert bool(few_returns(sparse)) and not bool(line_scan(sparse))
        both = model(torch.cat([image, image]), torch.cat([rings, sparse]), K[0])
        assert torch.allclose(both.depth[1], scattered(image, sparse, K).depth[0], rtol=1e-5, atol=1e-5)
        assert torch.allclose(both.depth[0], lines(image, rings, K).depth[0], rtol=1e-5, atol=1e-5)
    assert CRFDepth.from_pretrained(adaptive=False).line_regime is None
    model.double()
    assert all(p.dtype == torch.float64 for p in model.line_regime.parameters())


def test_sparse_regime_stays_out_of_the_state_and_moves_with_the_model():
    model = CRFDepth.from_pretrained()
    assert set(model.state_dict()) == set(CRFDepth.from_pretrained(adaptive=False).state_dict())
    assert all(p is not q for p in model.parameters() for q in model.sparse_regime.parameters())
    model.double()
    assert all(p.dtype == torch.float64 for p in model.sparse_regime.parameters())


def test_default_model_is_better_with_500_samples_of_real_indoor_frames(nyu_root):
    frames = build_nyu_dataset("nyu_sync", nyu_root / "official_test", samples=500, seed=0)
    adaptive, fixed = CRFDepth.from_pretrained(), CRFDepth.from_pretrained(adaptive=False)
    errors = {"adaptive": [], "fixed": []}
    for s in frames:
        for name, model in (("adaptive", adaptive), ("fixed", fixed)):
            with torch.no_grad():
                depth = model(s.image[None], s.sparse[None], s.K[None]).depth[0]
            valid = s.target > 0
            errors[name].append(float(((depth[valid] - s.target[valid]) ** 2).mean().sqrt()))
    # measured 0.96-0.98 x per frame on these three frames (docs/design.md section 17)
    assert sum(errors["adaptive"]) < 0.99 * sum(errors["fixed"])


@pytest.mark.parametrize("count", [20, 60, 150, 300, 600, 2000])
def test_few_returns_agrees_with_the_exact_median_distance(count):
    for seed in range(3):
        _, sparse, _, _ = _scene(h=64, w=96, count=count, seed=seed)
        median = float(median_return_distance(sparse))
        assert bool(few_returns(sparse, stride=1)) == (median > SPARSE_DISTANCE)
        if abs(median - SPARSE_DISTANCE) > 0.5:  # the default asks every third pixel of every third row
            assert bool(few_returns(sparse)) == (median > SPARSE_DISTANCE)


def test_few_returns_on_rings_and_on_a_depth_image_with_holes():
    rings = torch.zeros(2, 1, 120, 200)
    rings[0, :, ::3, :] = 5.0  # a ring every 3 rows: every pixel within 1 px
    rings[1, :, ::24, :] = 5.0  # every 24 rows: 9 rows in 24 within 4.5 px
    assert few_returns(rings).tolist() == [False, True]
    assert torch.equal(few_returns(rings, stride=1), median_return_distance(rings) > SPARSE_DISTANCE)
