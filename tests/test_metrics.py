"""KITTI metrics and the uncertainty metrics (sparsification, AUSE, Spearman, coverage, NLL,
reliability), against hand-computed values and seeded samples of known distribution."""

import math

import numpy as np
import pytest
import scipy.stats
import torch

from crfdepth.errors import InputError
from crfdepth.metrics import (
    UNCERTAINTY_METRICS,
    ause,
    average_metrics,
    average_uncertainty,
    depth_metrics,
    format_metrics,
    reliability,
    sparsification,
    uncertainty_metrics,
)


def test_hand_computed_single_image():
    target = torch.tensor([[10.0, 20.0], [0.0, 40.0]])  # one pixel without ground truth
    pred = torch.tensor([[11.0, 18.0], [99.0, 40.0]])
    m = depth_metrics(pred, target)
    # errors on the 3 valid pixels: +1, -2, 0 metres
    assert m["pixels"].tolist() == [3]
    assert m["rmse"].item() == pytest.approx(math.sqrt((1 + 4 + 0) / 3) * 1000)
    assert m["mae"].item() == pytest.approx((1 + 2 + 0) / 3 * 1000)
    inv = [1 / 11 - 1 / 10, 1 / 18 - 1 / 20, 0.0]
    assert m["irmse"].item() == pytest.approx(math.sqrt(sum(e * e for e in inv) / 3) * 1000)
    assert m["imae"].item() == pytest.approx(sum(abs(e) for e in inv) / 3 * 1000)
    assert m["rel"].item() == pytest.approx((0.1 + 0.1 + 0) / 3)
    assert m["delta1"].item() == pytest.approx(1.0)


def test_per_image_then_averaged_not_pooled():
    target = torch.zeros(2, 1, 1, 4)
    target[0, 0, 0, :1] = 10.0  # image 0: one pixel, error 2 m
    target[1, 0, 0, :] = 10.0  # image 1: four pixels, error 0
    pred = torch.full((2, 1, 1, 4), 10.0)
    pred[0, 0, 0, 0] = 12.0
    avg = average_metrics(depth_metrics(pred, target))
    assert avg["rmse"] == pytest.approx(1000.0)  # (2000 + 0) / 2; pooled would be 894.4
    assert avg["delta1"] == pytest.approx(1.0) and avg["pixels"] == 5
    assert "RMSE 1000.0 mm" in format_metrics(avg)


def test_delta_threshold():
    target = torch.tensor([[10.0, 10.0]])
    pred = torch.tensor([[12.4, 13.0]])  # ratios 1.24 and 1.30
    assert depth_metrics(pred, target)["delta1"].item() == pytest.approx(0.5)


def test_bad_input():
    with pytest.raises(InputError, match=r"pred: expected the shape of target \(1, 2, 2\), got \(1, 2, 3\)"):
        depth_metrics(torch.ones(2, 3), torch.ones(2, 2))
    with pytest.raises(InputError, match=r"target: image\(s\) \[1\] have no ground-truth pixel"):
        depth_metrics(torch.ones(2, 2, 2), torch.stack([torch.ones(2, 2), torch.zeros(2, 2)]))
    with pytest.raises(InputError, match="pred: expected finite depth > 0 at ground-truth pixels, got 1"):
        depth_metrics(torch.tensor([[0.0, 1.0]]), torch.tensor([[5.0, 5.0]]))


def test_ause_of_oracle_order_is_zero():
    rng = np.random.default_rng(0)
    err = rng.normal(size=5000) * 1000.0
    assert abs(ause(err, np.abs(err))["ause"]) < 1e-9
    # Any monotone function of |error| orders the same: also 0.
    assert abs(ause(err, np.sqrt(np.abs(err)) + 3.0)["ause"]) < 1e-9


