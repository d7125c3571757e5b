"""One structure per weights (issue 25): a bare state_dict is refused, every loader keeps the
structure stored with the weights, from_pretrained checks every stored key."""

from __future__ import annotations

import json
import shutil

import pytest
import torch

from crfdepth.checkpoints import describe, load_model, load_pretrained, own_structure, save_model, save_weights
from crfdepth.errors import InputError
from crfdepth.model import CRFDepth
from crfdepth.weights import LEARNED, files, weights_path
from crfdepth.weights.files import read_checkpoint
from crfdepth.weights.torch_files import BARE_STATE_DICT

KITTI_STRUCTURE = dict(mode="pixel", variable="log", gate=True)


def _structure(model: CRFDepth) -> dict:
    return dict(mode=model.settings.structure.mode, variable=model.settings.structure.variable,
                gate=model.settings.gate.enabled)


def _bare_refusal(path) -> str:
    return (f"path: {path}: expected a complete model file, got a bare state dict: it holds weights but not the "
            f"model's structure (mode, variable, gate ...); load it into the model it came from and save that "
            f"with crfdepth.save_model(model, path), or give the trainer's Lightning .ckpt as it is")


# --------------------------------------------------------------------------- bare state dicts


@pytest.mark.parametrize("source", ["kitti", "paper"])
def test_bare_state_dict_of_a_shipped_model_is_refused(tmp_path, source):
    """The issue's case: the shipped model's state_dict() used to run as the default superpixel model."""
    path = tmp_path / "weights.pt"
    torch.save(load_pretrained(source).state_dict(), path)
    with pytest.raises(InputError) as info:
        load_model(path)
    message = str(info.value)
    assert message == _bare_refusal(path) == BARE_STATE_DICT.format(file=path)
    assert "\n" not in message
    with pytest.raises(InputError, match="got a bare state dict"):  # the plain reader refuses it too
        read_checkpoint(path)


def test_bare_state_dict_is_refused_even_with_overrides(tmp_path):
    """Overrides change a stored structure; they do not stand in for a missing one."""
    path = tmp_path / "weights.pt"
    torch.save(load_pretrained("kitti").state_dict(), path)
    with pytest.raises(InputError, match="got a bare state dict"):
        load_model(path, overrides=dict(KITTI_STRUCTURE))


def test_the_fix_the_message_names_keeps_the_structure(tmp_path):
    """Load the bare weights into the model they came from, save_model it: it loads as that model."""
    shipped = load_pretrained("kitti")
    torch.save(shipped.state_dict(), tmp_path / "weights.pt")
    model = CRFDepth.from_pretrained("kitti")
    model.load_state_dict(torch.load(tmp_path / "weights.pt", weights_only=True))
    loaded = load_model(save_model(model, tmp_path / "model.pt"))
    assert _structure(loaded) == KITTI_STRUCTURE
    assert loaded.config == shipped.config
    for key, value in shipped.state_dict().items():
        torch.testing.assert_close(loaded.state_dict()[key], value, rtol=0, atol=0, msg=key)


def test_not_a_state_dict_keeps_its_own_message(tmp_path):
    torch.save({"alpha": 0.5}, tmp_path / "x.pt")  # no tensors: not a bare state dict either
    with pytest.raises(InputError, match="does not hold a state dict .*a dict holding other things"):
        load_model(tmp_path / "x.pt")


# --------------------------------------------------------------------------- complete files keep their structure


def _lightning(model: CRFDepth) -> dict:
    return {"epoch": 1, "global_step": 10, "hyper_parameters": {"crf": model.config},
            "state_dict": {f"model.{k}": v for k, v in model.state_dict().items()}}


def test_every_complete_file_kind_loads_in_its_stored_structure(tmp_path):
    shipped = load_pretrained("kitti")
    torch.save(_lightning(shipped), tmp_path / "last.ckpt")
    save_model(shipped, tmp_path / "model.pt")
    save_weights(shipped, tmp_path / "weights.json")
    for path in (tmp_path / "last.ckpt", tmp_path / "model.pt", tmp_path / "weights.json", weights_path("kitti")):
        loaded = load_model(path)
        assert _structure(loaded) == KITTI_STRUCTURE, path
        assert loaded.weights() == pytest.approx(shipped.weights(), rel=1e-6), path


def test_own_structure_and_describe():
    assert {k: own_structure("kitti")[k] for k in KITTI_STRUCTURE} == KITTI_STRUCTURE
    assert CRFDepth(own_structure("paper")).config == CRFDepth().config  # all defaults
    assert describe(load_pretrained("kitti")) == "pixel grid, log depth, occlusion gate"
    assert describe(own_structure("kitti")) == describe(load_pretrained("kitti"))
    assert describe(CRFDepth()) == "superpixel graph (5500 segments) + pixel refinement, depth, no gate"
    assert describe(CRFDepth(superpixels=300, refine=False, potentials=("colour",), uncertainty="posterior")) == (
        "superpixel graph (300 segments), no refinement, depth, no gate, potentials colour, posterior std")


# --------------------------------------------------------------------------- from_pretrained checks every key


def _headed_set(monkeypatch, tmp_path, edit=None) -> tuple[CRFDepth, object]:
    """Let the "kitti" set be a weights file of a model with the learned head (its tensors in "state")."""
    model = CRFDepth(mode="pixel", head=True)
    with torch.no_grad():
        for p in model.head.parameters():
            p.add_(0.25)
    path = save_weights(model, tmp_path / "kitti.json")
    if edit is not None:
        data = json.loads(path.read_text())
        edit(data["state"])
        path.write_text(json.dumps(data))
    shutil.copy(files._FOLDER / "nyu.json", tmp_path / "nyu.json")  # the default's indoor regime
    monkeypatch.setattr(files, "_FOLDER", tmp_path)
    return model, path


def test_from_pretrained_loads_the_stored_head(monkeypatch, tmp_path):
    model, _ = _headed_set(monkeypatch, tmp_path)
    for loaded in (CRFDepth.from_pretrained("kitti"), load_pretrained("kitti")):
        assert loaded.head is not None
        for key, value in model.head.state_dict().items():
            torch.testing.assert_close(loaded.head.state_dict()[key], value, rtol=1e-6, atol=1e-7, msg=key)
        assert loaded.weights() == pytest.approx(model.weights(), rel=1e-6)


@pytest.mark.parametrize("case, edit, words", [
    ("unexpected key", lambda state: state.update({"head.extra": [1.0]}), "unexpected keys (1): head.extra"),
    ("missing key", lambda state: state.pop(sorted(state)[0]), "missing keys (1)"),
])
def test_from_pretrained_refuses_keys_that_do_not_fit(monkeypatch, tmp_path, case, edit, words):
    """It loaded with strict=False before: a stored tensor that does not fit was dropped silently."""
    _, path = _headed_set(monkeypatch, tmp_path, edit)
    for load in (CRFDepth.from_pretrained, load_pretrained):
        with pytest.raises(InputError) as info:
            load("kitti")
        assert str(info.value).startswith(f"{path} does not match CRFDepth") and words in str(info.value)


def test_from_pretrained_builds_the_subclass_in_the_stored_structure():
    class Mine(CRFDepth):
        pass

    model = Mine.from_pretrained("kitti")
    assert type(model) is Mine and not model.training
    assert _structure(model) == KITTI_STRUCTURE
    assert model.weights() == pytest.approx(load_pretrained("kitti").weights(), rel=1e-6)
    assert set(LEARNED) <= set(model.weights())
