"""The compiled affinities (crfdepth.native, potentials.h) against grid_potentials' torch path, their reference; a later
round's terms built on the earlier round's are the terms built afresh."""

import pytest
import torch

from crfdepth import native
from crfdepth.data.synthetic import make_scene
from crfdepth.fill.nearest import nearest_fill
from crfdepth.model import CRFDepth
from crfdepth.potentials import compiled, energy


def _frames(dtype, batch: int = 2, size: tuple[int, int] = (48, 64)):
    scenes = [make_scene(seed, *size).to_tensors() for seed in range(batch)]
    image = torch.stack([s["image"] for s in scenes]).to(dtype)
    sparse = torch.stack([s["sparse"] for s in scenes]).to(dtype)
    K = torch.stack([s["K"] for s in scenes]).to(dtype)
    K[1, 0, 1] = 0.7  # a skewed camera in the batch
    geometry = nearest_fill(sparse)
    geometry[0, 0, 5:9, 10:14] = 0.0  # pixels without depth: no normal there
    return image, K, geometry


@pytest.mark.parametrize("dtype, atol", [(torch.float32, 1e-5), (torch.float64, 1e-12)])
@pytest.mark.parametrize("size", [(48, 64), (2, 9), (7, 2), (2, 2)])
def test_compiled_affinities_equal_the_torch_ones(kernels, dtype, atol, size):
    image, K, geometry = _frames(dtype, size=size)
    weights = CRFDepth.from_pretrained("kitti").to(dtype).potential_weights()
    with torch.no_grad():
        fused = compiled.fused_affinities(image, K, geometry, weights)
        reference = energy._affinities(image, K, geometry, weights)
        first_round = compiled.fused_affinities(image, K, None, weights)
    assert fused is not None and first_round is not None and first_round[1] is None and first_round[2] is None
    for got, want in zip(fused, reference):
        for a, b in zip(got, want):
            assert a.shape == b.shape and a.dtype == b.dtype
            torch.testing.assert_close(a, b, atol=atol, rtol=0)
    torch.testing.assert_close(first_round[0][0], reference[0][0], atol=atol, rtol=0)


def test_with_gradients_the_torch_path_runs(kernels):
    image, K, geometry = _frames(torch.float64)
    weights = CRFDepth.from_pretrained("kitti").double().potential_weights()
    geometry.requires_grad_(True)
    assert compiled.fused_affinities(image, K, geometry, weights) is None  # the training path: differentiable
    with torch.no_grad():
        assert compiled.fused_affinities(image, K, geometry, weights) is not None


def test_the_model_gives_the_same_depth_with_and_without_the_kernels(kernels):
    scene = make_scene(3).to_tensors()
    image, sparse, K = scene["image"][None], scene["sparse"][None], scene["K"][None]
    model = CRFDepth.from_pretrained("kitti").eval()
    with torch.inference_mode():
        fast = model(image, sparse, K, return_std=True)
        with native.eager():
            reference = model(image, sparse, K, return_std=True)
    # both stop their CG at rtol 1e-5 with sums in another order: the same answer to a few millimetres
    difference = (fast.depth - reference.depth).abs()
    assert float(difference.max()) < 0.05 and float(difference.quantile(0.99)) < 0.005
    assert float((fast.std / reference.std - 1).abs().max()) < 0.01
    assert [int(i.iterations) for i in fast.info] == pytest.approx([int(i.iterations) for i in reference.info], abs=8)


