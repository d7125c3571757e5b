"""benchmarks/speed_accuracy.py: RMSE against ms of every method, on a tiny synthetic frame, and a bad option."""

from __future__ import annotations

import json

import cv2
import numpy as np
import pytest

from tests.benchmark_scripts import load_benchmark


@pytest.fixture(scope="module")
def bench():
    return load_benchmark("speed_accuracy")


def test_every_method_gets_a_point_on_the_synthetic_street(bench, tmp_path, capsys):
    empty = tmp_path / "no_kitti"  # a folder without KITTI frames: the synthetic street
    empty.mkdir()
    out = tmp_path / "pictures" / "speed_accuracy.png"
    assert bench.main(["--kitti-root", str(empty), "--synthetic-size", "256x80", "--repeats", "1", "--threads", "1",
                       "--out", str(out)]) == 0
    lines = capsys.readouterr().out.splitlines()
    assert lines[0].startswith("note: no KITTI frames under ")
    record = json.loads(lines[-1])
    assert list(record["protocols"]) == ["synthetic"]
    rows = {r["method"]: r for r in record["rows"]}
    assert list(rows) == list(bench.METHODS)
    for method, row in rows.items():
        assert row["ms"] > 0 and row["rmse"]["synthetic"] > 0, method
        assert row["timing_size"] == "256x80"
    assert rows["default+std"]["rmse"] == pytest.approx(rows["default"]["rmse"])  # the std leaves the depth as it is
    image = cv2.imread(str(out))
    assert image is not None and image.shape[0] > 200 and image.shape[1] > 400
    assert np.unique(image.reshape(-1, 3), axis=0).shape[0] > 10  # something is drawn


def test_a_bad_option_is_one_line(bench, capsys):
    with pytest.raises(SystemExit) as info:
        bench.main(["--repeats", "0"])
    err = capsys.readouterr().err.splitlines()
    assert info.value.code == 2
    assert err == ["speed_accuracy.py: error: --repeats: expected an integer in [1, 2147483647], got '0'"]
