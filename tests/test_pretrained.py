"""Tests of the shipped weights and the JSON weights file (crfdepth.pretrained)."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from crfdepth import CRFDepth, complete_depth
from crfdepth.checkpoint import load_model
from crfdepth.data.synthetic import make_scene
from crfdepth.errors import InputError
from crfdepth.pretrained import (
    FORMAT, LEARNED, VERSION, WEIGHTS, load_pretrained, read_weights, save_weights, weights_path,
)


def _close(a: dict[str, float], b: dict[str, float], rtol: float = 1e-5) -> bool:
    return all(abs(a[k] - b[k]) <= rtol * abs(b[k]) for k in LEARNED)


def test_shipped_kitti_weights_are_learned_and_documented():
    file = weights_path("kitti")
    data = read_weights(file)
    model = load_pretrained("kitti")
    assert _close(model.weights(), {k: data["config"][k] for k in LEARNED})
    paper = CRFDepth().weights()
    moved = [k for k in LEARNED if abs(data["config"][k] - paper[k]) > 0.01 * paper[k]]
    assert len(moved) >= 5, f"only {moved} differ from the hand-set values by more than 1%"
    about = data["about"]
    assert "python -m train fit --config configs/kitti_weights.yaml" in about["command"]
    assert "extra_train" in about["config"] and about["epoch"] >= 1
    assert about["datamodule_hyper_parameters"]["val_names_contain"] == "drive_0001"
    readme = (file.parent / "README.md").read_text()
    assert "configs/kitti_weights.yaml" in readme and "python -m train.export" in readme


def test_paper_weights_are_the_constructor_defaults():
    assert weights_path("paper") is None
    assert load_pretrained("paper").weights() == CRFDepth().weights()
    assert CRFDepth.from_pretrained("paper").config == CRFDepth().config


def test_from_pretrained_overrides_structure_and_keeps_weights():
    model = CRFDepth.from_pretrained("kitti", mode="pixel", potentials=("colour",))
    assert model.mode == "pixel" and model.potentials == ("colour",) and not model.training
    assert _close(model.weights(), load_pretrained("kitti").weights())


@pytest.mark.parametrize("name, words", [("imagenet", ["weights", "kitti, paper", "'imagenet'"]),
                                         ("KITTI", ["weights", "'KITTI'"])])
def test_unknown_weight_set(name, words):
    with pytest.raises(InputError) as info:
        load_pretrained(name)
    assert all(w in str(info.value) for w in words)


def test_bad_override_is_named():
    with pytest.raises(InputError, match="overrides.*colour_weight"):
        load_pretrained("kitti", colour_weight=2.0)
    with pytest.raises(InputError, match="alpha"):
        load_pretrained("kitti", alpha=1.5)


def test_save_read_load_round_trip(tmp_path):
    model = CRFDepth(mode="pixel", potentials=("colour", "normal"))
    with torch.no_grad():
        model.raw_beta += 1.0
        model.log_confidence -= 0.5
        model.log_std_scale += 0.3
    path = save_weights(model, tmp_path / "mine.json", about={"data": "my drives", "val_rmse_mm": 1234.5})
    data = json.loads(path.read_text())
    assert data["format"] == FORMAT and data["version"] == VERSION and data["about"]["data"] == "my drives"
    assert data["config"]["mode"] == "pixel" and data["config"]["potentials"] == ["colour", "normal"]
    loaded = load_model(path)
    assert loaded.mode == "pixel" and loaded.potentials == ("colour", "normal")
    assert _close(loaded.weights(), model.weights())
    assert load_model(path, overrides={"mode": "superpixel"}).mode == "superpixel"
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
    "newer version": (json.dumps({"format": FORMAT, "version": 9, "config": {}}), ["version", "9"]),
    "no config": (json.dumps({"format": FORMAT, "version": VERSION}), ["config", "NoneType"]),
    "missing weight": (json.dumps({"format": FORMAT, "version": VERSION, "config": {"alpha": 0.5}}),
                       ["config['beta']", "finite number", "None"]),
    "nan weight": (json.dumps({"format": FORMAT, "version": VERSION,
                               "config": {**CRFDepth().weights(), "sigma_d": float("nan")}}),
                   ["config['sigma_d']", "nan"]),
    "bad value": (json.dumps({"format": FORMAT, "version": VERSION,
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


def test_complete_depth_defaults_to_the_kitti_weights():
    scene = make_scene(3, height=96, width=320)
    kwargs = dict(sparse=scene.sparse, K=scene.K, return_std=False)
    default, _ = complete_depth(scene.image, **kwargs)
    kitti, _ = complete_depth(scene.image, model=CRFDepth.from_pretrained("kitti"), **kwargs)
    paper, _ = complete_depth(scene.image, model=CRFDepth.from_pretrained("paper"), **kwargs)
    np.testing.assert_array_equal(default, kitti)
    assert np.abs(default - paper).max() > 1e-3  # metres: the learned weights change the result


def test_weight_sets_are_listed():
    assert WEIGHTS == ("kitti", "paper")