def test_sparsification_hand_computed_and_ties():
    err = np.array([4.0, 3.0, 0.0, 0.0])
    # Removing the largest error first: RMSE sqrt(25/4), sqrt(9/3), 0, 0 at 0, 1/4, 2/4, 3/4.
    curve = sparsification(err, np.abs(err), steps=4)
    np.testing.assert_allclose(curve, [2.5, math.sqrt(3.0), 0.0, 0.0], atol=1e-12)
    # A constant map is a random order: the expected remaining MSE is flat at the full MSE.
    flat = sparsification(err, np.ones(4), steps=4)
    np.testing.assert_allclose(flat, [2.5] * 4, atol=1e-12)
    a = ause(err, np.ones(4), steps=4)
    assert a["ause"] == pytest.approx(a["ause_random"])
    # The worst order (smallest error first) has a larger AUSE than random.
    assert ause(err, -np.abs(err), steps=4)["ause"] > a["ause_random"]


def test_sparsification_bad_input_is_named():
    with pytest.raises(InputError, match=r"error, uncertainty.*\(3,\) and \(2,\)"):
        sparsification(np.zeros(3), np.zeros(2))
    with pytest.raises(InputError, match="N > 0"):
        ause(np.zeros(0), np.zeros(0))


# --------------------------------------------------------------------------- uncertainty_metrics

# Four pixels: |error| 1, 2, 0.5, 4 against std 1, 1, 2, 1.
ERR = np.array([1.0, -2.0, 0.5, 4.0])
STD = np.array([1.0, 1.0, 2.0, 1.0])


def test_coverage_and_likelihoods_hand_computed():
    m = uncertainty_metrics(ERR, STD)
    assert list(m) == list(UNCERTAINTY_METRICS)
    assert m["coverage_1"] == 0.5  # 1 <= 1 and 0.5 <= 2; not 2 <= 1, 4 <= 1
    assert m["coverage_2"] == 0.75  # all but 4 <= 2
    # Gaussian: 0.5 log(2 pi std^2) + e^2 / (2 std^2) = 0.5 log(2 pi) + {0.5, 2, log 2 + 1/32, 8}.
    assert m["nll"] == pytest.approx(0.5 * math.log(2 * math.pi) + (0.5 + 2 + 1 / 32 + 8 + math.log(2)) / 4, rel=1e-12)
    # Laplace with b = std / sqrt(2): log(sqrt(2) std) + sqrt(2) |e| / std.
    laplace = 0.5 * math.log(2) + math.log(2) / 4 + math.sqrt(2) * (1 + 2 + 0.25 + 4) / 4
    assert m["nll_laplace"] == pytest.approx(laplace, rel=1e-12)


def test_spearman_hand_computed_with_and_without_ties():
    # Ties: std ranks (2, 2, 4, 2) (three 1s share ranks 1-3), |error| ranks (2, 3, 1, 4);
    # Pearson of the ranks: -3 / sqrt(3 * 5).
    assert uncertainty_metrics(ERR, STD)["spearman"] == pytest.approx(-3 / math.sqrt(15), rel=1e-12)
    # No ties: rank differences (0, 1, 0, -2, 1), rho = 1 - 6 * 6 / (5 * (25 - 1)) = 0.7.
    m = uncertainty_metrics(np.array([1.0, -3.0, 2.0, 5.0, -4.0]), np.array([0.1, 0.4, 0.2, 0.3, 0.5]))
    assert m["spearman"] == pytest.approx(0.7, rel=1e-12)


def test_spearman_of_a_two_level_count_map_uses_average_ranks():
    rng = np.random.default_rng(1)
    err = rng.normal(size=2000) * rng.uniform(0.1, 2.0, size=2000)
    count = np.where(np.abs(err) + rng.normal(scale=0.5, size=2000) > 0.5, 1.0, 0.0)  # 2 levels, 0 allowed
    m = uncertainty_metrics(err, count, is_std=False)
    assert list(m) == ["ause", "ause_random", "ause_ratio", "spearman"]  # no coverage / NLL for a score
    ranks_u, ranks_e = scipy.stats.rankdata(count), scipy.stats.rankdata(np.abs(err))  # average ranks
    assert m["spearman"] == pytest.approx(np.corrcoef(ranks_u, ranks_e)[0, 1], rel=1e-12)
    assert m["spearman"] == pytest.approx(scipy.stats.spearmanr(count, np.abs(err)).statistic, rel=1e-12)
    assert 0 < m["ause_ratio"] < 1  # informative, if coarse


def test_constant_uncertainty_has_nan_spearman_without_a_warning(recwarn):
    m = uncertainty_metrics(ERR, np.full(4, 0.5))
    assert math.isnan(m["spearman"])
    assert m["ause_ratio"] == pytest.approx(1.0)  # a constant map is a random order
    assert not recwarn.list


