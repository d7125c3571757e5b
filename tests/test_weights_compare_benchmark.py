"""benchmarks/weights_compare.py: weight files side by side on the real frames, and its refusals."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from tests.benchmark_scripts import load_benchmark

SHIPPED = Path(__file__).resolve().parents[1] / "crfdepth" / "weights" / "kitti.json"


@pytest.fixture(scope="module")
def bench():
    return load_benchmark("weights_compare")


@pytest.mark.kitti
@pytest.mark.slow
def test_the_shipped_weights_on_the_official_frames(bench, kitti_root, capsys):
    result = bench.main(["--weights", f"shipped={SHIPPED}", "--protocols", "a", "--kitti-root", str(kitti_root)])
    out = capsys.readouterr().out.splitlines()
    assert json.loads(out[-1])["protocols"] == result
    row = result["a"]
    assert row["frames"] == 2
    # measured on this CPU (docs/design.md section 16): IP-Basic 1075, hand-set 1006, shipped 950 mm
    assert row["hand-set"] == pytest.approx(1006, rel=0.01)
    assert row["shipped"] / row["hand-set"] == pytest.approx(0.945, abs=0.01)
    assert row["ipbasic"] / row["hand-set"] == pytest.approx(1.069, abs=0.01)
    assert any(line.startswith("| a | 2 |") for line in out)


@pytest.mark.parametrize(("weights", "message"), [
    (["shipped"], "--weights: expected distinct NAME=FILE pairs"),
    (["hand-set=x.json"], "--weights: expected distinct NAME=FILE pairs"),
    ([f"a={SHIPPED}", f"a={SHIPPED}"], "--weights: expected distinct NAME=FILE pairs"),
])
def test_bad_weight_lists_exit_2(bench, weights, message, capsys):
    with pytest.raises(SystemExit) as e:
        bench.parse_args(["--weights", *weights])
    assert e.value.code == 2
    assert capsys.readouterr().err.strip().splitlines()[-1].startswith(f"weights_compare.py: error: {message}")


def test_a_missing_weights_file_is_one_line(bench, tmp_path, capsys):
    with pytest.raises(SystemExit) as e:
        bench.main(["--weights", f"new={tmp_path / 'none.json'}", "--kitti-root", str(tmp_path)])
    assert e.value.code == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("weights_compare.py: error: --weights: new=") and "no such file" in err[0]


def test_a_missing_root_is_refused(bench, tmp_path, capsys):
    with pytest.raises(SystemExit) as e:
        bench.parse_args(["--kitti-root", str(tmp_path / "nowhere")])
    assert e.value.code == 2
    assert "--kitti-root: expected the KITTI sample folder" in capsys.readouterr().err
