"""benchmarks/accuracy.py: the sparsification/AUSE oracle and a smoke run on real frames."""

from __future__ import annotations

import importlib.util
import json
import math
from pathlib import Path

import numpy as np
import pytest

SCRIPT = Path(__file__).resolve().parents[1] / "benchmarks" / "accuracy.py"


@pytest.fixture(scope="module")
def accuracy():
    spec = importlib.util.spec_from_file_location("accuracy_benchmark", SCRIPT)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_ause_of_oracle_order_is_zero(accuracy):
    rng = np.random.default_rng(0)
    err = rng.normal(size=5000) * 1000.0
    assert abs(accuracy.ause(err, np.abs(err))["ause"]) < 1e-9
    # Any monotone function of |error| orders the same: also 0.
    assert abs(accuracy.ause(err, np.sqrt(np.abs(err)) + 3.0)["ause"]) < 1e-9


def test_sparsification_hand_computed_and_ties(accuracy):
    err = np.array([4.0, 3.0, 0.0, 0.0])
    # Removing the largest error first: RMSE sqrt(25/4), sqrt(9/3), 0, 0 at 0, 1/4, 2/4, 3/4.
    curve = accuracy.sparsification(err, np.abs(err), steps=4)
    np.testing.assert_allclose(curve, [2.5, math.sqrt(3.0), 0.0, 0.0], atol=1e-12)
    # A constant map is a random order: the expected remaining MSE is flat at the full MSE.
    flat = accuracy.sparsification(err, np.ones(4), steps=4)
    np.testing.assert_allclose(flat, [2.5] * 4, atol=1e-12)
    a = accuracy.ause(err, np.ones(4), steps=4)
    assert a["ause"] == pytest.approx(a["ause_random"])
    # The worst order (smallest error first) has a larger AUSE than random.
    assert accuracy.ause(err, -np.abs(err), steps=4)["ause"] > a["ause_random"]


def test_quick_run_writes_parseable_json(accuracy, kitti_root, tmp_path, capsys):
    rows = accuracy.main(["--quick", "--kitti-root", str(kitti_root), "--protocols", "a",
                          "--methods", "nn", "default", "--no-subsample", "--out-dir", str(tmp_path)])
    lines = [json.loads(x) for x in (tmp_path / "results.jsonl").read_text().splitlines()]
    assert lines == json.loads(json.dumps(rows))
    assert [(r["protocol"], r["method"]) for r in lines] == [("a", "nn"), ("a", "default")]
    by = {r["method"]: r for r in lines}
    # Nearest fill on the official frame: about 1.3-1.4 m RMSE (DESIGN.md section 6: 1386 mm over 2 frames).
    assert 1000 < by["nn"]["rmse"] < 1700
    assert by["default"]["rmse"] < by["nn"]["rmse"]
    for r in lines:
        assert r["frames"] == 1 and r["batch_size"] == 1 and r["fps_median"] > 0
    d = by["default"]
    assert 0 < d["ause_std_mm"] < d["ause_random_std_mm"]
    assert "| default |" in (tmp_path / "results.md").read_text()
    printed = capsys.readouterr().out
    assert sum(1 for x in printed.splitlines() if x.startswith("{")) == 2
