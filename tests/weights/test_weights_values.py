"""Stored weights that make no sense are refused at the boundary, naming the file and the key
(crfdepth.weights.files: POSITIVE_RANGE, UNIT_RANGE, STD_BIAS_RANGE, STD_EXPONENT_RANGE, MAX_ABS_TENSOR),
instead of ending in a solver warning and a NaN or constant depth map: in a JSON weights file's
configuration and state, in a torch model file's or Lightning checkpoint's tensors and configuration.
The shipped sets and weights at the very edge of the ranges still load."""

from __future__ import annotations

import json
import math
import re

import pytest
import torch

from crfdepth.checkpoints import load_model, save_model, save_weights
from crfdepth.errors import InputError
from crfdepth.model import CRFDepth
from crfdepth.weights import MODEL_FORMAT, MODEL_VERSION, read_weights
from crfdepth.weights.files import (
    MAX_ABS_TENSOR,
    POSITIVE_RANGE,
    STD_BIAS_RANGE,
    STD_EXPONENT_RANGE,
    UNIT_RANGE,
    weights_path,
)


def test_ranges_are_generous_around_the_shipped_values():
    assert POSITIVE_RANGE == (1e-6, 1e6) and UNIT_RANGE == (1e-6, 1 - 1e-6) and MAX_ABS_TENSOR == 1e6
    assert STD_BIAS_RANGE == pytest.approx((-13.8155, 13.8155), abs=1e-4) and STD_EXPONENT_RANGE == (-10.0, 10.0)
    for name in ("kitti", "paper", "nyu"):
        assert CRFDepth.from_pretrained(name).weights()  # every shipped set loads


def _kitti_with(tmp_path, edit) -> str:
    data = json.loads(weights_path("kitti").read_text())
    edit(data["config"])
    path = tmp_path / "w.json"
    path.write_text(json.dumps(data))
    return str(path)


def _set(key, value):
    return lambda config: config.__setitem__(key, value)


def _set_term(key, value):
    return lambda config: config["std_terms"].__setitem__(key, value)


JSON_CASES = {
    "confidence 1e38": (_set("confidence", 1e38), "config['confidence']: expected a number in [1e-06, 1e+06] (a "
                                                   "weight > 0), got 1e+38"),
    "negative sigma_d": (_set("sigma_d", -1.0), "config['sigma_d']: expected a number in [1e-06, 1e+06] (a weight > "
                                                "0), got -1.0"),
    "alpha 1e-9": (_set("alpha", 1e-9), "config['alpha']: expected a number in [1e-06, 0.999999] (a weight in (0, "
                                        "1)), got 1e-09"),
    "eps 1e7": (_set("eps", 1e7), "config['eps']: expected a number in [1e-06, 1e+06] (a weight > 0), got "
                                  "10000000.0"),
    "gate_softness 1e-9": (_set("gate_softness", 1e-9), "config['gate_softness']: expected a number in [1e-06, "
                                                        "1e+06] (a weight > 0), got 1e-09"),
    "eps nan": (_set("eps", float("nan")), "config['eps']: expected a number in [1e-06, 1e+06] (a weight > 0), got "
                                           "nan"),
    "std exponent 50": (_set_term("depth", 50.0), "config['std_terms']['depth']: expected a number in [-10, 10] (an "
                                                  "exponent), got 50.0"),
    "std bias 100": (_set_term("bias", 100.0), "config['std_terms']['bias']: expected a number in [-13.8155, 13.8155] "
                                               "(log metres), got 100.0"),
}


@pytest.mark.parametrize("case", list(JSON_CASES))
def test_weights_file_with_an_absurd_value_is_refused_naming_file_and_key(tmp_path, case):
    edit, expected = JSON_CASES[case]
    path = _kitti_with(tmp_path, edit)
    message = f"{path}: invalid model configuration in the weights file: {expected}"
    with pytest.raises(InputError, match=f"^{re.escape(message)}$"):
        load_model(path)
    with pytest.raises(InputError, match=f"^{re.escape(message)}$"):
        read_weights(path)


def test_weights_file_head_tensor_out_of_range_is_refused(tmp_path):
    model = CRFDepth(mode="pixel", head=True)
    path = save_weights(model, tmp_path / "w.json")
    data = json.loads(path.read_text())
    data["state"]["head.net.0.bias"][3] = 1e9
    path.write_text(json.dumps(data))
    with pytest.raises(InputError, match=re.escape(f"path: {path}: parameter head.net.0.bias: expected values in "
                                                   f"[-1e+06, 1e+06] (a learned weight), got 1e+09 (1 of 16 values "
                                                   f"outside)")):
        load_model(path)


