"""``python -m train.export``: a trainer checkpoint -> a JSON weights file (crfdepth.weights)."""

from __future__ import annotations

import json
import math

import pytest
import torch

from crfdepth.checkpoints import load_model
from crfdepth.model import CRFDepth
from train.export import main


def _checkpoint(path):
    model = CRFDepth(potentials=("colour", "normal"))
    with torch.no_grad():
        model.raw_alpha -= 0.7
        model.log_sigma_d += 0.2
        model.log_std_scale += 0.4
    ckpt = {
        "epoch": 3, "global_step": 192,
        "state_dict": {f"model.{k}": v for k, v in model.state_dict().items()},
        "hyper_parameters": {"crf": model.config, "loss": "l1", "nll_weight": 0.01, "lr": 0.02},
        "datamodule_hyper_parameters": {"layout": "raw", "val_names_contain": "drive_0001"},
        "callbacks": {"ModelCheckpoint{'monitor': 'val/rmse', 'mode': 'min'}": {
            "monitor": "val/rmse", "best_model_score": torch.tensor(1401.5),
            "best_model_path": "/somewhere/checkpoints/epoch002-rmse1401.5.ckpt"}},
    }
    torch.save(ckpt, path)
    return model


def test_export_writes_weights_and_provenance(tmp_path, capsys):
    model = _checkpoint(tmp_path / "last.ckpt")
    config = tmp_path / "recipe.yaml"
    config.write_text("model:\n  loss: l1\n")
    out = tmp_path / "w.json"
    assert main([str(tmp_path / "last.ckpt"), "--out", str(out), "--config", str(config),
                 "--command", "python -m train fit --config recipe.yaml", "--note", "val 1401.5 mm"]) == 0
    assert "wrote" in capsys.readouterr().out
    about = json.loads(out.read_text())["about"]
    assert about["epoch"] == 3 and about["global_step"] == 192 and about["monitor"] == "val/rmse"
    assert about["best_model_score"] == pytest.approx(1401.5)
    assert about["best_model_path"] == "epoch002-rmse1401.5.ckpt"
    assert about["hyper_parameters"]["loss"] == "l1" and about["datamodule_hyper_parameters"]["layout"] == "raw"
    assert about["config"] == "model:\n  loss: l1\n" and about["command"].startswith("python -m train fit")
    assert about["note"] == "val 1401.5 mm"
    loaded = load_model(out)
    assert loaded.settings.potentials.on == ("colour", "normal")
    assert loaded.weights() == pytest.approx(model.weights(), rel=1e-5)


def test_export_bad_input_exits_2_without_output(tmp_path, capsys):
    out = tmp_path / "w.json"
    assert main([str(tmp_path / "none.ckpt"), "--out", str(out)]) == 2
    assert "none.ckpt" in capsys.readouterr().err and not out.exists()
    _checkpoint(tmp_path / "last.ckpt")
    assert main([str(tmp_path / "last.ckpt"), "--out", str(out), "--config", str(tmp_path / "no.yaml")]) == 2
    assert "--config: no such file" in capsys.readouterr().err and not out.exists()


def test_export_calibrates_the_std_scale_on_the_configs_training_frames(tmp_path, capsys):
    _checkpoint(tmp_path / "last.ckpt")
    config = tmp_path / "recipe.yaml"
    config.write_text("data:\n  layout: synthetic\n  train_options: {count: 2, height: 48, width: 160}\n")
    out = tmp_path / "w.json"
    assert main([str(tmp_path / "last.ckpt"), "--out", str(out), "--config", str(config), "--calibrate-std",
                 "--uncertainty", "posterior"]) == 0
    about = json.loads(out.read_text())["about"]
    calibration = about["std_calibration"]
    assert calibration["frames"] == 2 and calibration["before"] == pytest.approx(math.exp(0.4), rel=1e-6)
    assert calibration["after"] != pytest.approx(calibration["before"], rel=1e-3)
    assert load_model(out).weights()["std_scale"] == pytest.approx(calibration["after"], rel=1e-6)
    assert "posterior std fitted on 2 training frames" in capsys.readouterr().out


def test_export_fits_the_predictive_std_on_the_configs_training_frames(tmp_path, capsys):
    _checkpoint(tmp_path / "last.ckpt")
    config = tmp_path / "recipe.yaml"
    config.write_text("data:\n  layout: synthetic\n  train_options: {count: 2, height: 48, width: 160}\n")
    out = tmp_path / "w.json"
    assert main([str(tmp_path / "last.ckpt"), "--out", str(out), "--config", str(config), "--calibrate-std"]) == 0
    data = json.loads(out.read_text())
    calibration = data["about"]["std_calibration"]
    assert calibration["uncertainty"] == "predictive" and calibration["frames"] == 2
    assert calibration["after"] != calibration["before"]
    assert data["config"]["uncertainty"]["terms"] == pytest.approx(calibration["after"], rel=1e-6)
    assert load_model(out).std_head.terms() == pytest.approx(calibration["after"], rel=1e-6)
    assert "predictive std fitted on 2 training frames" in capsys.readouterr().out


def test_export_calibrate_std_needs_a_config(tmp_path, capsys):
    _checkpoint(tmp_path / "last.ckpt")
    assert main([str(tmp_path / "last.ckpt"), "--out", str(tmp_path / "w.json"), "--calibrate-std"]) == 2
    assert "--calibrate-std: needs --config" in capsys.readouterr().err
