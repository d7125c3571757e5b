"""The torchmetrics wrapper: per-image values averaged over images, across batches."""

from __future__ import annotations

import pytest
import torch

from crfdepth.errors import InputError
from crfdepth.metrics import METRICS, average_metrics, depth_metrics
from train.metrics import DepthMetrics, PerImageMean


def _frames(seed: int, n: int, h: int = 6, w: int = 7):
    g = torch.Generator().manual_seed(seed)
    target = torch.rand(n, 1, h, w, generator=g) * 50 + 1
    target[torch.rand(n, 1, h, w, generator=g) < 0.5] = 0  # sparse ground truth
    pred = target.clamp_min(1) * (1 + 0.2 * torch.randn(n, 1, h, w, generator=g)).clamp_min(0.1)
    return pred, target


def test_per_image_mean_is_the_mean_over_images_not_batches():
    metric = PerImageMean(("loss",))
    metric.update(loss=torch.tensor([1.0, 3.0]))
    metric.update(loss=torch.tensor([8.0]))
    out = metric.compute()
    assert out["loss"].item() == pytest.approx(4.0)  # (1 + 3 + 8) / 3, not (2 + 8) / 2
    metric.reset()
    with pytest.warns(UserWarning, match="before the ``update``"):
        assert torch.isnan(metric.compute()["loss"])


def test_depth_metrics_match_the_pure_function_over_all_images():
    batches = [_frames(0, 3), _frames(1, 1), _frames(2, 2)]
    metric = DepthMetrics(extra=("loss",))
    for pred, target in batches:
        metric.update(pred, target, loss=torch.arange(pred.shape[0], dtype=torch.float32))
    got = metric.compute()
    pred = torch.cat([b[0] for b in batches])
    target = torch.cat([b[1] for b in batches])
    expected = average_metrics(depth_metrics(pred, target))
    for name in METRICS:
        assert got[name].item() == pytest.approx(expected[name], rel=1e-12), name
    assert got["loss"].item() == pytest.approx((0 + 1 + 2 + 0 + 0 + 1) / 6)


def test_depth_metrics_skip_images_without_ground_truth():
    pred, target = _frames(3, 3)
    target[1] = 0  # no ground-truth pixel: nothing to evaluate on this image
    metric = DepthMetrics(extra=("loss",))
    metric.update(pred, target, loss=torch.tensor([1.0, 100.0, 3.0]))
    got = metric.compute()
    expected = average_metrics(depth_metrics(pred[[0, 2]], target[[0, 2]]))
    assert got["rmse"].item() == pytest.approx(expected["rmse"], rel=1e-12)
    assert got["loss"].item() == pytest.approx(2.0)
    assert metric.images.item() == 2


def test_update_checks_names_and_sizes():
    metric = PerImageMean(("a", "b"))
    with pytest.raises(InputError, match="expected values for"):
        metric.update(a=torch.ones(2))
    with pytest.raises(InputError, match="one value per image"):
        metric.update(a=torch.ones(2), b=torch.ones(3))
    with pytest.raises(InputError, match="distinct"):
        PerImageMean(("a", "a"))
