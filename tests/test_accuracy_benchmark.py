"""benchmarks/accuracy.py: a smoke run on real frames."""

from __future__ import annotations

import json

import pytest
import torch

from crfdepth.model import CRFDepth
from crfdepth.uncertainty.predictive import STD_TERMS
from tests.benchmark_scripts import load_benchmark


@pytest.fixture(scope="module")
def accuracy():
    return load_benchmark("accuracy")


def test_quick_run_writes_parseable_json(accuracy, kitti_root, tmp_path, capsys):
    rows = accuracy.main(["--quick", "--kitti-root", str(kitti_root), "--protocols", "a",
                          "--methods", "nn", "paper", "learned", "--no-subsample", "--out-dir", str(tmp_path)])
    lines = [json.loads(x) for x in (tmp_path / "results.jsonl").read_text().splitlines()]
    assert lines == json.loads(json.dumps(rows))
    assert [(r["protocol"], r["method"]) for r in lines] == [("a", "nn"), ("a", "paper"), ("a", "learned")]
    by = {r["method"]: r for r in lines}
    # Nearest fill on the official frame: about 1.3-1.4 m RMSE (docs/design.md section 6: 1386 mm over 2 frames).
    assert 1000 < by["nn"]["rmse"] < 1700
    assert by["paper"]["rmse"] < by["nn"]["rmse"] and by["learned"]["rmse"] < by["nn"]["rmse"]
    assert "shipped weights" in by["learned"]["fit"]  # protocol a: the package's file, never trained on drive 0001
    for r in lines:
        assert r["frames"] == 1 and r["batch_size"] == 1 and r["fps_median"] > 0
    for m in ("paper", "learned"):
        assert 0 < by[m]["ause_std_mm"] < by[m]["ause_random_std_mm"]
        assert by[m]["ause_ratio_std"] == pytest.approx(by[m]["ause_std_mm"] / by[m]["ause_random_std_mm"])
        assert -1 <= by[m]["spearman_std"] <= 1 and 0 <= by[m]["coverage_1_std"] <= by[m]["coverage_2_std"] <= 1
        assert "coverage_1_count" not in by[m]  # the count map is a score, not a std
    # The learned model also reports its posterior-only std; the shipped weights carry its scale.
    learned = by["learned"]
    assert 0 < learned["ause_posterior_mm"] < learned["ause_random_posterior_mm"]
    assert set(learned["std_terms"]["val"]) == set(STD_TERMS) and "ause_posterior_mm" not in by["paper"]
    # Measured on frame image_02: predictive std 0.22 x random, posterior 0.28 x, count map 0.88 x;
    # within 1 std 0.66 (predictive) against 0.98 (posterior).
    assert learned["ause_ratio_std"] < learned["ause_ratio_count"] and learned["ause_ratio_std"] < 0.5
    assert 0.55 < learned["coverage_1_std"] < 0.8 and learned["coverage_1_posterior"] > 0.9
    assert (tmp_path / "reliability.png").stat().st_size > 0 and (tmp_path / "sparsification.png").stat().st_size > 0
    assert "- protocol a, learned std: Spearman" in (tmp_path / "results.md").read_text()
    assert "| paper |" in (tmp_path / "results.md").read_text()
    for r in lines:  # the error by target depth covers every target pixel once
        bins = r["depth_bins"]
        assert list(bins) == ["0-10 m", "10-20 m", "20-40 m", ">= 40 m"]
        assert sum(b["pixels"] for b in bins.values()) == r["pixels"]
        assert sum(b["share_of_squared_error"] for b in bins.values()) == pytest.approx(1.0)
        assert all(b["rmse_mm"] >= 0 for b in bins.values())
    assert "**Where the error is" in (tmp_path / "results.md").read_text()
    printed = capsys.readouterr().out
    assert sum(1 for x in printed.splitlines() if x.startswith("{")) == 3


def test_synthetic_protocol_needs_no_data_folder(accuracy, tmp_path):
    # Protocol s runs anywhere: built-in scenes, scored against the camera's true depth.
    rows = accuracy.main(["--quick", "--kitti-root", str(tmp_path / "nothing"), "--protocols", "s",
                          "--methods", "nn", "learned", "--no-subsample", "--out-dir", str(tmp_path / "out")])
    by = {r["method"]: r for r in rows}
    assert by["learned"]["frames"] == 1 and "synthetic frames: the shipped weights" in by["learned"]["fit"]
    assert by["learned"]["rmse"] < 0.9 * by["nn"]["rmse"]  # measured on seed 1000: 893 against 1380 mm


