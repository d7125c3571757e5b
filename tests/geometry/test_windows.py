"""Sliding-window maximum (crfdepth/geometry/windows.py) against max pooling."""

from __future__ import annotations

import pytest
import torch
import torch.nn.functional as F

from crfdepth.geometry.windows import window_max


@pytest.mark.parametrize("window", [1, 3, 5, 9, 15])
def test_window_max_equals_max_pooling(window):
    x = torch.randn(2, 3, 17, 23, generator=torch.Generator().manual_seed(window))
    assert torch.equal(window_max(x, window), F.max_pool2d(x, window, 1, window // 2))
