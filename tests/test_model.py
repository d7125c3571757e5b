"""The CRF model (issue: the CRF depth model) on known answers, oracles and real frames."""

from __future__ import annotations

import math

import pytest
import torch

from crfdepth.errors import InputError
from crfdepth.fill.nearest import nearest_fill
from crfdepth.metrics import average_metrics, depth_metrics
from crfdepth.model import CRFDepth
from crfdepth.potentials.energy import energy

F64 = torch.float64


def two_planes(h=48, w=64, line_step=3, parallel=False):
    """Left: a red plane receding to the left (a façade seen obliquely) around 10 m;
    right: a blue fronto-parallel plane at 14 m; noise-free samples on LiDAR-like scan
    lines (every pixel of every ``line_step``-th row, 33% of the pixels).

    With ``parallel=True`` the left plane nearly faces the camera too (normals agree)."""
    K = torch.tensor([[60.0, 0, w / 2], [0, 60.0, h / 2], [0, 0, 1]], dtype=F64)
    u = torch.arange(w, dtype=F64)[None, :].expand(h, w)
    v = torch.arange(h, dtype=F64)[:, None].expand(h, w)
    # A plane n.X = c has inverse depth linear in the pixel coordinates.
    tilt = 0.0004 if parallel else 0.001
    left = 1.0 / (0.1 + tilt * (u - w / 2) + 0.0002 * (v - h / 2))
    right = 1.0 / (1 / 14 + 0.0002 * (v - h / 2))
    edge = w // 2
    depth = torch.where(u < edge, left, right)
    image = torch.zeros(3, h, w, dtype=F64)
    image[0, :, :edge] = 0.8
    image[2, :, edge:] = 0.8
    image += 0.1
    sparse = torch.zeros(h, w, dtype=F64)
    sparse[1::line_step] = depth[1::line_step]
    return image[None], sparse[None, None], K, depth[None, None], edge


def _edge_and_plane_errors(model, parallel=False):
    image, sparse, K, depth, edge = two_planes(parallel=parallel)
    err = (model(image, sparse, K).depth - depth)[0, 0].detach()
    step = float((depth[0, 0, :, edge] - depth[0, 0, :, edge - 1]).abs().mean())
    at_edge = float(err[:, edge - 1:edge + 1].abs().max())
    sides = [float(side.pow(2).mean().sqrt()) for side in (err[:, :edge - 1], err[:, edge + 1:])]
    return at_edge, step, sides


@pytest.mark.parametrize("mode", ["pixel", "superpixel"])
def test_two_planes_keep_the_step_and_fit_each_plane(mode):
    model = CRFDepth(mode=mode, superpixels=300, scale_superpixels=False, rtol=1e-10).double()
    at_edge, step, sides = _edge_and_plane_errors(model)
    assert at_edge < 0.1 * step, f"error at the edge {at_edge:.3f} m vs step {step:.3f} m"
    assert max(sides) < 0.05, sides


def test_parallel_planes_keep_the_step_without_the_normal_term():
    """Colour and 3D distance keep a step between parallel planes; the normal term, which
    sees two parallel surfaces as one, is what leaks across it (hence its low default)."""
    model = CRFDepth(mode="pixel", potentials=("colour", "distance"), rtol=1e-10).double()
    at_edge, step, sides = _edge_and_plane_errors(model, parallel=True)
    assert at_edge < 0.1 * step and max(sides) < 0.05
    leaky = CRFDepth(mode="pixel", gamma=0.5, sigma_n=1.0, rtol=1e-10).double()
    assert _edge_and_plane_errors(leaky, parallel=True)[0] > 0.1 * step


def small_scene(h=12, w=16, seed=0):
    g = torch.Generator().manual_seed(seed)
    image = torch.rand(1, 3, h, w, generator=g, dtype=F64)
    depth = 8 + 4 * torch.rand(1, 1, h, w, generator=g, dtype=F64)
    sparse = torch.where(torch.rand(1, 1, h, w, generator=g) < 0.2, depth, torch.zeros_like(depth))
    K = torch.tensor([[20.0, 0, w / 2], [0, 20.0, h / 2], [0, 0, 1]], dtype=F64)
    return image, sparse, K, depth


@pytest.mark.parametrize("mode", ["pixel", "superpixel"])
def test_solution_minimises_the_energy(mode):
    image, sparse, K, _ = small_scene(24, 32)
    model = CRFDepth(mode=mode, superpixels=60, scale_superpixels=False, refine=False, rtol=1e-12).double()
    out = model(image, sparse, K)
    terms = out.terms
    x = out.node_depth.detach().clone().requires_grad_()
    e = energy(x, terms)["total"]
    (grad,) = torch.autograd.grad(e, x)
    x_fill = terms.x_prior.clone().requires_grad_()
    (grad_fill,) = torch.autograd.grad(energy(x_fill, terms)["total"], x_fill)
    assert grad.norm() < 1e-8 * grad_fill.norm()
    g = torch.Generator().manual_seed(1)
    for _ in range(5):
        dx = 0.05 * torch.randn(x.shape, generator=g, dtype=F64)
        assert energy(x.detach() + dx, terms)["total"] > e
    parts = energy(x.detach(), terms)
    assert set(parts) == {"data", "colour", "normal", "distance", "prior", "total"}
    assert all(float(v.detach()) >= 0 for v in parts.values())


