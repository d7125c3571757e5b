"""crfdepth.layer and CRFDepth on bad input: second-order gradients, singular systems, empty batches."""

from __future__ import annotations

import warnings

import pytest
import torch

from crfdepth.errors import ConvergenceWarning, InputError
from crfdepth.layer import CRFRefine, crf_refine
from crfdepth.model import CRFDepth

F64 = torch.float64
DOUBLE_BACKWARD = "create_graph: second-order gradients (double backward"


def inputs(b=1, c=2, h=4, w=5, dtype=F64, seed=0):
    g = torch.Generator().manual_seed(seed)
    depth = (1 + torch.rand(b, 1, h, w, generator=g, dtype=F64)).to(dtype)
    confidence = torch.rand(b, 1, h, w, generator=g, dtype=F64).to(dtype)
    features = torch.randn(b, c, h, w, generator=g, dtype=F64).to(dtype)
    projection = (0.5 * torch.randn(3, c, generator=g, dtype=F64)).to(dtype)
    return depth, confidence, features, projection


def small_scene(h=12, w=16, seed=0, batch=1):
    g = torch.Generator().manual_seed(seed)
    image = torch.rand(batch, 3, h, w, generator=g, dtype=F64)
    depth = 8 + 4 * torch.rand(batch, 1, h, w, generator=g, dtype=F64)
    sparse = torch.where(torch.rand(batch, 1, h, w, generator=g) < 0.2, depth, torch.zeros_like(depth))
    K = torch.tensor([[20.0, 0, w / 2], [0, 20.0, h / 2], [0, 0, 1]], dtype=F64)
    return image, sparse, K


def first_line(exc: pytest.ExceptionInfo) -> str:
    return str(exc.value).splitlines()[0]


# ----------------------------------------------------------------------------------------
# item 1: second-order gradients
# ----------------------------------------------------------------------------------------

def test_layer_first_order_gradcheck_and_create_graph_agree():
    depth, confidence, features, projection = inputs()
    leaves = [t.clone().requires_grad_() for t in (depth, confidence, features, projection)]
    assert torch.autograd.gradcheck(lambda *t: crf_refine(*t, rtol=1e-12).depth, leaves, atol=1e-6, rtol=1e-4)
    plain = torch.autograd.grad((crf_refine(*leaves).depth ** 2).sum(), leaves)
    graph = torch.autograd.grad((crf_refine(*leaves).depth ** 2).sum(), leaves, create_graph=True)
    for a, b in zip(plain, graph):
        torch.testing.assert_close(a, b.detach(), rtol=1e-6, atol=1e-8)


@pytest.mark.parametrize("wrt", [0, 1, 2, 3])  # depth, confidence, features, projection_weight
@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_layer_second_order_gradient_raises_the_clear_error(wrt, dtype):
    leaves = [t.clone().requires_grad_() for t in inputs(dtype=dtype)]
    (g,) = torch.autograd.grad(crf_refine(*leaves).depth.sum(), leaves[wrt], create_graph=True)
    with pytest.raises(RuntimeError) as exc:
        torch.autograd.grad((g ** 2).sum(), leaves[wrt])
    assert first_line(exc).startswith(DOUBLE_BACKWARD)


def test_module_gradient_penalty_raises_the_clear_error():
    depth, confidence, features, _ = (t.float() for t in inputs())
    features.requires_grad_()
    layer = CRFRefine(2, superpixels=None)
    out = layer(depth, confidence, features).depth
    (g,) = torch.autograd.grad(out.sum(), features, create_graph=True)
    with pytest.raises(RuntimeError) as exc:
        (out.mean() + g.pow(2).sum()).backward()
    assert first_line(exc).startswith(DOUBLE_BACKWARD)


def test_model_second_order_gradient_raises_the_clear_error():
    image, sparse, K = small_scene()
    model = CRFDepth(mode="pixel").double()
    image = image.requires_grad_()
    out = model(image, sparse, K).depth
    (g,) = torch.autograd.grad(out.sum(), image, create_graph=True)
    with pytest.raises(RuntimeError) as exc:
        torch.autograd.grad(g.pow(2).sum(), [p for p in model.parameters() if p.requires_grad], allow_unused=True)
    assert first_line(exc).startswith(DOUBLE_BACKWARD)


# ----------------------------------------------------------------------------------------
# item 2: a singular system never gives a silent NaN
# ----------------------------------------------------------------------------------------

