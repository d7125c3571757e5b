"""The default model's regimes in its files (crfdepth/weights/regimes.py): save_model and save_weights keep them,
load_model gives them back, and a damaged record is refused naming the file and the regime."""

from __future__ import annotations

import json

import pytest
import torch

from crfdepth.checkpoints import load_model, save_model, save_weights
from crfdepth.errors import InputError
from crfdepth.inference.regime import REGIMES
from crfdepth.model import CRFDepth

TOLERANCE = 1e-4  # metres: the same model on the same input, solved twice


def _frame(depths: tuple[float, float], count: int = 120, h: int = 90, w: int = 150, seed: int = 0):
    """A frame of ``count`` scattered returns between ``depths`` (metres) on a two-colour image: few returns."""
    g = torch.Generator().manual_seed(seed)
    sparse = torch.zeros(1, 1, h, w)
    pick = torch.randperm(h * w, generator=g)[:count]
    sparse.view(-1)[pick] = depths[0] + (depths[1] - depths[0]) * torch.rand(count, generator=g)
    image = torch.full((1, 3, h, w), 0.3)
    image[:, 0, :, w // 2:] = 0.8
    K = torch.tensor([[100.0, 0.0, w / 2], [0.0, 100.0, h / 2], [0.0, 0.0, 1.0]])[None]
    return image, sparse, K


@pytest.fixture(scope="module")
def default():
    return CRFDepth.from_pretrained()


@pytest.mark.parametrize("save", [save_model, save_weights], ids=["model file", "weights file"])
def test_a_saved_default_keeps_its_regimes(tmp_path, default, save):
    path = tmp_path / ("model.pt" if save is save_model else "weights.json")
    save(default, path)
    loaded = load_model(path)
    assert list(loaded.regimes()) == list(REGIMES)
    for name, regime in default.regimes().items():
        assert loaded.regimes()[name].settings.structure == regime.settings.structure
        assert loaded.regimes()[name].weights() == pytest.approx(regime.weights(), rel=1e-5)
    # outdoor and indoor frames with few returns: the regimes complete them, as before the file
    for depths in ((15.0, 40.0), (1.5, 4.0)):
        frame = _frame(depths)
        with torch.no_grad():
            before, after = default(*frame).depth, loaded(*frame).depth
            alone = CRFDepth.from_pretrained(adaptive=False)(*frame).depth
        assert (after - before).abs().max() <= TOLERANCE
        assert (alone - before).abs().max() > 100 * TOLERANCE  # the regimes matter on these frames


def test_a_model_without_regimes_writes_none(tmp_path):
    save_weights(CRFDepth.from_pretrained(adaptive=False), tmp_path / "w.json")
    assert "regimes" not in json.loads((tmp_path / "w.json").read_text())
    save_model(CRFDepth(), tmp_path / "m.pt")
    assert "regimes" not in torch.load(tmp_path / "m.pt", weights_only=True)
    assert load_model(tmp_path / "m.pt").regimes() == {}


def test_an_override_of_the_structure_asks_for_one_model(tmp_path, default):
    save_model(default, tmp_path / "m.pt")
    assert load_model(tmp_path / "m.pt", overrides={"variable": "depth"}).regimes() == {}
    assert list(load_model(tmp_path / "m.pt", overrides={"rtol": 1e-4}).regimes()) == list(REGIMES)


def _damage_json(data, case):
    regimes = data["regimes"]
    if case == "not a mapping":
        data["regimes"] = [1, 2]
    elif case == "unknown name":
        regimes["fog_regime"] = regimes.pop("line_regime")
    elif case == "no config":
        regimes["sparse_regime"] = {"state": {}}
    else:  # a learned value out of its range
        regimes["indoor_regime"]["config"]["potentials"]["confidence"] = 1e30
    return data


@pytest.mark.parametrize("case", ["not a mapping", "unknown name", "no config", "weight out of range"])
def test_a_damaged_weights_file_names_the_file_and_the_regime(tmp_path, default, case):
    path = tmp_path / "w.json"
    save_weights(default, path)
    path.write_text(json.dumps(_damage_json(json.loads(path.read_text()), case)))
    with pytest.raises(InputError) as info:
        load_model(path)
    message = str(info.value)
    assert str(path) in message and "regimes" in message
    if case == "weight out of range":
        assert "regimes['indoor_regime']" in message and "confidence" in message


@pytest.mark.parametrize("case", ["not a state dict", "not finite"])
def test_a_damaged_model_file_names_the_file_and_the_regime(tmp_path, default, case):
    path = tmp_path / "m.pt"
    save_model(default, path)
    payload = torch.load(path, weights_only=True)
    record = payload["regimes"]["sparse_regime"]
    if case == "not a state dict":
        record["state_dict"] = [1.0]
    else:
        key = next(k for k in record["state_dict"] if k.startswith("raw_"))
        record["state_dict"][key] = torch.tensor(float("nan"))
    torch.save(payload, path)
    with pytest.raises(InputError) as info:
        load_model(path)
    message = str(info.value)
    assert str(path) in message
    assert "regimes['sparse_regime']" in message
    if case == "not finite":
        assert "raw_" in message