@pytest.mark.parametrize("compiled", [True, False])
def test_a_later_round_built_on_the_earlier_one_is_the_round_built_afresh(compiled):
    image, K, geometry = _frames(torch.float64)
    sparse = torch.where(torch.rand_like(geometry) < 0.1, geometry, torch.zeros_like(geometry))
    gate = torch.rand_like(geometry)
    weights = CRFDepth.from_pretrained("kitti").double().potential_weights()
    eps = torch.tensor(0.01, dtype=torch.float64)
    args = (image, sparse, K, geometry, eps)
    with torch.no_grad(), (native.eager() if not compiled else torch.no_grad()):
        first = energy.grid_potentials(*args, None, weights, variable="log", gate=gate)
        later = energy.grid_potentials(*args, geometry, weights, variable="log", gate=gate, previous=first)
        fresh = energy.grid_potentials(*args, geometry, weights, variable="log", gate=gate)
    later_system, fresh_system = energy.grid_system(later), energy.grid_system(fresh)
    for a, b in zip((later_system.diagonal, later_system.rhs, *later_system.weights),
                    (fresh_system.diagonal, fresh_system.rhs, *fresh_system.weights)):
        torch.testing.assert_close(a, b, atol=1e-12, rtol=0)


def test_a_later_round_built_on_the_earlier_one_has_the_same_gradients():
    image, K, geometry = _frames(torch.float64, size=(12, 16))
    sparse = torch.where(torch.rand_like(geometry) < 0.2, geometry, torch.zeros_like(geometry))
    model = CRFDepth.from_pretrained("kitti").double()
    eps = torch.tensor(0.01, dtype=torch.float64)

    def loss(reuse: bool) -> list[torch.Tensor]:
        weights = model.potential_weights()
        first = energy.grid_potentials(image, sparse, K, geometry, eps, None, weights, variable="log")
        later = energy.grid_potentials(image, sparse, K, geometry, eps, geometry, weights, variable="log",
                                       previous=first if reuse else None)
        system = energy.grid_system(later)
        total = sum((t ** 2).sum() for t in (system.diagonal, system.rhs, *system.weights))
        return torch.autograd.grad(total, [model.sigma_d, model.sigma_n, model.sigma_p, model.beta, model.confidence],
                                   allow_unused=True)

    for a, b in zip(loss(True), loss(False)):
        torch.testing.assert_close(a, b, atol=1e-10, rtol=1e-10)


@pytest.mark.parametrize("dtype, tol", [(torch.float32, 1e-6), (torch.float64, 1e-14)])
@pytest.mark.parametrize("normal, distance, factor", [(False, False, False), (True, True, False), (True, False, True),
                                                      (False, True, True)])
def test_the_compiled_grid_system_is_torchs(kernels, dtype, tol, normal, distance, factor):
    g = torch.Generator().manual_seed(3)
    b_, h, w = 2, 9, 13

    def maps(*shape):
        return torch.rand(*shape, generator=g, dtype=torch.float64).to(dtype)

    def pair():
        return maps(b_, h, w - 1), maps(b_, h - 1, w)

    scalar = [torch.tensor(v, dtype=dtype) for v in (0.3, 0.7, 0.05, 0.4, 1e-3)]
    terms = energy.GridTerms(alpha=scalar[0], beta=scalar[1], gamma=scalar[2] if normal else None,
                             delta=scalar[3] if distance else None, eps=scalar[4], z=maps(b_, h, w), w=maps(b_, h, w),
                             prior=maps(b_, h, w), colour=pair(), normal=pair() if normal else None,
                             distance=pair() if distance else None, edge_factor=pair() if factor else None)
    fused = compiled.fused_system(terms)
    with native.eager():
        reference = energy.grid_system(terms)
    assert fused is not None
    for got, want in zip(fused, (reference.diagonal, reference.rhs, *reference.weights)):
        assert got.shape == want.shape and got.dtype == want.dtype
        torch.testing.assert_close(got, want, atol=0, rtol=tol)  # an FMA may round once where torch rounds twice


def test_with_gradients_torch_builds_the_grid_system(kernels):
    model = CRFDepth.from_pretrained("kitti").double()
    image, K, geometry = _frames(torch.float64, size=(12, 16))
    sparse = torch.where(geometry > 30, geometry, torch.zeros_like(geometry))
    eps = torch.tensor(0.01, dtype=torch.float64)
    terms = energy.grid_potentials(image, sparse, K, geometry, eps, geometry, model.potential_weights(),
                                   variable="log")
    assert compiled.fused_system(terms) is None  # the weights require grad: autograd needs torch's graph
    with torch.no_grad():
        assert compiled.fused_system(terms) is not None
