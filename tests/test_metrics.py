"""KITTI metrics and the sparsification / AUSE of an uncertainty, against hand-computed values."""

import math

import numpy as np
import pytest
import torch

from crfdepth.errors import InputError
from crfdepth.metrics import ause, average_metrics, depth_metrics, format_metrics, sparsification


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
