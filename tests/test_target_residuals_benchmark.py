"""benchmarks/target_residuals.py: the residual statistics on hand-made arrays, and a run on a synthetic drive."""

from __future__ import annotations

import json

import numpy as np
import pytest

from crfdepth.cli import main as cli
from crfdepth.data.synthetic import make_sequence
from tests.benchmark_scripts import load_benchmark
from tests.sequence_drive import poses_file, write_drive


@pytest.fixture(scope="module")
def bench():
    return load_benchmark("target_residuals")


def test_residual_statistics_on_hand_made_arrays(bench):
    # 200 target pixels at 10 m: 198 predicted 0.1 m too far, one predicted 5 m too far (its target
    # nearer than the prediction) and one 4 m too near; the own scan has a return at the first of the two,
    # and the second has two supporting scans
    target = np.full((10, 20), 10.0)
    prediction = target + 0.1
    prediction[0, 0], prediction[0, 1] = 15.0, 6.0
    own = np.zeros_like(target)
    own[0, 0] = 15.0
    support = np.ones(target.shape, np.uint16)
    support[0, 1] = 2
    r = bench.residuals(prediction, target, own, support, top=0.01, far_m=3.0)
    squared = 198 * 0.01 + 25 + 16
    assert r.pixels == 200
    assert r.top_share == pytest.approx((25 + 16) / squared, rel=1e-6)  # the top 1%: the two largest
    assert r.rmse_mm == pytest.approx(1000 * np.sqrt(squared / 200), rel=1e-6)
    assert r.mae_mm == pytest.approx(1000 * (198 * 0.1 + 5 + 4) / 200, rel=1e-6)
    assert r.far == pytest.approx(2 / 200)
    assert (r.far_nearer, r.far_own, r.far_support1) == (0.5, 0.5, 0.5)
    # pixels without a target take no part
    target[5:, :] = 0
    assert bench.residuals(prediction, target, own, support).pixels == 100


def test_run_on_a_synthetic_drive(bench, tmp_path, capsys):
    seq = make_sequence(6, 0, height=176, width=608, movers=1)
    drive = write_drive(tmp_path / "raw", seq)
    assert cli(["targets", "--drive", str(drive), "--poses", str(poses_file(drive)), "--out-dir",
                str(tmp_path / "targets"), "-k", "2", "--quiet"]) == 0
    capsys.readouterr()
    code = bench.main(["--raw-root", str(tmp_path / "raw"), "--targets-root", str(tmp_path / "targets"),
                       "--frames", "0", "5", "--every", "2", "--threads", "1"])
    out = capsys.readouterr().out
    assert code == 0
    result = json.loads(out.strip().splitlines()[-1])
    # frames 1-4 have both neighbours inside 0-5; every 2nd: frames 1 and 3
    assert [f["name"].rsplit("_", 3)[1] for f in result["frames"]] == ["0000000001", "0000000003"]
    for frame in result["frames"]:
        assert frame["pixels"] > 0.3 * 176 * 608 and 0 < frame["top_share"] <= 1
        assert 0 < frame["rmse_mm"] < 5000


def test_missing_raw_root_is_named(bench, tmp_path, capsys):
    with pytest.raises(SystemExit):
        bench.main(["--raw-root", str(tmp_path / "nothing")])
    assert f"--raw-root: expected a folder of KITTI raw drives (<date>/<drive>_sync), got {tmp_path / 'nothing'}" \
        in capsys.readouterr().err