def test_equal_errors_have_nan_ause_ratio():
    # Every |error| equal: the random AUSE is 0 up to rounding, and no order beats another.
    m = uncertainty_metrics(np.array([0.3, -0.3] * 500), np.random.default_rng(0).uniform(0.1, 1.0, 1000))
    assert abs(m["ause_random"]) < 1e-12 and math.isnan(m["ause_ratio"]) and math.isnan(m["spearman"])


def test_ause_hand_computed():
    err = np.array([4.0, 3.0, 0.0, 0.0])
    # The worst order removes 0, 0, 3: RMSE 2.5, sqrt(25/3), sqrt(25/2), 4 at f = 0, 1/4, 2/4, 3/4;
    # the oracle's is 2.5, sqrt(3), 0, 0 and a random order's is flat at 2.5. Trapezoid, step 1/4:
    m = uncertainty_metrics(err, np.array([1.0, 2.0, 3.0, 4.0]), steps=4)
    worst = 0.25 * ((math.sqrt(25 / 3) - math.sqrt(3)) + math.sqrt(25 / 2) + 4 / 2)
    random = 0.25 * ((2.5 - math.sqrt(3)) + 2.5 + 2.5 / 2)
    assert m["ause"] == pytest.approx(worst, rel=1e-12)
    assert m["ause_random"] == pytest.approx(random, rel=1e-12)
    assert m["ause_ratio"] == pytest.approx(worst / random, rel=1e-12) and m["ause_ratio"] > 1


def test_oracle_order_has_zero_ause_and_ratio():
    rng = np.random.default_rng(2)
    err = rng.normal(size=5000)
    m = uncertainty_metrics(err, 0.01 + np.abs(err))
    assert abs(m["ause"]) < 1e-9 and abs(m["ause_ratio"]) < 1e-9 and m["ause_random"] > 0.1
    assert m["spearman"] == pytest.approx(1.0)


def test_random_uncertainty_has_ause_ratio_near_one():
    rng = np.random.default_rng(3)
    err = rng.normal(size=20000) * rng.uniform(0.1, 3.0, size=20000)
    m = uncertainty_metrics(err, rng.uniform(0.1, 1.0, size=20000))
    assert abs(m["ause_ratio"] - 1.0) < 0.1  # seeds 0-7 give 0.98-1.01
    assert abs(m["spearman"]) < 0.05  # standard error 1 / sqrt(20000) = 0.007


def test_calibrated_gaussian():
    rng = np.random.default_rng(4)
    std = rng.uniform(0.05, 3.0, size=200_000)
    err = rng.normal(size=std.size) * std
    m = uncertainty_metrics(err, std)
    assert abs(m["coverage_1"] - 0.6827) < 0.005  # standard error 0.001
    assert abs(m["coverage_2"] - 0.9545) < 0.005  # standard error 0.0005
    expected_nll = 0.5 * math.log(2 * math.pi) + np.mean(np.log(std)) + 0.5
    assert abs(m["nll"] - expected_nll) < 0.01  # standard error 0.0016
    # The std does not change with the unit; the likelihood shifts by log 1000 from metres to mm.
    mm = uncertainty_metrics(err * 1000, std * 1000)
    assert mm["nll"] == pytest.approx(m["nll"] + math.log(1000), rel=1e-9)
    assert mm["coverage_1"] == m["coverage_1"] and mm["ause_ratio"] == pytest.approx(m["ause_ratio"], rel=1e-9)
    # An over-confident std (half the true one) covers less and costs more.
    tight = uncertainty_metrics(err, std / 2)
    assert tight["coverage_1"] < 0.4 and tight["nll"] > m["nll"] + 0.5


def test_inputs_are_not_modified():
    err, std = ERR.copy(), STD.copy()
    uncertainty_metrics(err, std)
    reliability(err, std)
    np.testing.assert_array_equal(err, ERR)
    np.testing.assert_array_equal(std, STD)


