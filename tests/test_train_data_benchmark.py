"""benchmarks/train_data.py: the config's data re-rooted, the synthetic stand-in, a smoke run."""

from __future__ import annotations

import json
import math
from pathlib import Path

import pytest
import yaml

from tests.benchmark_scripts import load_benchmark

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def bench():
    return load_benchmark("train_data")


def test_config_roots_move_under_data(bench, tmp_path):
    (tmp_path / "raw").mkdir()
    config = yaml.safe_load((ROOT / "configs" / "kitti_weights.yaml").read_text())
    options, what = bench.data_options(config, tmp_path, 8)
    assert options["root"] == str(tmp_path / "raw") and what == f"raw under {tmp_path}"
    assert [s["root"] for s in options["extra_train"]] == [str(tmp_path / "raw"), *[str(tmp_path / "object/training")] * 2]
    assert options["crop"] == [320, 896] and config["data"]["root"] == "../shared/data/kitti/raw"  # not modified


def test_synthetic_stand_in_keeps_the_augmentation(bench, tmp_path, capsys):
    config = yaml.safe_load((ROOT / "configs" / "kitti_weights.yaml").read_text())
    options, what = bench.data_options(config, tmp_path / "none", 8)
    assert options["layout"] == "synthetic" and options["train_options"]["count"] == 8
    assert {k: options[k] for k in ("flip", "crop", "thin")} == {k: config["data"][k] for k in ("flip", "crop", "thin")}
    assert "no KITTI raw drive" in capsys.readouterr().out and "synthetic" in what


def test_smoke_run_prints_one_json_line_per_case(bench, tmp_path, capsys):
    assert bench.main(["--data", str(tmp_path), "--frames", "2", "--steps", "1", "--workers", "0", "1"]) == 0
    rows = [json.loads(line) for line in capsys.readouterr().out.splitlines() if line.startswith("{")]
    assert [(r["case"], r["workers"]) for r in rows] == [("loader", 0), ("loader", 1), ("step", None)]
    for r in rows:
        assert r["size"] == [320, 896] and r["frames_per_s"] > 0 and r["data"] == "synthetic (no KITTI data)"
    assert all(r["frames"] >= 2 and r["startup_s"] > 0 for r in rows[:2])
    assert math.isfinite(rows[2]["loss"]) and rows[2]["seconds_min"] <= rows[2]["seconds"]
