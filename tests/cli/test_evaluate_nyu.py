"""Tests of ``crfdepth evaluate`` on NYU Depth v2 (``--layout nyu_sync / nyu_raw / nyu_h5``, ``--samples``,
``--seed``; crfdepth.cli.evaluate).

Real frames from ``../shared/data/nyu`` (the official test split's basement frames, the labeled crop); a small
synthetic folder in NYU's sync layout (tests/cli/rgbd_scenes.py) so that the options and errors are tested without
the shared data. The expected numbers are computed here from the dataset, the model and
:func:`crfdepth.metrics.depth_metrics`.
"""

from __future__ import annotations

import csv
import json
import math
import re
from pathlib import Path

import numpy as np
import pytest

from crfdepth.api import complete_batch
from crfdepth.checkpoints import load_pretrained
from crfdepth.data.factory import build_dataset
from crfdepth.metrics import depth_metrics
from tests.cli.frames import run
from tests.cli.rgbd_scenes import write_sync_folder

GATE_OFF = "occlusion gate off: registered depth has no see-through returns"


@pytest.fixture
def synth_sync(tmp_path) -> Path:
    """Two synthetic frames in NYU's sync layout (160x120; the protocol resizes them to 320x240)."""
    folder = tmp_path / "nyu" / "scene"
    write_sync_folder(folder, 2)
    return tmp_path / "nyu"


def _nyu_line(stdout: str) -> dict[str, float]:
    match = re.search(r"^NYU Depth v2 as papers report it: RMSE ([0-9.]+) m, REL ([0-9.]+), delta<1.25 ([0-9.]+)",
                      stdout, re.MULTILINE)
    assert match, stdout
    return dict(zip(("rmse_m", "rel", "delta1"), map(float, match.groups())))


def _expected(layout: str, root: Path, limit: int, **options) -> dict[str, float]:
    """The per-frame means computed here: the dataset's frames through the shipped weights with the gate off."""
    dataset = build_dataset(layout, root, **options)
    model = load_pretrained("kitti", gate=False).eval()
    rows = []
    for index in range(limit):
        sample = dataset[index]
        depth, _ = complete_batch(sample.image[None], sample.sparse[None], sample.K, model=model, return_std=False)
        rows.append({k: float(v[0]) for k, v in depth_metrics(depth, sample.target[None, 0]).items()})
    return {"rmse_m": np.mean([r["rmse"] for r in rows]) / 1000.0, "rel": np.mean([r["rel"] for r in rows]),
            "delta1": np.mean([r["delta1"] for r in rows])}


def test_real_nyu_sync_with_the_protocol(nyu_root, tmp_path):
    root = nyu_root / "official_test"
    out = tmp_path / "eval"
    code, stdout, err = run(["evaluate", "--layout", "nyu_sync", "--data", root, "--samples", "500", "--limit", "2",
                             "--out-dir", out])
    assert code == 0, err
    assert GATE_OFF in stdout and "(500 samples, seed 0)" in stdout
    printed = _nyu_line(stdout)
    summary = json.loads((out / "summary.json").read_text())
    expected = _expected("nyu_sync", root, 2, samples=500, seed=0)
    for key in ("rmse_m", "rel", "delta1"):
        assert summary["nyu"][key] == pytest.approx(expected[key], rel=1e-5), key
        assert printed[key] == pytest.approx(expected[key], abs=1e-4), key
    assert summary["nyu"]["rmse_m"] == pytest.approx(summary["metrics"]["rmse"] / 1000.0)
    assert summary["nyu"]["samples"] == 500 and summary["dataset_options"] == {"samples": 500}
    assert summary["model_config"]["gate"]["enabled"] is False
    assert 0.05 < summary["nyu"]["rmse_m"] < 0.6 and summary["nyu"]["delta1"] > 0.9  # measured: 0.29 m, 0.977
    with open(out / "per_frame.csv") as handle:
        assert [row["name"] for row in csv.DictReader(handle)] == ["basement_00000", "basement_00050"]