def test_learned_weights_on_raw_protocols_come_from_the_other_source(accuracy, kitti_root, tmp_path):
    rows = accuracy.main(["--quick", "--kitti-root", str(kitti_root), "--protocols", "c",
                          "--methods", "nn", "learned", "--no-subsample", "--out-dir", str(tmp_path)])
    learned = next(r for r in rows if r["method"] == "learned")
    assert learned["frames"] == 2  # one raw frame, one object frame
    assert "raw frames: fitted on the 1 object frames" in learned["fit"]
    assert "object frames: fitted on the 1 raw frames" in learned["fit"]
    paper = CRFDepth().weights()
    for group, weights in learned["weights"].items():  # each fit moved the hand-set weights
        assert any(abs(weights[k] - paper[k]) > 1e-3 * paper[k] for k in ("alpha", "beta", "confidence")), group


def test_learned_ablations_are_fitted_per_configuration_on_protocol_a_only(accuracy, kitti_root, tmp_path):
    rows = accuracy.main(["--quick", "--kitti-root", str(kitti_root), "--protocols", "a", "c", "--methods", "nn",
                          "--learn-ablations", "--no-subsample", "--out-dir", str(tmp_path)])
    names = [(r["protocol"], r["method"]) for r in rows]
    assert names == [("a", "nn"), *[("a", m) for m in accuracy.methods.LEARNED_ABLATIONS], ("c", "nn")]
    by = {r["method"]: r for r in rows if r["protocol"] == "a"}
    assert by["sp-c/learned"]["config"] == {"potentials": ["colour"], "refine": False}
    assert "drive 0060, object frames" in by["sp-cn+r/learned"]["fit"]
    # Each configuration had its own fit: the normal weight is learned only where the term is on.
    assert by["sp-c/learned"]["weights"]["gamma"] == pytest.approx(0.05)
    assert by["sp-cn/learned"]["weights"]["gamma"] != pytest.approx(0.05)
    text = (tmp_path / "results.md").read_text()
    assert "Table 1 order on protocol a (no refinement, weights learned per configuration)" in text


def test_kitti_root_without_the_protocol_folders_is_named_before_any_output(accuracy, tmp_path, capsys):
    (tmp_path / "raw").mkdir()
    out = tmp_path / "results"
    with pytest.raises(SystemExit) as info:
        accuracy.main(["--kitti-root", str(tmp_path), "--protocols", "a", "b", "--out-dir", str(out)])
    assert info.value.code == 2
    err = capsys.readouterr().err
    assert "--kitti-root" in err and str(tmp_path) in err
    assert "missing: depth_selection/val_selection_cropped, object/training" in err
    assert not out.exists()


@pytest.fixture(scope="module")
def protocols(accuracy):
    import sys

    return sys.modules["accuracy_parts.protocols"]


@pytest.mark.parametrize(("key", "size", "count"), [("t500", (228, 912), 500), ("t200", (228, 912), 200),
                                                      ("n500", (228, 304), 500), ("n200", (228, 304), 200)])
def test_sparse_protocols_draw_n_pixels_of_their_target(protocols, kitti_root, nyu_root, key, size, count):
    frames = 0
    for _, layout, folder, options in protocols.PROTOCOLS[key][1]:
        for s in protocols.load_group(kitti_root, layout, folder, options, 2, nyu_root=nyu_root):
            assert s.size == size
            given = s.sparse > 0
            assert int(given.sum()) == count
            assert torch.equal(s.sparse[given], s.target[given])  # the input is part of the target
            assert int((s.target > 0).sum()) > 20 * count  # the target is the whole scan or depth
            frames += 1
    assert frames == (4 if key.startswith("t") else 3)  # at most 2 per group; the dining room has 1


def test_sparse_protocol_rows_report_log10(accuracy, kitti_root, nyu_root, tmp_path):
    rows = accuracy.main(["--kitti-root", str(kitti_root), "--nyu-root", str(nyu_root), "--protocols", "n500",
                          "--methods", "nn", "default", "--no-subsample", "--max-frames", "1",
                          "--out-dir", str(tmp_path)])
    by = {r["method"]: r for r in rows}
    assert set(by) == {"nn", "default"} and all(r["frames"] == 2 for r in rows)
    assert 0 < by["default"]["log10"] < by["nn"]["log10"] < 0.05
    assert by["default"]["rmse"] < by["nn"]["rmse"]  # measured 284 against 360 mm over the four frames


def test_nyu_root_without_the_scenes_is_named(accuracy, kitti_root, tmp_path, capsys):
    with pytest.raises(SystemExit) as info:
        accuracy.main(["--kitti-root", str(kitti_root), "--nyu-root", str(tmp_path), "--protocols", "n500",
                       "--out-dir", str(tmp_path / "out")])
    assert info.value.code == 2 and "--nyu-root" in capsys.readouterr().err
