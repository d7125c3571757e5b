"""The compiled predictive std and nearest search (crfdepth/native/predictive_std.h, nearest.h) against the eager torch
path, their reference: the same signals and std on the same inputs, every variable, with and without the gate,
both dtypes, frames down to one row or column, and the model's output with the kernels on and off."""

import math

import numpy as np
import pytest
import torch
from scipy.ndimage import distance_transform_edt

from crfdepth import native
from crfdepth.fill.nearest import nearest_fill
from crfdepth.inference.pixel import grid_std, predictive_std
from crfdepth.model import CRFDepth
from crfdepth.uncertainty.posterior import grid_conditional_variance
from crfdepth.uncertainty.predictive import return_distance


class _System:  # what grid_std reads of a linalg System
    def __init__(self, diagonal, weight_h, weight_v):
        self.diagonal, self.weights = diagonal, (weight_h, weight_v)


def _frame(seed: int, batch: int, h: int, w: int, dtype, gated: bool):
    g = torch.Generator().manual_seed(seed)
    depth = (torch.rand(batch, 1, h, w, generator=g, dtype=dtype) * 60 + 2)
    depth[..., : h // 2, : w // 3] = 5.0  # a flat patch (edge signal 0) beside a step
    keep = torch.rand(batch, 1, h, w, generator=g, dtype=dtype) < 0.08
    keep[:, :, 0, 0] = True
    sparse = torch.where(keep, depth * (1 + 0.3 * torch.randn(batch, 1, h, w, generator=g, dtype=dtype)).clamp_min(0.2),
                         torch.zeros_like(depth))
    gate = torch.where(keep, torch.rand(batch, 1, h, w, generator=g, dtype=dtype), torch.ones_like(depth)) if gated else None
    kept = sparse if gate is None else torch.where(gate >= 0.5, sparse, torch.zeros_like(sparse))
    kept[:, :, 0, 0] = sparse[:, :, 0, 0].clamp_min(1.0)  # every frame keeps a return
    d = torch.rand(batch, h, w, generator=g, dtype=dtype) * 3 + 1e-3
    wh = torch.rand(batch, h, w - 1, generator=g, dtype=dtype) ** 3 * 10
    wv = torch.rand(batch, h - 1, w, generator=g, dtype=dtype) ** 3 * 10
    return depth, sparse, kept, gate, _System(d, wh, wv)


def _eager(model, depth, sparse, kept, gate, system):
    with native.eager():
        variance = grid_conditional_variance(system.diagonal, *system.weights)[:, None]
        return predictive_std(model, depth, sparse, kept, gate, variance)


@pytest.mark.parametrize("variable", ["log", "depth", "inverse"])
@pytest.mark.parametrize("gated", [True, False])
@pytest.mark.parametrize("dtype, tol", [(torch.float32, 1e-4), (torch.float64, 1e-10)])
@pytest.mark.parametrize("shape", [(2, 23, 41), (1, 1, 19), (1, 17, 1), (1, 3, 4)])
def test_compiled_std_is_the_eager_std(kernels, variable, gated, dtype, tol, shape):
    model = CRFDepth.from_pretrained(variable=variable).to(dtype)
    depth, sparse, kept, gate, system = _frame(sum(shape), *shape, dtype, gated)
    with torch.no_grad():
        std, features = grid_std(model, depth, sparse, kept, gate, system)
        ref_std, ref_features = _eager(model, depth, sparse, kept, gate, system)
    assert std.shape == ref_std.shape and features.shape == ref_features.shape
    assert std.dtype == dtype and features.dtype == dtype
    # the distance to the nearest kept return: exact here (tested below), OpenCV's in the reference, within 1e-4
    assert torch.allclose(features[:, 2], ref_features[:, 2], rtol=1e-4, atol=1e-5)
    assert torch.equal(features[:, 0], ref_features[:, 0])
    # the other signals within tol of their scale (float32: an ulp of a logarithm in the window signals)
    others = [1, 3, 4]
    scale = ref_features[:, others].abs().amax((0, 2, 3)) + 1e-12
    assert torch.all((features[:, others] - ref_features[:, others]).abs().amax((0, 2, 3)) <= tol * scale)
    # the std: a sum of five logarithms through exp, within 1e-4 (the distance's log moves it most)
    assert float(((std - ref_std).abs() / ref_std).max()) <= 1e-4


def test_compiled_std_keeps_the_std_weights_gradient(kernels):
    model = CRFDepth.from_pretrained().double()
    depth, sparse, kept, gate, system = _frame(3, 1, 12, 15, torch.float64, True)
    std, _ = grid_std(model, depth, sparse, kept, gate, system)
    (grad,) = torch.autograd.grad(std.sum(), model.std_head.weights)
    ref_std, _ = _eager(model, depth, sparse, kept, gate, system)
    (ref_grad,) = torch.autograd.grad(ref_std.sum(), model.std_head.weights)
    assert torch.allclose(grad, ref_grad, rtol=1e-4, atol=0)  # the reference's distance is OpenCV's


@pytest.mark.parametrize("seed", range(6))
def test_compiled_fill_and_distance_are_the_eager_ones(kernels, seed):
    g = np.random.default_rng(seed)
    h, w = (int(v) for v in g.integers(1, 60, 2))
    sparse = torch.from_numpy(np.where(g.random((2, 1, h, w)) < [0.003, 0.05, 0.5][seed % 3],
                                       g.random((2, 1, h, w)) * 80 + 1, 0.0)).float()
    sparse[:, :, g.integers(h), g.integers(w)] = 7.0
    filled, distance = kernels.nearest_fill(sparse[:, 0].contiguous())
    with native.eager():
        assert torch.equal(filled[:, None], nearest_fill(sparse))
    exact = np.stack([distance_transform_edt(frame <= 0) for frame in sparse[:, 0].numpy()])
    assert np.allclose(distance.numpy(), exact, rtol=1e-6, atol=0)  # SciPy's exact transform
    assert torch.allclose(distance[:, None], return_distance(sparse), rtol=1e-4, atol=1e-5)  # the eager path's


def test_compiled_distance_of_a_frame_without_returns_is_the_diagonal(kernels):
    sparse = torch.zeros(2, 5, 7)
    sparse[1, 4, 6] = 3.0
    filled, distance = kernels.nearest_fill(sparse)
    assert bool((filled[0] == 0).all()) and torch.allclose(distance[0], torch.full((5, 7), math.hypot(5, 7)))
    assert float(filled[1, 0, 0]) == 3.0 and float(distance[1, 0, 0]) == pytest.approx(math.hypot(4, 6))


@pytest.mark.parametrize("options", [{}, {"mode": "superpixel", "superpixels": 40}])
def test_the_models_std_is_the_same_with_and_without_the_kernels(kernels, options):
    from crfdepth.data.synthetic import SyntheticScenes

    sample = SyntheticScenes(count=1, seed=4, height=48, width=160)[0]
    model = CRFDepth.from_pretrained(**options).double()
    image, sparse, K = sample.image[None].double(), sample.sparse[None].double(), sample.K.double()
    with torch.no_grad():
        out = model(image, sparse, K, return_std=True)
        with native.eager():
            ref = model(image, sparse, K, return_std=True)
    assert torch.allclose(out.depth, ref.depth, rtol=1e-6)  # float64: the solves agree far inside rtol
    assert torch.allclose(out.std, ref.std, rtol=1e-5)
