"""crfdepth.layer: the CRF refinement layer (oracle, gradients, module, bad input, example)."""

import importlib.util
import math
from pathlib import Path

import pytest
import torch

from crfdepth.errors import InputError
from crfdepth.layer import CRFRefine, crf_edge_weights, crf_refine
from crfdepth.linalg import grid_edge_index

ROOT = Path(__file__).resolve().parents[1]


def _inputs(b=2, c=3, h=5, w=6, dtype=torch.float64, seed=0):
    g = torch.Generator().manual_seed(seed)
    depth = torch.rand(b, 1, h, w, generator=g, dtype=dtype) * 10 + 1
    conf = torch.rand(b, 1, h, w, generator=g, dtype=dtype)
    feats = torch.randn(b, c, h, w, generator=g, dtype=dtype)
    proj = torch.randn(4, c, generator=g, dtype=dtype) * 0.5
    sparse = torch.zeros(b, 1, h, w, dtype=dtype)
    sparse[:, :, ::2, ::3] = torch.rand(b, 1, (h + 1) // 2, (w + 2) // 3, generator=g, dtype=dtype) * 10 + 1
    return depth, conf, feats, proj, sparse


def _dense_system(depth, conf, feats, proj, sparse, lam, scale, eps):
    """Dense A, b of one frame (oracle): A = diag(c + eps + lam m) + L(w)."""
    _, h, w = depth.shape
    wh, wv = crf_edge_weights(feats[None], proj, torch.tensor(scale, dtype=depth.dtype))
    ei = grid_edge_index(h, w)
    wts = torch.cat([wh.reshape(-1), wv.reshape(-1)])
    n = h * w
    m = (sparse.reshape(-1) > 0).to(depth.dtype)
    A = torch.diag(conf.reshape(-1) + eps + lam * m)
    s, t = ei
    A.index_put_((s, s), wts, accumulate=True)
    A.index_put_((t, t), wts, accumulate=True)
    A.index_put_((s, t), -wts, accumulate=True)
    A.index_put_((t, s), -wts, accumulate=True)
    b = (conf.reshape(-1) + eps) * depth.reshape(-1) + lam * m * sparse.reshape(-1)
    assert A.shape == (n, n)
    return A, b


def test_matches_dense_solve_of_the_energy():
    depth, conf, feats, proj, sparse = _inputs()
    out = crf_refine(depth, conf, feats, proj, sparse=sparse, sparse_weight=2.5, edge_scale=1.5,
                     prior_weight=1e-2, rtol=1e-12)
    assert out.depth.shape == depth.shape and out.std is None
    assert bool(out.info.converged.all())
    for k in range(2):
        A, b = _dense_system(depth[k], conf[k], feats[k], proj, sparse[k], 2.5, 1.5, 1e-2)
        x = torch.linalg.solve(A, b)
        torch.testing.assert_close(out.depth[k, 0].reshape(-1), x, rtol=1e-9, atol=1e-9)


def test_superpixel_mode_is_the_piecewise_constant_minimiser():
    depth, conf, feats, proj, sparse = _inputs()
    h, w = depth.shape[-2:]
    labels = (torch.arange(h * w).view(h, w) // 4 * 3 + 7).expand(2, h, w).clone()  # non-consecutive
    out = crf_refine(depth, conf, feats, proj, sparse=sparse, sparse_weight=2.5, edge_scale=1.5,
                     prior_weight=1e-2, labels=labels, rtol=1e-12, return_std=True, std_scale=2.0)
    for k in range(2):
        A, b = _dense_system(depth[k], conf[k], feats[k], proj, sparse[k], 2.5, 1.5, 1e-2)
        _, inv = torch.unique(labels[k].reshape(-1), return_inverse=True)
        Q = torch.nn.functional.one_hot(inv).to(A.dtype)  # (n, S): x = Q x_s
        As = Q.T @ A @ Q
        xs = torch.linalg.solve(As, Q.T @ b)
        torch.testing.assert_close(out.depth[k, 0].reshape(-1), Q @ xs, rtol=1e-9, atol=1e-9)
        std = 2.0 * torch.linalg.inv(As).diagonal().sqrt()  # exact: <= 1,000 segments
        torch.testing.assert_close(out.std[k, 0].reshape(-1), Q @ std, rtol=1e-9, atol=1e-9)


def test_std_matches_dense_inverse_roughly():
    depth, conf, feats, proj, sparse = _inputs(b=1)
    out = crf_refine(depth, conf, feats, proj, sparse=sparse, sparse_weight=2.5, return_std=True,
                     std_scale=3.0, std_samples=400, rtol=1e-10)
    A, _ = _dense_system(depth[0], conf[0], feats[0], proj, sparse[0], 2.5, 1.0, 1e-3)
    exact = 3.0 * torch.linalg.inv(A).diagonal().sqrt()
    rel = (out.std[0, 0].reshape(-1) - exact).abs() / exact
    assert float(rel.max()) < 0.15


@pytest.mark.parametrize("superpixel", [False, True])
def test_gradcheck_all_inputs(superpixel):
    depth, conf, feats, proj, sparse = _inputs(b=2, c=2, h=4, w=5)
    lam = torch.tensor(2.0, dtype=torch.float64)
    scale = torch.tensor(1.3, dtype=torch.float64)
    labels = (torch.arange(20).view(4, 5) // 3).expand(2, 4, 5).clone() if superpixel else None
    tensors = [t.clone().requires_grad_() for t in (depth, conf, feats, proj, sparse, lam, scale)]

    def f(y, c, fe, p, z, l, s):
        # LiDAR pixels fixed (the mask is not differentiable), their values are.
        z = torch.where(sparse > 0, z, torch.zeros_like(z))
        return crf_refine(y, c, fe, p, sparse=z, sparse_weight=l, edge_scale=s, labels=labels,
                          rtol=1e-13).depth

    assert torch.autograd.gradcheck(f, tensors, eps=1e-6, atol=1e-6)


def _grads_all_nonzero(dtype, device="cpu"):
    torch.manual_seed(0)
    depth, conf, feats, _, sparse = (t.to(device) for t in _inputs(b=2, c=3, h=8, w=9, dtype=dtype))
    layer = CRFRefine(3, embed_dim=4, init_scale=0.5).to(device)
    ins = [t.clone().requires_grad_() for t in (depth, conf, feats, sparse)]
    out = layer(*ins, return_std=True)
    assert out.depth.dtype == dtype and out.depth.device.type == torch.device(device).type
    loss = ((out.depth - 5.0) ** 2).mean() + out.std.mean()
    loss.backward()
    for name, t in zip(("depth", "confidence", "features", "sparse"), ins):
        assert t.grad is not None and bool(torch.isfinite(t.grad).all()), name
        g = t.grad if name != "sparse" else t.grad[sparse > 0]
        assert float(g.abs().max()) > 0, name
    for name, p in layer.named_parameters():
        assert p.grad is not None and bool(torch.isfinite(p.grad).all()), name
        assert float(p.grad.abs().max()) > 0, name
    return out


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_module_gradients_reach_every_input_and_parameter(dtype):
    _grads_all_nonzero(dtype)


@pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA device")
def test_cuda_matches_cpu():
    cpu = _grads_all_nonzero(torch.float64, "cpu")
    gpu = _grads_all_nonzero(torch.float64, "cuda")
    torch.testing.assert_close(gpu.depth.cpu(), cpu.depth, rtol=1e-6, atol=1e-6)


def test_batch_equals_frames_alone_and_inputs_untouched():
    depth, conf, feats, proj, sparse = _inputs(b=3)
    copies = [t.clone() for t in (depth, conf, feats, proj, sparse)]
    both = crf_refine(depth, conf, feats, proj, sparse=sparse, sparse_weight=1.0, rtol=1e-12).depth
    for k in range(3):
        one = crf_refine(depth[k:k + 1], conf[k:k + 1], feats[k:k + 1], proj, sparse=sparse[k:k + 1],
                         sparse_weight=1.0, rtol=1e-12).depth
        torch.testing.assert_close(both[k:k + 1], one, rtol=1e-9, atol=1e-9)
    for a, b in zip(copies, (depth, conf, feats, proj, sparse)):
        assert torch.equal(a, b)


def test_known_answer_step_edge_is_kept():
    # Two flat regions (5 m / 20 m) told apart by the features: the CRF fills the
    # zero-confidence pixels from LiDAR on their own side and keeps the step.
    h, w = 6, 10
    feats = torch.zeros(1, 1, h, w, dtype=torch.float64)
    feats[..., 5:] = 1.0
    truth = torch.where(feats > 0, 20.0, 5.0).double()
    sparse = torch.zeros_like(truth)
    sparse[..., 0, 0], sparse[..., 0, 9] = 5.0, 20.0
    depth = torch.full_like(truth, 12.0)
    conf = torch.zeros_like(truth)
    proj = torch.tensor([[5.0]], dtype=torch.float64)  # exp(-25): the step edge is cut
    out = crf_refine(depth, conf, feats, proj, sparse=sparse, sparse_weight=100.0, prior_weight=1e-6,
                     rtol=1e-12).depth
    assert float((out - truth).abs().max()) < 0.05


def test_superpixels_from_image_in_module():
    depth, conf, feats, _, sparse = _inputs(b=1, c=3, h=24, w=32, dtype=torch.float32)
    image = torch.rand(1, 3, 24, 32)
    layer = CRFRefine(3, superpixels=12)
    out = layer(depth, conf, feats, sparse, image=image)
    assert out.depth.shape == depth.shape
    assert out.depth.flatten().unique().numel() <= 24  # piecewise constant
    with pytest.raises(InputError, match="image"):
        layer(depth, conf, feats, sparse)


@pytest.mark.parametrize("change, match", [
    (lambda a: a.update(depth=a["depth"][:, :, :-1]), "depth|confidence"),
    (lambda a: a.update(confidence=-a["confidence"]), "confidence: expected values >= 0"),
    (lambda a: a["confidence"].__setitem__((0, 0, 0, 0), math.inf), "confidence: expected finite"),
    (lambda a: a["features"].__setitem__((0, 1, 2, 2), math.nan), "features: expected finite"),
    (lambda a: a["depth"].__setitem__((1, 0, 2, 2), math.nan), "depth: expected finite"),
    (lambda a: a.update(features=a["features"][:1]), "features: expected batch"),
    (lambda a: a.update(features=a["features"].float()), "features: expected dtype"),
    (lambda a: a.update(proj=a["proj"][:, :2]), "projection_weight"),
    (lambda a: a.update(sparse=-a["sparse"]), "sparse: expected values >= 0"),
    (lambda a: a.update(sparse_weight=None), "sparse_weight"),
    (lambda a: a.update(edge_scale=0.0), "edge_scale"),
    (lambda a: a.update(labels=torch.zeros(2, 5, 5, dtype=torch.int64)), "labels"),
    (lambda a: a.update(depth=a["depth"][:, 0]), "depth: expected a \\(B, 1, H, W\\)"),
])
def test_bad_input_names_the_argument(change, match):
    depth, conf, feats, proj, sparse = _inputs()
    a = dict(depth=depth, confidence=conf, features=feats, proj=proj, sparse=sparse, sparse_weight=1.0,
             edge_scale=1.0, labels=None)
    change(a)
    with pytest.raises(InputError, match=match):
        crf_refine(a["depth"], a["confidence"], a["features"], a["proj"], sparse=a["sparse"],
                   sparse_weight=a["sparse_weight"], edge_scale=a["edge_scale"], labels=a["labels"])


def test_module_rejects_bad_constructor_arguments():
    with pytest.raises(InputError, match="in_channels"):
        CRFRefine(0)
    with pytest.raises(InputError, match="edge_scale"):
        CRFRefine(3, edge_scale=-1.0)
    with pytest.raises(InputError, match="superpixels"):
        CRFRefine(3, superpixels=0)


def _load_example():
    spec = importlib.util.spec_from_file_location("layer_example", ROOT / "benchmarks" / "layer_example.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


@pytest.fixture
def one_thread():
    """torch on one thread, as the example's main() runs it; the process's count restored afterwards
    (a bare set_num_threads(1) here made every later test in the session single-threaded)."""
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)


def test_end_to_end_example_gradients_reach_cnn_and_crf_helps(one_thread):
    example = _load_example()
    r = example.run(steps=30, train_scenes=8, test_scenes=4)
    # (a) loss on the CRF output only reaches the CNN's first convolution
    g = r["grad_norm_first_conv_through_crf"]
    assert math.isfinite(g) and g > 1e-6
    assert r["params_cnn"] < 50_000
    # (b) same CNN, same steps, same seed, same data: the layer lowers held-out RMSE and MAE
    assert r["cnn+crf"]["rmse"] < r["cnn"]["rmse"]
    assert r["cnn+crf"]["mae"] < r["cnn"]["mae"]
    assert r["cnn+crf"]["rmse"] < r["nearest_fill"]["rmse"]
