"""The grouped configuration (crfdepth/config.py, docs/design.md section 8)."""

from __future__ import annotations

import json

import pytest

from crfdepth.config import FLAT, GROUPS, CRFConfig, Gate, flat_view, is_grouped
from crfdepth.model import CRFDepth


def test_every_flat_name_has_one_field_and_every_field_one_flat_name():
    fields = {(group, f) for group, kind in GROUPS.items() for f in kind.__dataclass_fields__}
    assert len(FLAT) == 34 and set(FLAT.values()) == fields and len(set(FLAT.values())) == len(FLAT)


def test_groups_and_flat_names_build_the_same_model():
    flat = CRFDepth(mode="pixel", variable="log", gate=True, gate_window=7, alpha=0.3, uncertainty="posterior")
    grouped = CRFDepth(structure={"mode": "pixel", "variable": "log"}, gate={"enabled": True, "window": 7},
                       potentials={"alpha": 0.3}, uncertainty={"kind": "posterior"})
    typed = CRFDepth(CRFConfig(gate=Gate(enabled=True, window=7)), mode="pixel", variable="log", alpha=0.3,
                     uncertainty="posterior")
    assert flat.config == grouped.config == typed.config
    assert (flat.mode, flat.variable, flat.gate, flat.gate_window, flat.uncertainty) == ("pixel", "log", True, 7,
                                                                                         "posterior")
    assert float(grouped.alpha) == pytest.approx(0.3)


def test_the_stored_configuration_is_plain_json_in_five_groups_and_rebuilds_the_model():
    model = CRFDepth(mode="pixel", potentials=("colour", "distance"), std_terms=None)
    text = json.dumps(model.config)
    assert set(model.config) == set(GROUPS) and model.config["potentials"]["on"] == ["colour", "distance"]
    assert CRFDepth(json.loads(text)).config == model.config
    assert CRFDepth(**json.loads(text)).config == model.config  # as LightningCLI passes a YAML mapping


def test_a_group_updates_only_the_fields_it_names():
    config = CRFConfig.build({"structure": {"mode": "pixel"}}, gate={"threshold": 0.02})
    assert config.structure.mode == "pixel" and config.structure.superpixels == 5500
    assert config.gate.threshold == 0.02 and config.gate.enabled is False


def test_flat_view_reads_both_kinds_of_stored_configuration():
    grouped = CRFDepth(mode="pixel", alpha=0.25).config
    assert is_grouped(grouped) and not is_grouped({"mode": "pixel", "gate": True})
    view = flat_view(grouped)
    assert view["mode"] == "pixel" and view["alpha"] == 0.25 and len(view) == 34
    assert flat_view({"mode": "pixel"}) == {"mode": "pixel"}


@pytest.mark.parametrize("kwargs, match", [
    ({"colour": 1}, "unexpected keyword argument 'colour'"),
    ({"gate": {"enabeld": True}}, "unexpected gate field"),
    ({"structure": {"mod": "pixel"}}, "unexpected structure field"),
])
def test_unknown_names_are_refused_like_unknown_arguments(kwargs, match):
    with pytest.raises(TypeError, match=match):
        CRFDepth(**kwargs)


def test_bad_values_in_a_group_name_the_option():
    from crfdepth.errors import InputError

    with pytest.raises(InputError, match="gate_window: expected an odd int >= 3"):
        CRFDepth(gate={"enabled": True, "window": 4})
    with pytest.raises(InputError, match=r"mode: expected one of \('superpixel', 'pixel'\), got 'grid'"):
        CRFDepth(structure={"mode": "grid"})


def test_weights_files_are_written_in_groups_and_flat_ones_still_load(tmp_path):
    from crfdepth.checkpoints import load_model, save_weights

    model = CRFDepth(mode="pixel", variable="log", gate=True, alpha=0.3, sigma_d=0.2)
    new = save_weights(model, tmp_path / "new.json")
    stored = json.loads(new.read_text())["config"]
    assert is_grouped(stored) and stored["potentials"]["alpha"] == pytest.approx(0.3)
    old = json.loads(new.read_text())
    old["config"] = flat_view(stored)  # a file written before the groups
    (tmp_path / "old.json").write_text(json.dumps(old))
    a, b = load_model(new), load_model(tmp_path / "old.json")
    assert a.config == b.config and a.mode == "pixel" and b.gate
    assert float(a.alpha) == pytest.approx(0.3) and float(b.sigma_d) == pytest.approx(0.2)


def test_the_shipped_weights_file_predates_the_groups_and_loads():
    from crfdepth.weights import weights_path

    stored = json.loads(weights_path("kitti").read_text())["config"]
    assert not is_grouped(stored)
    model = CRFDepth.from_pretrained("kitti")
    assert model.config["structure"]["mode"] == stored["mode"] and model.gate == stored["gate"]
