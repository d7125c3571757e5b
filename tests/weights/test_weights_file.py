"""The JSON weights file of crfdepth.weights: save_weights, read_weights, load_model, refusals."""

from __future__ import annotations

import json

import pytest
import torch

from crfdepth.checkpoints import load_model, save_weights
from crfdepth.errors import InputError
from crfdepth.model import CRFDepth
from crfdepth.weights import LEARNED, WEIGHTS_FORMAT, WEIGHTS_VERSION, read_weights


def _close(a: dict[str, float], b: dict[str, float], rtol: float = 1e-5) -> bool:
    return all(abs(a[k] - b[k]) <= rtol * abs(b[k]) for k in LEARNED)


def test_save_read_load_round_trip(tmp_path):
    model = CRFDepth(mode="pixel", potentials=("colour", "normal"))
    with torch.no_grad():
        model.raw_beta += 1.0
        model.log_confidence -= 0.5
        model.log_std_scale += 0.3
    path = save_weights(model, tmp_path / "mine.json", about={"data": "my drives", "val_rmse_mm": 1234.5})
    data = json.loads(path.read_text())
    assert data["format"] == WEIGHTS_FORMAT and data["version"] == WEIGHTS_VERSION
    assert data["about"]["data"] == "my drives"
    config = data["config"]  # in groups
    assert config["structure"]["mode"] == "pixel" and config["potentials"]["on"] == ["colour", "normal"]
    loaded = load_model(path)
    assert loaded.settings.structure.mode == "pixel" and loaded.settings.potentials.on == ("colour", "normal")
    assert _close(loaded.weights(), model.weights())
    assert load_model(path, overrides={"mode": "superpixel"}).settings.structure.mode == "superpixel"
    assert [p.name for p in tmp_path.iterdir()] == ["mine.json"]  # no temporary left


def test_save_refuses_bad_about_without_writing(tmp_path):
    with pytest.raises(InputError, match="about"):
        save_weights(CRFDepth(), tmp_path / "w.json", about={"when": object()})
    assert list(tmp_path.iterdir()) == []
    with pytest.raises(InputError, match="model"):
        save_weights({"alpha": 0.5}, tmp_path / "w.json")
    with pytest.raises(FileNotFoundError, match="folder"):
        save_weights(CRFDepth(), tmp_path / "missing" / "w.json")


BAD_FILES = {
    "not json": ("{alpha: 0.5", ["unreadable"]),
    "other format": (json.dumps({"format": "onnx", "version": 1, "config": {}}), ["format", "'onnx'"]),
    "newer version": (json.dumps({"format": WEIGHTS_FORMAT, "version": 9, "config": {}}), ["version", "9"]),
    "no config": (json.dumps({"format": WEIGHTS_FORMAT, "version": WEIGHTS_VERSION}), ["config", "NoneType"]),
    "missing weight": (json.dumps({"format": WEIGHTS_FORMAT, "version": WEIGHTS_VERSION, "config": {"alpha": 0.5}}),
                       ["config['beta']", "finite number", "None"]),
    "nan weight": (json.dumps({"format": WEIGHTS_FORMAT, "version": WEIGHTS_VERSION,
                               "config": {**CRFDepth().weights(), "sigma_d": float("nan")}}),
                   ["config['sigma_d']", "nan"]),
    "bad value": (json.dumps({"format": WEIGHTS_FORMAT, "version": WEIGHTS_VERSION,
                              "config": {**CRFDepth().weights(), "confidence": -3.0}}),
                  ["invalid model configuration", "confidence"]),
}


@pytest.mark.parametrize("case", list(BAD_FILES))
def test_bad_weights_file_is_named(tmp_path, case):
    text, words = BAD_FILES[case]
    path = tmp_path / "w.json"
    path.write_text(text)
    with pytest.raises(InputError) as info:
        load_model(path)
    assert str(path) in str(info.value) and all(w in str(info.value) for w in words), str(info.value)


def test_missing_weights_file():
    with pytest.raises(FileNotFoundError, match="nope.json"):
        read_weights("nope.json")