def test_average_uncertainty_recomputes_the_ratio_from_the_mean_areas():
    per_image = [{"ause": 1.0, "ause_random": 2.0, "ause_ratio": 0.5, "spearman": 0.2},
                 {"ause": 1.0, "ause_random": 8.0, "ause_ratio": 0.125, "spearman": 0.4}]
    avg = average_uncertainty(per_image)
    assert avg["ause"] == 1.0 and avg["ause_random"] == 5.0 and avg["spearman"] == pytest.approx(0.3)
    assert avg["ause_ratio"] == pytest.approx(2.0 / 10.0)  # not the mean of the ratios, 0.3125
    with_nan = average_uncertainty([*per_image, {**per_image[0], "spearman": math.nan}])
    assert math.isnan(with_nan["spearman"])  # a plain mean: nan propagates
    zero = average_uncertainty([{"ause": 0.0, "ause_random": 0.0, "ause_ratio": math.nan}])
    assert math.isnan(zero["ause_ratio"])


def test_reliability():
    r = reliability(ERR, STD)
    np.testing.assert_allclose(r["k"], np.linspace(0, 3, 31))
    np.testing.assert_allclose(r["expected"], [math.erf(k / math.sqrt(2)) for k in r["k"]], rtol=1e-12, atol=1e-15)
    assert r["expected"][10] == pytest.approx(0.682689, abs=1e-6)
    # |error| / std = 1, 2, 0.25, 4.
    r = reliability(ERR, STD, ks=[0.0, 0.25, 1.0, 1.5, 2.0, 4.0])
    np.testing.assert_array_equal(r["observed"], [0.0, 0.25, 0.5, 0.5, 0.75, 1.0])
    m = uncertainty_metrics(ERR, STD)
    assert (r["observed"][2], r["observed"][4]) == (m["coverage_1"], m["coverage_2"])


BAD_UNCERTAINTY = [
    (lambda: uncertainty_metrics(np.zeros(3), np.ones(2)), r"std: expected the shape of error \(3,\), got \(2,\)"),
    (lambda: uncertainty_metrics(np.zeros((2, 2)), np.ones((2, 2))),
     r"error: expected a 1-D array .*got shape \(2, 2\)"),
    (lambda: uncertainty_metrics(np.zeros(0), np.ones(0)),
     r"error: expected a 1-D array \(N,\) with N > 0, got shape \(0,\)"),
    (lambda: uncertainty_metrics(np.array([0.0, np.nan, 1.0]), np.ones(3)),
     "error: expected finite values, got 1 of 3"),
    (lambda: uncertainty_metrics(np.zeros(3), np.array([1.0, np.inf, np.nan])),
     "std: expected finite values, got 2 of 3"),
    (lambda: uncertainty_metrics(np.zeros(3), np.array([1.0, 0.0, -1.0])),
     r"std: expected a standard deviation > 0 at every pixel, got 2 of 3 pixel\(s\) <= 0"),
    (lambda: uncertainty_metrics(np.zeros(3), np.ones(3), steps=1), "steps: expected an integer >= 2, got 1"),
    (lambda: uncertainty_metrics(np.zeros(3), np.ones(3), is_std="yes"), "is_std: expected True or False"),
    (lambda: uncertainty_metrics(["a", "b"], np.ones(2)), "error: expected an array of real numbers"),
    (lambda: reliability(np.zeros(3), np.zeros(3)), "std: expected a standard deviation > 0"),
    (lambda: reliability(np.zeros(3), np.ones(3), ks=[1.0, -1.0]), "ks: expected a non-empty 1-D array of finite"),
    (lambda: average_uncertainty([]), "per_image: expected at least one"),
    (lambda: average_uncertainty([{"ause": 1.0}, {"nll": 1.0}]), r"per_image: .*for image 1"),
]


@pytest.mark.parametrize("call, message", BAD_UNCERTAINTY, ids=[m.split(":")[0] + f"-{i}" for i, (_, m) in
                                                                 enumerate(BAD_UNCERTAINTY)])
def test_uncertainty_bad_input_is_named(call, message):
    with pytest.raises(InputError, match=message):
        call()


def test_zero_is_allowed_for_a_score():
    m = uncertainty_metrics(ERR, np.array([0.0, 0.5, 0.0, 1.0]), is_std=False)
    assert m["ause"] >= 0 and -1 <= m["spearman"] <= 1
