"""benchmarks/stereo_check.py: the labels and pictures on hand-made arrays, the synthetic measurement against the
truth, and drive 0048."""

from __future__ import annotations

import json

import cv2
import numpy as np
import pytest
import torch

from tests.benchmark_scripts import load_benchmark


@pytest.fixture(scope="module")
def bench():
    return load_benchmark("stereo_check")


@pytest.fixture
def one_thread():
    """The check's small batched products are slower on two threads of a shared machine than on one."""
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)


def test_labels_of_hand_made_returns(bench):
    z = np.array([10.0, 10.2, 11.2, 12.0, 12.0, 8.0, 5.0])
    truth = np.array([10.0, 10.0, 10.0, 10.0, 0.0, 10.0, 10.0])
    mover = np.array([False, False, False, True, False, False, False])
    # 3% + 5 cm: good; 10% + 0.3 m: bad (behind: see-through, a mover's, in front: nearer); between: not counted
    assert bench.label(z, truth, mover).tolist() == [bench.GOOD, bench.GOOD, 0, bench.MOVER, bench.SEE_THROUGH,
                                                     bench.NEARER, bench.NEARER]
    kinds = np.array([bench.GOOD] * 4 + [bench.SEE_THROUGH, bench.MOVER, bench.NEARER, 0])
    dropped = np.array([True, False, False, False, True, True, False, True])
    informative = np.array([True] * 5 + [False] * 3)
    s = bench.scores(kinds, dropped, informative)
    assert (s.good, s.bad, s.good_kept, s.bad_removed) == (4, 3, 0.75, pytest.approx(2 / 3))
    assert (s.bad_informative, s.bad_removed_informative) == (pytest.approx(1 / 3), 1.0)
    assert s.removed == {"see_through": 1.0, "mover": 1.0, "nearer": 0.0}


def test_picture_paints_the_layers(bench, tmp_path):
    rgb = np.full((20, 30, 3), 128, np.uint8)
    kept, dropped = np.zeros((20, 30), bool), np.zeros((20, 30), bool)
    kept[2, 3], dropped[10, 10] = True, True
    bench.picture(rgb, [(kept, bench.GREEN), (dropped, bench.RED)], tmp_path / "p.png")
    out = cv2.cvtColor(cv2.imread(str(tmp_path / "p.png")), cv2.COLOR_BGR2RGB)
    assert tuple(out[2, 3]) == bench.GREEN and tuple(out[9, 11]) == bench.RED  # the dropped one grown to 3x3
    assert tuple(out[0, 0]) == (76, 76, 76)  # grey 128 darkened: 128 // 16 * 7 + 20


def test_synthetic_stereo_against_the_truth(bench, one_thread):
    # A short drive (5 frames, k = 2; the benchmark's default is 9 frames, k = 4). Measured, seed 0 at 176 x 608:
    # 51,637 good and 1,774 bad returns; good kept 0.992, bad removed 0.363 (movers 0.576, see-through 0.174),
    # 0.645 of the bad returns informative and 0.562 of those removed; the camera-view targets keep 0.995 of their
    # good pixels. The margins below allow for other platforms' floating point, not for another rule.
    r = bench.measure_synthetic(0, n_frames=5, index=2, k=2)
    a = r.accumulated
    assert a.good > 40_000 and a.bad > 1_000
    assert a.good_kept > 0.985
    assert a.bad_removed > 0.32 and a.removed["mover"] > 0.5
    assert a.bad_removed_informative > 0.5
    assert r.targets.good_kept > 0.99


def test_missing_kitti_root_is_named(bench, tmp_path, capsys):
    with pytest.raises(SystemExit):
        bench.main(["--seeds", "--kitti", str(tmp_path / "nothing")])
    assert (f"--kitti: expected the KITTI sample root holding stereo/2011_09_26/2011_09_26_drive_0048_sync, got "
            f"{tmp_path / 'nothing'}") in capsys.readouterr().err


@pytest.mark.kitti
def test_drive_0048_drop_shares_and_pictures(bench, kitti_root, tmp_path, one_thread):
    # Measured: scan 3.7-5.1%, 20% hold-out 2.6-3.9%, camera-view targets (k = 1) 2.3-2.7% of the returns dropped.
    rows = bench.measure_kitti(kitti_root, tmp_path, frames=[1])
    assert [r.frame for r in rows] == ["0000000001"]
    r = rows[0]
    assert r.scan_returns > 15_000 and 0.02 < r.scan_dropped < 0.08
    assert r.holdout_returns > 2_500 and 0.01 < r.holdout_dropped < 0.06
    assert r.targets_returns > 2 * r.scan_returns and 0.01 < r.targets_dropped < 0.05
    for name in ("scan", "targets"):
        path = tmp_path / f"drive0048_0000000001_{name}.png"
        assert path.stat().st_size < 300_000
        image = cv2.cvtColor(cv2.imread(str(path)), cv2.COLOR_BGR2RGB)
        assert image.shape == (375, 1242, 3) and (image == bench.RED).all(axis=2).sum() > 100


@pytest.mark.kitti
def test_main_prints_a_table_and_json(bench, kitti_root, capsys, monkeypatch):
    # The whole script, its measurements replaced by a quick stand-in (the two tests above measure).
    monkeypatch.setattr(bench, "measure_kitti", lambda root, pictures: [bench.KittiFrame("0000000000", 10, 0.1, 5, 0.2,
                                                                                         20, 0.05, 1.0)])
    assert bench.main(["--seeds", "--kitti", str(kitti_root)]) == 0
    out = capsys.readouterr().out.strip().splitlines()
    assert "drive 0048: share of returns dropped (returns)" in out
    result = json.loads(out[-1])
    assert result["synthetic"] == [] and result["kitti"][0]["targets_dropped"] == 0.05
