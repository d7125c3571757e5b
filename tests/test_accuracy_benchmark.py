"""benchmarks/accuracy.py: a smoke run on real frames."""

from __future__ import annotations

import importlib.util
import json
from pathlib import Path

import pytest

SCRIPT = Path(__file__).resolve().parents[1] / "benchmarks" / "accuracy.py"


@pytest.fixture(scope="module")
def accuracy():
    spec = importlib.util.spec_from_file_location("accuracy_benchmark", SCRIPT)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


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