def _model_file(path, state, config=None):
    torch.save({"format": MODEL_FORMAT, "version": MODEL_VERSION, "config": config or CRFDepth().config,
                "state_dict": state}, path)
    return path


def _lightning(state, config):
    return {"state_dict": {f"model.{k}": v for k, v in state.items()}, "hyper_parameters": {"crf": config}}


TENSOR_CASES = {
    "log_confidence": (torch.tensor(math.log(1e38)), "expected values in [-13.82, 13.82] (the log of confidence, a "
                                                     "weight in [1e-06, 1e+06]), got 87.4982 (confidence 1e+38)"),
    "raw_alpha": (torch.tensor(40.0), "expected values in [-13.82, 13.82] (the logit of alpha, a weight in [1e-06, "
                                      "0.999999]), got 40 (alpha 1)"),
    "log_sigma_n": (torch.tensor(-30.0), "expected values in [-13.82, 13.82] (the log of sigma_n, a weight in "
                                         "[1e-06, 1e+06]), got -30 (sigma_n 9.358e-14)"),
    "eps": (torch.tensor(-1.0), "expected values in [1e-06, 1e+06] (a weight > 0), got -1"),
    "std_head.weights": (torch.tensor([-50.0, 1, 1, 1, 1, 1]), "expected values in [-13.82, -10, -10, -10, -10, -10] "
                                                             "to [13.82, 10, 10, 10, 10, 10] (the predictive std's bias "
                                                             "(log metres) and exponents), got -50 (1 of 6 values "
                                                             "outside)"),
}


@pytest.mark.parametrize("kind", ["crfdepth model file", "Lightning checkpoint"])
@pytest.mark.parametrize("key", list(TENSOR_CASES))
def test_torch_file_with_an_absurd_tensor_is_refused_naming_file_and_parameter(tmp_path, kind, key):
    value, expected = TENSOR_CASES[key]
    state = {**CRFDepth().state_dict(), key: value}
    path = tmp_path / "x.ckpt"
    if kind == "crfdepth model file":
        _model_file(path, state)
    else:
        torch.save(_lightning(state, CRFDepth().config), path)
    with pytest.raises(InputError, match=f"^{re.escape(f'path: {path}: parameter {key}: {expected}')}$"):
        load_model(path)


def test_torch_file_head_weights_out_of_range_are_refused(tmp_path):
    state = CRFDepth(head=True).state_dict()
    state["head.net.2.weight"] = torch.full_like(state["head.net.2.weight"], -3e7)
    path = _model_file(tmp_path / "x.pt", state, CRFDepth(head=True).config)
    with pytest.raises(InputError, match=re.escape("parameter head.net.2.weight: expected values in [-1e+06, 1e+06] "
                                                   "(a learned weight), got -3e+07 (2304 of 2304 values outside)")):
        load_model(path)


def test_torch_file_configuration_out_of_range_is_refused(tmp_path):
    config = CRFDepth(confidence=1e38).config
    path = _model_file(tmp_path / "x.pt", CRFDepth().state_dict(), config)
    with pytest.raises(InputError, match=re.escape(f"{path}: invalid model configuration in the crfdepth model file: "
                                                   f"config['confidence']: expected a number in [1e-06, 1e+06] (a "
                                                   f"weight > 0), got 1e+38")):
        load_model(path)


def test_weights_at_the_edges_of_the_ranges_load_from_every_kind_of_file(tmp_path):
    """float32 rounding puts a weight saved at a bound just outside it: allowed (1e-5 of the bound)."""
    model = CRFDepth(mode="pixel", confidence=1e6, alpha=1e-6, beta=1 - 1e-6, gate=True, gate_softness=1e-6,
                     std_terms={"bias": -13.8, "depth": 10.0, "posterior": -10.0, "distance": 1.0, "edge": 1.0,
                                "gate": 1.0})
    for path in (save_model(model, tmp_path / "m.pt"), save_weights(model, tmp_path / "w.json")):
        loaded = load_model(path)
        assert loaded.weights() == pytest.approx(model.weights(), rel=1e-5)
