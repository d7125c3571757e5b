"""benchmarks/crossval.py: folds by scene, learned against hand-set in one run, its refusals."""

from __future__ import annotations

import json

import pytest

from crfdepth.errors import InputError
from tests.benchmark_scripts import load_benchmark


@pytest.fixture(scope="module")
def bench():
    return load_benchmark("crossval")


@pytest.mark.kitti
def test_folds_are_disjoint_scenes(bench, kitti_root):
    seen: dict[str, str] = {}
    for fold in bench.FOLDS:
        assert all(len(d) > 0 for _, d in bench.fold_datasets(kitti_root, fold, train=False))
        names = {n for _, d in bench.fold_datasets(kitti_root, fold, train=True, recipe=bench.RECIPES["l1"])
                 for n in _names(d)}
        for n in names:  # a frame trains in one fold only
            assert seen.setdefault(n, fold) == fold
    # every annotated frame of drive 0001 and every scan sample is in some fold
    assert sum("drive_0001" in n for n in seen) == 12
    assert sum("drive_0060" in n for n in seen) == 13
    assert sum("drive_0048" in n for n in seen) == 3


def _names(dataset):
    from torch.utils.data import Subset

    return [dataset.dataset.names[i] for i in dataset.indices] if isinstance(dataset, Subset) else dataset.names


@pytest.mark.kitti
def test_source_choice_follows_the_recipe(bench, kitti_root):
    annotated_only = bench.fold_datasets(kitti_root, "0060-00-24", train=True, recipe=bench.RECIPES["l1-annotated"])
    assert annotated_only == []
    scans_only = bench.fold_datasets(kitti_root, "0001-50", train=True, recipe=bench.RECIPES["l1-scans"])
    assert scans_only == []
    both = bench.fold_datasets(kitti_root, "0001-50", train=True, recipe=bench.RECIPES["l1"])
    assert [s for s, _ in both] == ["annotated", "annotated"]  # the share and the ring inputs


@pytest.mark.kitti
def test_simulated_scan_recipes_draw_their_inputs(bench, kitti_root):
    parts = bench.fold_datasets(kitti_root, "0001-50", train=True, recipe=bench.RECIPES["l1-annotated-lidar-beams"])
    datasets = [d.dataset for _, d in parts]
    assert [(d.input_from, d.keep_every_ring) for d in datasets[:3]] == [("share", 1), ("lidar", 1), ("lidar", 4)]
    # a scan fold is scored with 20% held out (its figure) and at 16 beams
    assert [p for p, _ in bench.fold_datasets(kitti_root, "0048", train=False)] == ["holdout", "holdout16"]


@pytest.mark.kitti
@pytest.mark.parametrize("recipe, hidden", [("head-annotated-lidar-beams", 16), ("head8-annotated-lidar-beams", 8)])
def test_a_head_recipe_trains_a_head_of_its_width(bench, kitti_root, monkeypatch, recipe, hidden):
    trained = []
    monkeypatch.setattr(bench, "train_module", lambda module, *args, **kwargs: trained.append(module))
    model, _, frames = bench.train_fold(kitti_root, ["0001-50", "0001-100"], bench.RECIPES[recipe], epochs=1,
                                        seed=0, device="cpu")
    assert frames == 6  # frames 50 and 100, three inputs each (a share, 64- and 16-beam simulated scans)
    assert model.head.net[0].out_channels == hidden
    # the optimiser is built from the trained module's parameters: the head's weights are among them
    assert any(p is model.head.net[0].weight for p in trained[0].parameters())


@pytest.mark.kitti
@pytest.mark.slow
def test_a_short_run_prints_a_table_and_json(bench, kitti_root, capsys):
    rows = bench.main(["--recipes", "l1", "--folds", "0001-50", "0048", "--epochs", "1",
                       "--kitti-root", str(kitti_root)])
    out = capsys.readouterr().out.splitlines()
    record = json.loads(out[-1])
    assert record["benchmark"] == "crossval" and record["rows"] == rows
    row = rows[0]
    for fold, protocol in (("0001-50", "a22"), ("0048", "holdout")):
        result = row["folds"][fold]
        assert result[protocol]["hand_set_mm"] > 100 and result[protocol]["learned_mm"] > 100
        assert result["ratio"] == pytest.approx(result[protocol]["learned_mm"] / result[protocol]["hand_set_mm"],
                                                rel=1e-3)
    assert row["worst"] == max(row["folds"][f]["ratio"] for f in row["folds"])
    assert "| l1 |" in "\n".join(out)


@pytest.mark.parametrize(("folds", "message"), [
    (["0001-50", "nowhere"], r"^--folds: expected fold names among .*, got \['nowhere'\]"),
    (["0048"], r"^--folds: expected at least two distinct folds"),
    (["0048", "0048"], r"^--folds: expected at least two distinct folds"),
])
def test_bad_fold_lists_are_refused(bench, folds, message):
    with pytest.raises(InputError, match=message):
        bench.check_folds(folds)


def test_bad_arguments_exit_2_with_one_line(bench, capsys):
    with pytest.raises(SystemExit) as e:
        bench.parse_args(["--folds", "0048"])
    assert e.value.code == 2
    assert "--folds: expected at least two distinct folds" in capsys.readouterr().err.splitlines()[-1]


def test_a_root_without_the_folds_is_refused(bench, tmp_path, capsys):
    with pytest.raises(SystemExit) as e:
        bench.main(["--folds", "0001-50", "0048", "--kitti-root", str(tmp_path)])
    assert e.value.code == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("crossval.py: error: --kitti-root: fold '0001-50' needs a folder")


@pytest.mark.kitti
def test_an_empty_fold_is_refused(bench, kitti_root, tmp_path, monkeypatch):
    monkeypatch.setitem(bench.FOLDS, "0001-50", [("annotated", "annotated", ["drive_0001_sync_velodyne_raw_0000000999"])])
    with pytest.raises(InputError, match=r"^--folds: fold '0001-50' would be empty: no frame of "
                                         r"drive_0001_sync_velodyne_raw_0000000999"):
        bench.scored_sets(kitti_root, ["0001-50", "0048"])
