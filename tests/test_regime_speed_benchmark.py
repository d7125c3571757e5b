"""benchmarks/regime_speed.py: the default's time per frame against the shipped weights alone."""

from __future__ import annotations

import json

import pytest

from tests.benchmark_scripts import load_benchmark


@pytest.mark.slow
def test_every_input_is_timed_for_both_models(capsys):
    bench = load_benchmark("regime_speed")
    result = bench.main(["--repeats", "3", "--threads", "1"])
    lines = capsys.readouterr().out.splitlines()
    assert json.loads(lines[-1])["rows"] == result["rows"]
    assert {"64-beam", "kitti-500"} <= set(result["rows"])
    for row in result["rows"].values():
        assert row["default"] > 0 and row["shipped alone"] > 0
        assert row["ratio"] == pytest.approx(row["default"] / row["shipped alone"])
    assert result["met"] == all(r["ratio"] <= bench.TARGET for r in result["rows"].values())


def test_repeats_below_three_exit_2(capsys):
    bench = load_benchmark("regime_speed")
    with pytest.raises(SystemExit) as stop:
        bench.main(["--repeats", "1"])
    assert stop.value.code == 2 and "--repeats" in capsys.readouterr().err