def test_real_nyu_raw_fills_the_raw_depth_against_the_filled_one(nyu_root, tmp_path):
    out = tmp_path / "eval"
    code, stdout, err = run(["evaluate", "--layout", "nyu_raw", "--data", nyu_root / "labeled_crop", "--out-dir", out,
                             "--quiet"])
    assert code == 0, err
    assert "(the stored input, no --samples)" in stdout
    summary = json.loads((out / "summary.json").read_text())
    assert summary["frames"] == 1 and summary["pixels"] == 560 * 425  # the filled depth is dense
    assert summary["nyu"]["samples"] is None
    expected = _expected("nyu_raw", nyu_root / "labeled_crop", 1)
    assert summary["nyu"]["rmse_m"] == pytest.approx(expected["rmse_m"], rel=1e-5)
    assert summary["nyu"]["delta1"] > 0.95  # measured: 0.992 (83% of the pixels are the raw depth itself)


def test_the_seed_decides_the_samples(synth_sync, tmp_path):
    def rmse(seed: str, out: str) -> list[str]:
        code, _, err = run(["evaluate", "--layout", "nyu_sync", "--data", synth_sync, "--samples", "200", "--seed",
                            seed, "--out-dir", tmp_path / out, "--quiet"])
        assert code == 0, err
        with open(tmp_path / out / "per_frame.csv") as handle:
            return [row["rmse"] for row in csv.DictReader(handle)]

    first, again, other = rmse("0", "a"), rmse("0", "b"), rmse("7", "c")
    assert first == again and first != other
    assert max(map(float, first)) < 400.0  # mm: the wall and box from 200 samples (measured: 246-269 mm)


@pytest.mark.parametrize("argv, words", [
    ([], ["--samples: required with --layout nyu_sync", "--samples 500"]),
    (["--samples", "60000"], ["--samples 60000: expected at most the", "valid pixel(s)", "frame 1 of 2"]),
    (["--samples", "0"], ["--samples: expected an integer in [1,"]),
])
def test_sync_samples_errors_name_samples(synth_sync, tmp_path, argv, words):
    out = tmp_path / "eval"
    code, _, err = run(["evaluate", "--layout", "nyu_sync", "--data", synth_sync, *argv, "--out-dir", out, "--quiet"])
    assert code == 2 and "Traceback" not in err and err.count("\n") == 1, err
    assert all(word in err for word in words), err
    assert not out.exists()  # nothing written, the folder not left behind


def test_options_of_other_layouts_are_refused(synth_sync, tmp_path, nyu_root):
    code, _, err = run(["evaluate", "--layout", "val_selection", "--data", synth_sync, "--samples", "500"])
    assert code == 2 and "--samples: only applies to --layout nyu_sync / nyu_raw / nyu_h5" in err
    code, _, err = run(["evaluate", "--layout", "nyu_raw", "--data", nyu_root / "labeled_crop", "--seed", "3",
                        "--out-dir", tmp_path / "e"])
    assert code == 2 and "--seed 3: applies with --samples" in err
    assert not (tmp_path / "e").exists()


def test_nyu_h5_with_the_protocol(tmp_path):
    h5py = pytest.importorskip("h5py")
    from tests.cli.rgbd_scenes import scene

    frame = scene(0)
    rgb = np.kron(frame.rgb.transpose(2, 0, 1), np.ones((1, 4, 4), np.uint8))  # 640x480, as the release
    depth = np.kron(frame.depth, np.ones((4, 4), np.float32))
    folder = tmp_path / "nyudepthv2" / "val" / "office"
    folder.mkdir(parents=True)
    with h5py.File(folder / "00001.h5", "w") as handle:
        handle["rgb"], handle["depth"] = rgb, depth
    out = tmp_path / "eval"
    code, stdout, err = run(["evaluate", "--layout", "nyu_h5", "--data", tmp_path / "nyudepthv2", "--split", "val",
                             "--samples", "300", "--out-dir", out, "--quiet"])
    assert code == 0, err
    summary = json.loads((out / "summary.json").read_text())
    assert summary["dataset_options"] == {"split": "val", "samples": 300}
    assert summary["pixels"] == 304 * 228  # the protocol's crop, every pixel with ground truth
    assert summary["nyu"]["rmse_m"] < 0.4 and summary["nyu"]["delta1"] > 0.9  # measured: 0.263 m
    assert math.isfinite(summary["nyu"]["rel"])