def test_every_parameter_gets_a_finite_nonzero_gradient():
    image, sparse, K, depth = small_scene()
    model = CRFDepth(mode="pixel", rtol=1e-12).double()
    out = model(image, sparse, K, return_std=True)
    loss = ((out.depth - depth) ** 2).mean() + (torch.log(out.std) + (out.depth - depth) ** 2 / out.std ** 2).mean()
    loss.backward()
    for name, p in model.named_parameters():
        if name in ("log_refine_prior", "log_std_scale"):  # no refinement in pixel mode; the predictive std
            assert p.grad is None                            # does not use the posterior's scale
            continue
        assert p.grad is not None and torch.isfinite(p.grad).all() and bool((p.grad.abs() > 0).all()), name


def test_refinement_prior_gradient_matches_finite_differences():
    image, sparse, K, depth = small_scene(24, 32)
    model = CRFDepth(superpixels=40, scale_superpixels=False, rtol=1e-13).double()

    def loss(log_prior):
        out = torch.func.functional_call(model, {"log_refine_prior": log_prior}, (image, sparse, K))
        return ((out.depth - depth) ** 2).mean()

    value = model.log_refine_prior.detach().clone().requires_grad_()
    (grad,) = torch.autograd.grad(loss(value), value)
    h = 1e-5
    with torch.no_grad():
        numeric = (loss(value.detach() + h) - loss(value.detach() - h)) / (2 * h)
    assert float(grad.abs()) > 0 and float(grad) == pytest.approx(float(numeric), rel=1e-4)


def test_coarse_prior_weight_gets_a_gradient_on_the_pixel_grid():
    image, sparse, K, depth = small_scene(24, 32)
    model = CRFDepth(mode="pixel", coarse=4, rtol=1e-12).double()
    ((model(image, sparse, K).depth - depth) ** 2).mean().backward()
    grad = model.log_refine_prior.grad  # the weight of the painted coarse depth (design section 17)
    assert grad is not None and torch.isfinite(grad).all() and float(grad.abs()) > 0


def test_gradcheck_through_the_whole_model():
    image, sparse, K, depth = small_scene()
    model = CRFDepth(mode="pixel", rtol=1e-13).double()
    names = [n for n, _ in model.named_parameters() if n not in ("log_std_scale", "log_refine_prior")]
    params = tuple(dict(model.named_parameters())[n].detach().clone().requires_grad_() for n in names)

    def f(*values):
        out = torch.func.functional_call(model, dict(zip(names, values)), (image, sparse, K))
        return out.depth

    assert torch.autograd.gradcheck(f, params, atol=1e-6, rtol=1e-4)


@pytest.mark.parametrize("mode", ["pixel", "superpixel"])
def test_common_factor_on_alpha_to_delta_leaves_depth_unchanged(mode):
    image, sparse, K, _ = small_scene(24, 32)
    model = CRFDepth(mode=mode, superpixels=60, scale_superpixels=False, rtol=1e-12).double()
    before = model(image, sparse, K).depth
    with torch.no_grad():
        for name in ("raw_alpha", "raw_beta", "raw_gamma", "raw_delta"):
            p = getattr(model, name)
            p.copy_(torch.logit(0.3 * torch.sigmoid(p)))
    after = model(image, sparse, K).depth
    assert model.alpha.item() == pytest.approx(0.15)
    assert torch.allclose(before, after, atol=1e-8)


@pytest.mark.parametrize("mutate, match", [
    (lambda i, s, K: (i[:, :2], s, K), r"image: expected shape \(B, 3, H, W\)"),
    (lambda i, s, K: (i[..., :-1], s, K), r"image: expected batch and size"),
    (lambda i, s, K: (i, -s, K), r"sparse: expected finite depth >= 0"),
    (lambda i, s, K: (i, s.clone().fill_(float("nan")), K), r"sparse: expected finite depth >= 0"),
    (lambda i, s, K: (i, torch.zeros_like(s), K), r"sparse: frame\(s\) \[0\] have no LiDAR pixel"),
    (lambda i, s, K: (i, s, K[:2]), r"K: expected shape \(3, 3\)"),
    (lambda i, s, K: (i, s, K * torch.tensor([[-1.0, 1, 1], [1, 1, 1], [1, 1, 1]], dtype=F64)),
     r"K: expected finite intrinsics with focal lengths > 0"),
    (lambda i, s, K: (i * 2, s, K), r"image: expected finite RGB values in \[0, 1\]"),
])
def test_bad_input(mutate, match):
    image, sparse, K, _ = small_scene()
    with pytest.raises(InputError, match=match):
        CRFDepth(mode="pixel").double()(*mutate(image, sparse, K))


def test_bad_configuration():
    with pytest.raises(InputError, match="mode: expected"):
        CRFDepth(mode="voxel")
    with pytest.raises(InputError, match="potentials: expected a subset"):
        CRFDepth(potentials=("colour", "texture"))
    with pytest.raises(InputError, match=r"alpha: expected a number in \(0, 1\)"):
        CRFDepth(alpha=1.5)


@pytest.mark.kitti
def test_default_model_beats_nearest_neighbour_on_the_real_frame(kitti_root):
    from crfdepth.data.kitti import KittiValSelection

    sample = KittiValSelection(kitti_root / "depth_selection" / "val_selection_cropped")[0]
    image, sparse, K, target = sample.image[None], sample.sparse[None], sample.K[None], sample.target[None]
    model = CRFDepth()
    crf = average_metrics(depth_metrics(model(image, sparse, K).depth, target))["rmse"]
    nn = average_metrics(depth_metrics(nearest_fill(sparse), target))["rmse"]
    print(f"\n{sample.name}: CRF RMSE {crf:.1f} mm, nearest-neighbour RMSE {nn:.1f} mm")
    assert crf < nn
    assert math.isfinite(crf)
