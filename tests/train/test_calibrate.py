"""The closed-form std-scale calibration (train.calibrate)."""

import dataclasses

import pytest
import torch

from crfdepth.data.synthetic import SyntheticScenes
from crfdepth.errors import InputError
from crfdepth.model import CRFDepth
from train.calibrate import calibrate_std_scale, fit_predictive_std


def _nll(model, frames, scale: float) -> float:
    """Mean over frames of the per-pixel Gaussian NLL (constant dropped) with std scale ``scale``."""
    total = []
    with torch.no_grad():
        for s in frames:
            out = model(s.image[None], s.sparse[None], s.K[None], return_std=True)
            valid = s.target[None] > 0
            sigma = out.std[valid] / model.std_scale * scale
            err = out.depth[valid] - s.target[None][valid]
            total.append(float((sigma.log() + err.square() / (2 * sigma.square())).mean()))
    return sum(total) / len(total)


def test_calibrated_std_scale_minimises_the_nll():
    frames = [SyntheticScenes(count=2, height=64, width=192)[i] for i in range(2)]
    model = CRFDepth(mode="pixel", std_scale=3.0, uncertainty="posterior").eval()
    s = calibrate_std_scale(model, frames, apply=False)
    assert float(model.std_scale.detach()) == pytest.approx(3.0)  # apply=False leaves the model alone
    assert _nll(model, frames, s) < min(_nll(model, frames, 0.9 * s), _nll(model, frames, 1.1 * s))
    assert calibrate_std_scale(model, frames) == pytest.approx(s, rel=1e-6)
    assert float(model.std_scale.detach()) == pytest.approx(s, rel=1e-6)
    # The result does not depend on the scale the model had.
    assert calibrate_std_scale(CRFDepth(mode="pixel", uncertainty="posterior").eval(), frames) == pytest.approx(s, rel=1e-5)


def test_calibration_without_target_pixels_is_refused():
    frame = SyntheticScenes(count=1, height=48, width=160)[0]
    empty = dataclasses.replace(frame, target=torch.zeros_like(frame.target))
    with pytest.raises(InputError, match="frames: expected at least one frame with target pixels"):
        calibrate_std_scale(CRFDepth(mode="pixel", uncertainty="posterior"), [empty])
    with pytest.raises(InputError, match="frames: expected at least one frame with target pixels"):
        fit_predictive_std(CRFDepth(mode="pixel"), [empty])
    with pytest.raises(InputError, match="uncertainty='predictive'"):
        fit_predictive_std(CRFDepth(mode="pixel", uncertainty="posterior"), [frame])
