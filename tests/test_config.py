"""The grouped configuration (crfdepth/config.py, docs/design.md section 8)."""

from __future__ import annotations

import json

import pytest

from crfdepth.config import (
    DEFAULT_STD_TERMS,
    FLAT,
    GROUPS,
    SOLVER_METHODS,
    CRFConfig,
    Gate,
    Potentials,
    Solver,
    Structure,
    Uncertainty,
    flat_view,
    is_grouped,
)
from crfdepth.errors import InputError
from crfdepth.model import CRFDepth

OLD_ATTRIBUTES = ("mode", "superpixels", "scale_superpixels", "potentials", "aggregate", "refine", "rounds", "variable",
                  "prior", "std_samples", "gate", "gate_window", "irls", "uncertainty", "memory_limit_gb", "solver")
"""The flat attributes ``CRFDepth`` copied its configuration into before ``model.settings`` was the one copy."""


def test_every_flat_name_has_one_field_and_every_field_one_flat_name():
    fields = {(group, f) for group, kind in GROUPS.items() for f in kind.__dataclass_fields__}
    assert len(FLAT) == 37 and set(FLAT.values()) == fields and len(set(FLAT.values())) == len(FLAT)


def test_groups_and_flat_names_build_the_same_model():
    flat = CRFDepth(mode="pixel", variable="log", gate=True, gate_window=7, alpha=0.3, uncertainty="posterior")
    grouped = CRFDepth(structure={"mode": "pixel", "variable": "log"}, gate={"enabled": True, "window": 7},
                       potentials={"alpha": 0.3}, uncertainty={"kind": "posterior"})
    typed = CRFDepth(CRFConfig(gate=Gate(enabled=True, window=7)), mode="pixel", variable="log", alpha=0.3,
                     uncertainty="posterior")
    assert flat.config == grouped.config == typed.config
    s = flat.settings
    assert (s.structure.mode, s.structure.variable, s.gate.enabled, s.gate.window, s.uncertainty.kind) == (
        "pixel", "log", True, 7, "posterior")
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
    assert view["mode"] == "pixel" and view["alpha"] == 0.25 and len(view) == 37
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
    assert a.config == b.config and a.settings.structure.mode == "pixel" and b.settings.gate.enabled
    assert float(a.alpha) == pytest.approx(0.3) and float(b.sigma_d) == pytest.approx(0.2)


def test_the_shipped_weights_file_predates_the_groups_and_loads():
    from crfdepth.weights import weights_path

    stored = json.loads(weights_path("kitti").read_text())["config"]
    assert not is_grouped(stored)
    model = CRFDepth.from_pretrained("kitti")
    assert model.config["structure"]["mode"] == stored["mode"] and model.settings.gate.enabled == stored["gate"]


@pytest.mark.parametrize("build, name", [
    (lambda: Structure(mode="grid"), "mode"), (lambda: Structure(variable="sqrt"), "variable"),
    (lambda: Structure(prior="zero"), "prior"), (lambda: Structure(superpixels=0), "superpixels"),
    (lambda: Structure(rounds=1.5), "rounds"), (lambda: Potentials(on=("normal",)), "potentials"),
    (lambda: Potentials(alpha=1.5), "alpha"), (lambda: Potentials(irls=-1), "irls"),
    (lambda: Potentials(sigma_p=0.0), "sigma_p"), (lambda: Potentials(eps=-1.0), "eps"),
    (lambda: Gate(window=4), "gate_window"), (lambda: Gate(threshold=0.0), "gate_threshold"),
    (lambda: Gate(softness=float("nan")), "gate_softness"), (lambda: Solver(memory_limit_gb=0), "memory_limit_gb"),
    (lambda: Uncertainty(kind="sampled"), "uncertainty"), (lambda: Uncertainty(scale=-2.0), "std_scale"),
    (lambda: Solver(method="gmres"), "method"), (lambda: Solver(rtol=1.0), "rtol"), (lambda: Solver(rtol=True), "rtol"),
    (lambda: Solver(max_iter=-1), "max_iter"), (lambda: Solver(max_iter=2.5), "max_iter"),
    (lambda: Uncertainty(terms={"bias": 0.0}), "std_terms"),
    (lambda: Uncertainty(terms={**DEFAULT_STD_TERMS, "edge": float("inf")}), "std_terms"),
])
def test_each_group_refuses_a_bad_value_naming_its_flat_name(build, name):
    with pytest.raises(InputError, match=rf"^{name}: expected"):
        build()


def test_the_solver_group_takes_the_methods_the_solves_have_and_keeps_std_terms_as_given():
    from crfdepth.linalg import adjoint

    assert set(SOLVER_METHODS) == set(adjoint._METHODS)
    assert Uncertainty().terms is None and Uncertainty(terms=DEFAULT_STD_TERMS).terms == DEFAULT_STD_TERMS
    with pytest.raises(InputError, match=r"^method: expected one of 'cg', 'cgs', got 'gmres'$"):
        CRFDepth(method="gmres")  # the model's message is the group's


def test_a_group_is_refused_with_the_message_the_model_gave():
    with pytest.raises(InputError, match=r"^gate_window: expected an odd int >= 3 \(pixels\), got 4$"):
        Gate(window=4)
    assert Potentials(on=["colour", "normal"]).on == ("colour", "normal")  # as YAML gives it


def test_the_gate_needs_the_mean_across_groups():
    with pytest.raises(InputError, match="aggregate: the occlusion gate weights a mean, expected 'mean' with gate=True"):
        CRFConfig(structure=Structure(aggregate="median"), gate=Gate(enabled=True))
    with pytest.raises(InputError, match="^aggregate: "):
        CRFConfig.build(structure={"aggregate": "median"}, gate=True)
    # Checked once the whole configuration is updated: turning the gate on and the mean back in one call is fine.
    config = CRFConfig.build(CRFConfig(structure=Structure(aggregate="median")), gate=True, aggregate="mean")
    assert config.gate.enabled and config.structure.aggregate == "mean"


def test_a_model_keeps_one_configuration_and_no_copies_of_it():
    model = CRFDepth(mode="pixel", gate=True, potentials=["colour", "distance"], irls=1)
    present = [name for name in OLD_ATTRIBUTES if hasattr(model, name)]
    assert not present, present
    assert isinstance(model.settings, CRFConfig) and model.config == model.settings.groups()
    assert model.settings.potentials.on == ("colour", "distance") and model.solve_settings.rtol == 1e-5
    with pytest.raises(AttributeError):
        model.config = {}  # read-only: the groups are derived from model.settings
