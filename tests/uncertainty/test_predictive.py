"""The predictive std (crfdepth/uncertainty/predictive.py, docs/design.md section 5): its signals on
known scenes, the log-linear model, the Newton fit against a known answer, bad input."""

import math

import numpy as np
import pytest
import torch
import torch.nn.functional as F

from crfdepth.data.synthetic import SyntheticScenes
from crfdepth.errors import InputError
from crfdepth.geometry.windows import window_max
from crfdepth.metrics import uncertainty_metrics
from crfdepth.model import CRFDepth
from crfdepth.uncertainty.predictive import (
    DEFAULT_STD_TERMS,
    OFFSETS,
    SIGNALS,
    STD_TERMS,
    PredictiveStd,
    fit_std_terms,
    predictive_std,
    std_features,
)


@pytest.mark.parametrize("window", [3, 5, 7, 15])
def test_window_max_equals_max_pool(window):
    x = torch.randn(2, 3, 23, 41, generator=torch.Generator().manual_seed(window))
    assert torch.equal(window_max(x, window), F.max_pool2d(x, window, 1, window // 2))


def _step_scene():
    """A 10 m wall left of column 20, a 40 m wall right of it, returns on every 4th row and column."""
    depth = torch.full((1, 1, 40, 40), 10.0)
    depth[..., 20:] = 40.0
    sparse = torch.zeros_like(depth)
    sparse[..., ::4, ::4] = depth[..., ::4, ::4]
    return depth, sparse


def test_signals_on_a_depth_step():
    depth, sparse = _step_scene()
    var = torch.full_like(depth, 1e-4)
    f = std_features(depth, sparse, sparse, None, var)
    names = dict(zip(SIGNALS, f[0]))
    assert torch.equal(names["depth"], depth[0, 0]) and torch.equal(names["posterior"], var[0, 0])
    # the edge signal is log(40 / 10) within 2 columns of the step, 0 elsewhere
    edge = names["edge"]
    assert torch.allclose(edge[:, 18:22], torch.full((40, 4), math.log(4.0)))
    assert float(edge[:, :18].abs().max()) == 0 and float(edge[:, 22:].abs().max()) == 0
    # distance: 0 on a return, sqrt(2^2 + 2^2) in the middle of a cell, exact Euclidean
    assert float(names["distance"][0, 0]) == 0 and float(names["distance"][2, 2]) == pytest.approx(math.sqrt(8))
    assert float(names["gate"].abs().max()) == 0  # no gate, no disagreement


def test_gate_signal_marks_a_see_through_return():
    depth, sparse = _step_scene()
    depth[...] = 10.0
    sparse = torch.zeros_like(depth)
    sparse[..., ::4, ::4] = 10.0
    sparse[..., 8, 8] = 30.0  # a background return among foreground ones
    gate = torch.ones_like(depth)
    gate[..., 8, 8] = 0.0  # rejected by the occlusion gate
    g = std_features(depth, sparse, torch.where(gate > 0.5, sparse, 0), gate, torch.ones_like(depth))[0, 4]
    assert float(g[8, 8]) == pytest.approx(math.log(3.0), rel=1e-6)
    assert float(g[8 + 7, 8 + 7]) == pytest.approx(math.log(3.0), rel=1e-6) and float(g[8 + 8, 8]) == 0


def test_predictive_std_is_the_log_linear_model():
    f = torch.rand(7, len(SIGNALS), dtype=torch.float64) * 5
    w = torch.randn(len(STD_TERMS), dtype=torch.float64)
    expected = torch.exp(w[0] + sum(w[1 + k] * torch.log(f[:, k] + OFFSETS[n]) for k, n in enumerate(SIGNALS)))
    assert torch.allclose(predictive_std(f, w), expected)
    maps = f.T.reshape(1, len(SIGNALS), 7, 1)
    assert torch.allclose(predictive_std(maps, w)[0, 0, :, 0], expected)


def test_fit_recovers_known_weights_and_covers_68_percent():
    gen = torch.Generator().manual_seed(0)
    truth = {"bias": -4.0, "depth": 1.0, "posterior": 0.0, "distance": 0.5, "edge": 0.3, "gate": 0.0}
    w = torch.tensor([truth[k] for k in STD_TERMS], dtype=torch.float64)
    feats, errs = [], []
    for _ in range(4):
        f = torch.rand(20000, len(SIGNALS), generator=gen, dtype=torch.float64) * torch.tensor([50, 1e-4, 10, 1, 1])
        b = predictive_std(f, w) / math.sqrt(2)  # Laplace errors with std predictive_std
        u = torch.rand(20000, generator=gen, dtype=torch.float64) - 0.5
        feats.append(f)
        errs.append(-b * torch.sign(u) * torch.log1p(-2 * u.abs()))
    fitted = fit_std_terms(feats, errs)
    for k in STD_TERMS[1:]:
        assert fitted[k] == pytest.approx(truth[k], abs=0.05), k
    std = predictive_std(torch.cat(feats), torch.tensor([fitted[k] for k in STD_TERMS], dtype=torch.float64))
    assert float((torch.cat(errs).abs() <= std).double().mean()) == pytest.approx(math.erf(1 / math.sqrt(2)), abs=0.002)
    # For Laplace errors the 68.3% quantile of |e| is 0.81 std: the bias moves by log(0.81).
    assert fitted["bias"] == pytest.approx(truth["bias"] + math.log(-math.log(1 - 0.6827) / math.sqrt(2)), abs=0.05)


@pytest.mark.parametrize("terms, match", [({"bias": 0.0}, "std_terms: expected a mapping"),
                                          ({**DEFAULT_STD_TERMS, "edge": float("nan")}, "std_terms: expected finite"),
                                          ([1, 2], "std_terms: expected a mapping")])
def test_bad_std_terms_are_refused(terms, match):
    with pytest.raises(InputError, match=match):
        PredictiveStd(terms)
    with pytest.raises(InputError, match=match):
        CRFDepth(std_terms=terms, uncertainty="posterior")


def test_bad_fit_input_is_refused():
    with pytest.raises(InputError, match="features, errors: expected one entry per frame"):
        fit_std_terms([torch.zeros(3, 5)], [])
    with pytest.raises(InputError, match="features: expected \\(3, 5\\)"):
        fit_std_terms([torch.zeros(3, 4)], [torch.zeros(3)])
    with pytest.raises(InputError, match="errors: expected at least one frame with target pixels"):
        fit_std_terms([torch.zeros(0, 5)], [torch.zeros(0)])
    with pytest.raises(InputError, match="start: expected a mapping"):
        fit_std_terms([torch.zeros(3, 5)], [torch.zeros(3)], start={"bias": 0.0})
    with pytest.raises(InputError, match="non-finite"):
        fit_std_terms([torch.zeros(3, 5)], [torch.tensor([0.0, float("inf"), 1.0])])
    with pytest.raises(InputError, match="uncertainty: expected one of"):
        CRFDepth(uncertainty="bayes")


def _scene_scores(model):
    ratios, rhos, covered = [], [], []
    for s in SyntheticScenes(count=3, seed=1000, height=96, width=320):
        with torch.no_grad():
            out = model(s.image[None], s.sparse[None], s.K, return_std=True)
        assert out.std.shape == out.depth.shape and bool(torch.isfinite(out.std).all() and (out.std > 0).all())
        assert out.std_features.shape == (1, len(SIGNALS), 96, 320) and out.node_std.numel() == out.node_depth.numel()
        truth = s.target[0]
        m = truth > 0
        u = uncertainty_metrics((out.depth[0, 0][m] - truth[m]).double().numpy(), out.std[0, 0][m].double().numpy())
        ratios.append(u["ause_ratio"])
        rhos.append(u["spearman"])
        covered.append(u["coverage_1"])
    return np.mean(ratios), np.mean(rhos), np.mean(covered)


@pytest.mark.parametrize("mode", [dict(mode="pixel"), dict(mode="superpixel", superpixels=600)])
def test_model_std_on_synthetic_scenes_ranks_errors(mode):
    """On small built-in scenes (camera truth), the hand-set predictive std ranks the errors:
    AUSE under 0.7 x a random order's (the issue's target), positive Spearman; the std is
    positive and finite."""
    ratio, rho, _ = _scene_scores(CRFDepth(**mode).eval())
    assert ratio < 0.7 and rho > 0.15, (ratio, rho)


def test_fitting_the_std_adapts_it_to_another_structure():
    """The hand-set terms are the shipped pixel model's fit; the unrefined superpixel painting
    is another structure (measured with them: AUSE 0.98 x random, the 2 cm range noise
    dominates). Fitted on three other scenes, its std ranks and covers the held-out scenes
    (measured 0.20 x random, Spearman 0.62, 70% within 1 std)."""
    from train.calibrate import fit_predictive_std

    model = CRFDepth(mode="superpixel", superpixels=600, refine=False).eval()
    fit_predictive_std(model, list(SyntheticScenes(count=3, seed=20, height=96, width=320)))
    ratio, rho, covered = _scene_scores(model)
    assert ratio < 0.4 and rho > 0.4 and 0.6 < covered < 0.8, (ratio, rho, covered)


def test_posterior_option_keeps_the_sampled_std():
    s = SyntheticScenes(count=1, seed=3, height=48, width=160)[0]
    with torch.no_grad():
        post = CRFDepth(mode="pixel", uncertainty="posterior")(s.image[None], s.sparse[None], s.K, return_std=True)
        pred = CRFDepth(mode="pixel")(s.image[None], s.sparse[None], s.K, return_std=True)
    assert post.std_features is None and pred.std_features is not None
    assert torch.equal(post.depth, pred.depth) and not torch.allclose(post.std, pred.std)


def test_shipped_std_shows_edges_and_blank_regions():
    """The std picture of the demo and ``--vis`` has structure: on the built-in street the shipped
    std is larger at depth edges than on smooth surfaces at the same range, and larger far from
    any return (sky) than near returns (measured: 101x and 72x the medians)."""
    s = SyntheticScenes(count=1, seed=0, height=176, width=608)[0]
    with torch.no_grad():
        out = CRFDepth.from_pretrained("kitti")(s.image[None], s.sparse[None], s.K, return_std=True)
    std, f = out.std[0, 0], dict(zip(SIGNALS, out.std_features[0]))
    near = (f["depth"] > 8) & (f["depth"] < 20)
    edge, smooth = near & (f["edge"] > 0.3), near & (f["edge"] < 0.01) & (f["distance"] < 3)
    blank, close = f["distance"] > 20, f["distance"] < 2
    assert int(edge.sum()) > 100 and int(smooth.sum()) > 100 and int(blank.sum()) > 100
    assert float(std[edge].median()) > 10 * float(std[smooth].median())
    assert float(std[blank].median()) > 10 * float(std[close].median())