@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("grad", [False, True])
@pytest.mark.parametrize("superpixels", [False, True])
def test_zero_confidence_and_tiny_prior_weight_is_refused_by_name(dtype, grad, superpixels):
    depth, confidence, features, projection = inputs(b=2, dtype=dtype)
    confidence[1] = 0  # frame 1: nothing but the prior anchors it
    labels = (torch.arange(20).view(1, 4, 5) // 3).expand(2, 4, 5).contiguous() if superpixels else None
    with pytest.raises(InputError) as exc:
        crf_refine(depth.requires_grad_(grad), confidence, features, projection, prior_weight=1e-30, labels=labels)
    eps = torch.finfo(dtype).eps
    assert first_line(exc).startswith(f"prior_weight: expected at least {eps:.3g} (edge_scale 1 x the machine "
                                      f"epsilon of {str(dtype)[6:]}) for frame(s) [1] (batch index)")


def test_lidar_or_confidence_anchors_a_tiny_prior_weight():
    depth, confidence, features, projection = inputs()
    sparse = torch.zeros_like(depth)
    sparse[..., 1, 2] = 3.0
    out = crf_refine(depth, torch.zeros_like(confidence), features, projection, sparse=sparse, sparse_weight=1.0,
                     prior_weight=1e-30, rtol=1e-8)
    assert bool(out.info.converged.all()) and bool(torch.isfinite(out.depth).all())
    with pytest.raises(InputError, match=r"^prior_weight: expected at least"):  # a LiDAR weight of 0 anchors nothing
        crf_refine(depth, torch.zeros_like(confidence), features, projection, sparse=sparse, sparse_weight=0.0,
                   prior_weight=1e-30)


@pytest.mark.parametrize("grad", [False, True])
@pytest.mark.parametrize("dtype, prior_weight", [(torch.float32, 1e-6), (torch.float64, 1e-6), (torch.float64, 1e-9),
                                                 (torch.float64, 1e-12), (torch.float64, 1e-15)])
def test_ill_conditioned_layer_never_returns_nan_as_converged(dtype, grad, prior_weight):
    """Zero confidence, a prior weight above the floor (machine epsilon x edge_scale) but far
    below the edges: the solve may fail, but a converged result is finite and a failure warns,
    naming prior_weight when the result is not finite."""
    depth, confidence, features, projection = inputs(h=16, w=20, dtype=dtype)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        out = crf_refine(depth.requires_grad_(grad), torch.zeros_like(confidence), features, projection,
                         prior_weight=prior_weight)
    conv = out.info.converged
    assert bool(torch.isfinite(out.depth[conv]).all())
    messages = [str(w.message) for w in caught if issubclass(w.category, ConvergenceWarning)]
    assert bool(conv.all()) or messages
    if not bool(torch.isfinite(out.depth).all()):
        assert any("raise prior_weight" in m for m in messages)


# ----------------------------------------------------------------------------------------
# item 3: a batch of no frame
# ----------------------------------------------------------------------------------------

EMPTY = "depth: expected a batch of at least 1 frame of at least 1x1 pixels, (B, 1, H, W) with B, H, W >= 1, got shape"


@pytest.mark.parametrize("shape", [(0, 4, 5), (1, 0, 5), (1, 4, 0)])
def test_layer_refuses_an_empty_batch(shape):
    b, h, w = shape
    depth, confidence, features = (torch.ones(b, c, h, w, dtype=F64) for c in (1, 1, 2))
    projection = torch.ones(3, 2, dtype=F64)
    with pytest.raises(InputError) as exc:
        crf_refine(depth, confidence, features, projection)
    assert first_line(exc) == f"{EMPTY} {(b, 1, h, w)}"
    for superpixels in (None, 4):
        with pytest.raises(InputError) as exc:
            CRFRefine(2, superpixels=superpixels)(depth.float(), confidence.float(), features.float(),
                                                  image=torch.ones(b, 3, h, w))
        assert first_line(exc) == f"{EMPTY} {(b, 1, h, w)}"


def test_model_refuses_an_empty_batch():
    image, sparse, K = small_scene()
    with pytest.raises(InputError) as exc:
        CRFDepth(mode="pixel")(image[:0].float(), sparse[:0].float(), K.float())
    assert first_line(exc) == "sparse: expected at least one frame of at least one pixel, got shape (0, 1, 12, 16)"
