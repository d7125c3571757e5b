"""The constrained weights (crfdepth/potentials/parameters.py)."""

from __future__ import annotations

import pytest
import torch

from crfdepth.model import CRFDepth


def test_constrained_weights_return_the_initial_values_and_stay_in_range_for_any_free_value():
    model = CRFDepth(mode="pixel", gate=True, alpha=0.3, sigma_d=0.2, confidence=50.0)
    assert model.weights()["alpha"] == pytest.approx(0.3, rel=1e-6)
    assert model.weights()["sigma_d"] == pytest.approx(0.2, rel=1e-6)
    assert model.weights()["confidence"] == pytest.approx(50.0, rel=1e-6)
    with torch.no_grad():
        model.raw_alpha.fill_(40.0)
        model.log_sigma_d.fill_(-40.0)
    assert 0.0 < float(model.alpha) <= 1.0 and float(model.sigma_d) > 0.0


def test_optional_weights_exist_only_with_their_option():
    plain, gated = CRFDepth(mode="pixel"), CRFDepth(mode="pixel", gate=True)
    assert "gate_threshold" not in plain.weights() and "log_gate_threshold" not in dict(plain.named_parameters())
    assert gated.weights()["gate_threshold"] == pytest.approx(0.015, rel=1e-6)
