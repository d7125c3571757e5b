"""The shipped weight sets of crfdepth.weights: "kitti" (learned, a JSON file) and "paper" (hand-set)."""

from __future__ import annotations

import shutil

import numpy as np
import pytest
import torch

from crfdepth import CRFDepth, complete_depth
from crfdepth.checkpoints import load_pretrained
from crfdepth.data.synthetic import make_scene
from crfdepth.errors import InputError
from crfdepth.weights import LEARNED, WEIGHTS, files, pretrained_state, read_weights, torch_files, weights_path


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
    settings = model.settings
    assert settings.structure.mode == "pixel" and settings.potentials.on == ("colour",) and not model.training
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


def test_complete_depth_defaults_to_the_kitti_weights():
    scene = make_scene(3, height=96, width=320)
    kwargs = dict(sparse=scene.sparse, K=scene.K, return_std=False)
    default, _ = complete_depth(scene.image, **kwargs)
    kitti, _ = complete_depth(scene.image, model=CRFDepth.from_pretrained("kitti"), **kwargs)
    paper, _ = complete_depth(scene.image, model=CRFDepth.from_pretrained("paper"), **kwargs)
    np.testing.assert_array_equal(default, kitti)
    assert np.abs(default - paper).max() > 1e-3  # metres: the learned weights change the result


def test_weight_sets_are_listed():
    assert WEIGHTS == ("kitti", "paper", "nyu")


# --------------------------------------------------------------------------- pretrained_state


def test_pretrained_state_of_kitti_is_the_files_configuration():
    config, state = pretrained_state("kitti")
    stored = read_weights(weights_path("kitti"))
    # Options the file predates take their old meaning (crfdepth.weights.files._OLD_DEFAULTS).
    assert config.items() >= stored["config"].items()
    assert state.keys() == stored.get("state", {}).keys()
    config["alpha"] = 0.3  # a fresh copy each call
    assert pretrained_state("kitti")[0]["alpha"] != 0.3


def test_pretrained_state_of_paper_is_empty():
    assert pretrained_state("paper") == ({}, {})


@pytest.mark.parametrize("name", ["imagenet", "KITTI", None, 3])
def test_pretrained_state_names_the_argument_and_the_choices(name):
    with pytest.raises(InputError) as info:
        pretrained_state(name)
    assert str(info.value) == f"name: expected one of the shipped weights kitti, paper, nyu, got {name!r}"


@pytest.mark.parametrize("overrides", [{}, {"mode": "pixel", "potentials": ("colour",)}, {"alpha": 0.3, "eps": 0.2}])
@pytest.mark.parametrize("name", WEIGHTS)
def test_load_pretrained_and_from_pretrained_build_the_same_model(name, overrides):
    a, b = load_pretrained(name, **overrides), CRFDepth.from_pretrained(name, **overrides)
    assert a.config == b.config and not a.training and not b.training
    for key, value in a.state_dict().items():
        assert torch.equal(value, b.state_dict()[key]), key
    if "alpha" in overrides:  # an overridden learned value replaces the stored one
        assert a.weights()["alpha"] == pytest.approx(0.3, rel=1e-6)


def _shipped_torch_file(monkeypatch, tmp_path, state: dict[str, torch.Tensor], config: dict | None = None):
    """Let the "kitti" set be a crfdepth model file holding ``state`` and ``config`` (the shipped one is JSON);
    the "nyu" set, the default's indoor regime, is the shipped one."""
    shutil.copy(files._FOLDER / "nyu.json", tmp_path / "nyu.json")
    monkeypatch.setattr(files, "_FOLDER", tmp_path)
    torch.save({"format": torch_files.MODEL_FORMAT, "version": torch_files.MODEL_VERSION,
                "config": CRFDepth().config if config is None else config, "state_dict": state},
               tmp_path / "kitti.json")  # a zip archive: read as a torch file, not JSON
    return tmp_path / "kitti.json"


def test_shipped_state_dict_of_the_old_layout_is_upgraded(monkeypatch, tmp_path):
    model = CRFDepth(refine_prior=0.02)
    state = {k: v for k, v in model.state_dict().items() if k not in ("log_refine_prior", "std_head.weights")}
    state["refine_prior"] = torch.tensor(0.02)  # the buffer before the prior became learnable
    _shipped_torch_file(monkeypatch, tmp_path, state, {"refine_prior": 0.02})  # a configuration of that time
    config, loaded = pretrained_state("kitti")
    # The options the configuration predates take their old meaning: no gate, no head, posterior std.
    assert config == {"variable": "depth", "gate": False, "head": False, "prior": "nearest",
                      "uncertainty": "posterior", "refine_prior": 0.02} and "refine_prior" not in loaded
    assert float(loaded["log_refine_prior"].exp()) == pytest.approx(0.02, rel=1e-6)
    for built in (load_pretrained("kitti"), CRFDepth.from_pretrained("kitti")):
        assert built.weights() == pytest.approx(model.weights(), rel=1e-6)


def test_shipped_state_dict_with_nan_is_refused(monkeypatch, tmp_path):
    state = {**CRFDepth().state_dict(), "log_sigma_p": torch.tensor(float("nan"))}
    file = _shipped_torch_file(monkeypatch, tmp_path, state)
    for load in (pretrained_state, load_pretrained, CRFDepth.from_pretrained):
        with pytest.raises(InputError) as info:
            load("kitti")
        assert str(info.value) == f"path: {file}: parameter log_sigma_p: expected finite values, got nan"
