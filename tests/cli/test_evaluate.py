"""Tests of ``crfdepth evaluate`` (crfdepth.cli.evaluate) and of the KITTI submission export
(``crfdepth complete --input-dir`` on the test layout).

Real frames: the two ``val_selection_cropped`` frames of the shared KITTI data; the
expected numbers are computed in the test with :func:`crfdepth.metrics.depth_metrics`.
"""

from __future__ import annotations

import contextlib
import csv
import io
import json
import math
import os
import re
import shutil
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch

from crfdepth import cli
from crfdepth.api import complete_checked, complete_depth
from crfdepth.checkpoints import save_model
from crfdepth.data.factory import build_dataset
from crfdepth.data.kitti import KittiValSelection
from crfdepth.io.kitti import read_depth_png
from crfdepth.metrics import METRICS, UNCERTAINTY_METRICS, UNITS, average_metrics, depth_metrics, uncertainty_metrics
from crfdepth.model import CRFDepth
from crfdepth.runs.resume import RUN_RECORD

COMMANDS = ("crfdepth.cli.complete", "crfdepth.cli.evaluate")


def test_evaluate_is_registered():
    assert "crfdepth.cli.evaluate" in cli._COMMANDS


def _run(argv: list) -> tuple[int, str, str]:
    """(exit status, stdout, stderr) of ``crfdepth`` with ``argv``, in this process, with only
    complete and evaluate registered (another sub-command's import cannot fail these tests)."""
    out, err = io.StringIO(), io.StringIO()
    with pytest.MonkeyPatch.context() as mp, contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        mp.setattr(cli, "_COMMANDS", COMMANDS)
        try:
            code = cli.main([str(a) for a in argv])
        except SystemExit as exc:  # argparse usage errors
            code = exc.code
    return code, out.getvalue(), err.getvalue()


def _printed(stdout: str, label: str) -> float:
    match = re.search(rf"^\s+{re.escape(label)}\s+([0-9.]+)", stdout, re.MULTILINE)
    assert match, f"no {label} line in:\n{stdout}"
    return float(match.group(1))


def _read_csv(path: Path) -> list[dict[str, str]]:
    with open(path, newline="") as handle:
        return list(csv.DictReader(handle))


@pytest.fixture(scope="module")
def val_dir(kitti_root) -> Path:
    return kitti_root / "depth_selection" / "val_selection_cropped"


@pytest.fixture(scope="module")
def expected(val_dir) -> dict:
    """Per-frame metrics of the default (shipped KITTI) weights on the two frames, computed directly."""
    dataset = KittiValSelection(val_dir)
    model = CRFDepth.from_pretrained()
    per_frame, depths = [], {}
    with torch.no_grad():
        for i in range(len(dataset)):
            s = dataset[i]
            depth = model(s.image[None], s.sparse[None], s.K[None]).depth
            per_frame.append(depth_metrics(depth, s.target[None]))
            depths[s.name] = depth[0, 0].double().numpy()
    stacked = {k: torch.cat([m[k] for m in per_frame]) for k in per_frame[0]}
    return {"names": dataset.names, "per_frame": stacked, "mean": average_metrics(stacked), "depth": depths}


@pytest.fixture(scope="module")
def default_run(val_dir, tmp_path_factory) -> dict:
    """One ``crfdepth evaluate --save-png`` run with the default weights."""
    out_dir = tmp_path_factory.mktemp("eval") / "evaluation"
    code, stdout, stderr = _run(["evaluate", "--layout", "val_selection", "--data", val_dir,
                                 "--out-dir", out_dir, "--save-png", "--quiet"])
    assert code == 0, stderr
    return {"out_dir": out_dir, "stdout": stdout}


# --------------------------------------------------------------------------- real frames


@pytest.mark.kitti
def test_printed_metrics_match_depth_metrics(default_run, expected):
    stdout = default_run["stdout"]
    mean = expected["mean"]
    assert abs(_printed(stdout, "RMSE") - mean["rmse"]) < 0.1  # mm
    assert abs(_printed(stdout, "MAE") - mean["mae"]) < 0.1  # mm
    assert abs(_printed(stdout, "iRMSE") - mean["irmse"]) < 0.01  # 1/km
    assert abs(_printed(stdout, "d<1.25") - mean["delta1"]) < 1e-4
    assert 500 < mean["rmse"] < 3000  # a sane completion of a real frame
    assert "mean over 2 frame(s)" in stdout and f"{mean['pixels']:,} ground-truth pixels" in stdout
    assert re.search(r"RMSE\s+[0-9.]+\s+mm", stdout) and re.search(r"iRMSE\s+[0-9.]+\s+1/km", stdout)


@pytest.mark.kitti
def test_csv_has_one_row_per_frame(default_run, expected):
    rows = _read_csv(default_run["out_dir"] / "per_frame.csv")
    assert len(rows) == 2 and list(rows[0]) == ["name", *METRICS, "pixels"]
    assert [r["name"] for r in rows] == expected["names"]
    for i, row in enumerate(rows):
        for m in METRICS:
            assert float(row[m]) == pytest.approx(float(expected["per_frame"][m][i]), rel=1e-6, abs=1e-9)
        assert int(row["pixels"]) == int(expected["per_frame"]["pixels"][i])


@pytest.mark.kitti
def test_summary_json(default_run, expected, val_dir):
    summary = json.loads((default_run["out_dir"] / "summary.json").read_text())
    for m in METRICS:
        assert summary["metrics"][m] == pytest.approx(expected["mean"][m], rel=1e-6)
    assert summary["units"]["rmse"] == "mm" and summary["units"]["irmse"] == "1/km"
    assert summary["frames"] == 2 and summary["pixels"] == expected["mean"]["pixels"]
    assert summary["checkpoint"] is None and summary["shipped_weights"] == "kitti"
    assert summary["layout"] == "val_selection"
    assert summary["data_root"] == str(val_dir.resolve())
    assert summary["model_config"] == CRFDepth.from_pretrained().config
    with torch.no_grad():
        assert summary["weights"] == pytest.approx(CRFDepth.from_pretrained().weights())
    assert summary["dtype"] == "float32" and summary["skipped"] == []
    # Written atomically: no temporary file left.
    assert sorted(p.name for p in default_run["out_dir"].iterdir()) == ["depth", "per_frame.csv", "summary.json"]


@pytest.mark.kitti
def test_save_png_writes_the_predictions_named_like_the_frames(default_run, expected):
    pngs = sorted((default_run["out_dir"] / "depth").iterdir())
    assert [p.name for p in pngs] == [f"{n}.png" for n in expected["names"]]
    for png in pngs:
        raw = cv2.imread(str(png), cv2.IMREAD_UNCHANGED)
        assert raw.dtype == np.uint16 and raw.shape == (352, 1216) and raw.min() > 0
        np.testing.assert_allclose(read_depth_png(png), expected["depth"][png.stem], atol=1 / 512 + 1e-6)


@pytest.mark.kitti
def test_changed_weights_change_the_numbers(val_dir, tmp_path, default_run, expected):
    model = CRFDepth()
    with torch.no_grad():
        model.raw_beta += 4.0  # much stronger colour smoothing
        model.log_sigma_d += 1.5  # across colour edges too
        model.log_confidence -= 3.0  # weaker data term
    save_model(model, tmp_path / "changed.pt")
    code, stdout, stderr = _run(["evaluate", "--layout", "val_selection", "--data", val_dir, "--quiet",
                                 "--checkpoint", tmp_path / "changed.pt", "--out-dir", tmp_path / "out"])
    assert code == 0, stderr
    summary = json.loads((tmp_path / "out" / "summary.json").read_text())
    assert abs(summary["metrics"]["rmse"] - expected["mean"]["rmse"]) > 10.0  # mm
    assert abs(_printed(stdout, "RMSE") - summary["metrics"]["rmse"]) < 0.01
    assert summary["checkpoint"] == str((tmp_path / "changed.pt").resolve())
    with torch.no_grad():
        assert summary["weights"] == pytest.approx(model.weights())
        assert summary["weights"]["beta"] > 0.95


@pytest.mark.kitti
def test_limit_and_batch_size(val_dir, tmp_path, expected):
    code, _, stderr = _run(["evaluate", "--layout", "val_selection", "--data", val_dir, "--quiet",
                            "--limit", 1, "--out-dir", tmp_path / "one"])
    assert code == 0, stderr
    rows = _read_csv(tmp_path / "one" / "per_frame.csv")
    assert [r["name"] for r in rows] == expected["names"][:1]
    assert float(rows[0]["rmse"]) == pytest.approx(float(expected["per_frame"]["rmse"][0]), rel=1e-6)

    code, _, stderr = _run(["evaluate", "--layout", "val_selection", "--data", val_dir, "--quiet",
                            "--batch-size", 2, "--out-dir", tmp_path / "two"])
    assert code == 0, stderr
    summary = json.loads((tmp_path / "two" / "summary.json").read_text())
    assert summary["frames"] == 2
    assert summary["metrics"]["rmse"] == pytest.approx(expected["mean"]["rmse"], abs=0.1)  # mm


# --------------------------------------------------------------------------- synthetic


def test_synthetic_layout_needs_no_data_folder(tmp_path):
    code, stdout, stderr = _run(["evaluate", "--layout", "synthetic", "--limit", 1, "--seed", 3,
                                 "--mode", "pixel", "--out-dir", tmp_path / "out"])
    assert code == 0, stderr
    rows = _read_csv(tmp_path / "out" / "per_frame.csv")
    assert [r["name"] for r in rows] == ["synthetic-seed3"]
    assert list(rows[0]) == ["name", *METRICS, "pixels"]  # without --std: no uncertainty columns
    summary = json.loads((tmp_path / "out" / "summary.json").read_text())
    assert "uncertainty" not in summary and summary["units"] == UNITS and "AUSE" not in stdout
    assert summary["data_root"] is None and summary["model_config"]["structure"]["mode"] == "pixel"
    assert summary["dataset_options"] == {"seed": 3}
    assert 0 < summary["metrics"]["rmse"] < 3000 and summary["metrics"]["delta1"] > 0.9
    assert abs(_printed(stdout, "RMSE") - summary["metrics"]["rmse"]) < 0.01


# A model whose std is cheap: superpixel mode without the pixel refinement has at most
# 1,000 nodes, so the std is exact (dense Cholesky) and adds little time.
FAST_STD_MODEL = ["--mode", "superpixel", "--superpixels", 800, "--no-refine"]


@pytest.fixture(scope="module")
def std_run(tmp_path_factory) -> dict:
    """``crfdepth evaluate --std`` on two synthetic scenes in one batch of two."""
    out_dir = tmp_path_factory.mktemp("eval-std") / "out"
    code, stdout, stderr = _run(["evaluate", "--layout", "synthetic", "--limit", 2, "--batch-size", 2, "--std",
                                 *FAST_STD_MODEL, "--quiet", "--out-dir", out_dir])
    assert code == 0, stderr
    return {"out_dir": out_dir, "stdout": stdout, "rows": _read_csv(out_dir / "per_frame.csv"),
            "summary": json.loads((out_dir / "summary.json").read_text())}


def test_std_adds_uncertainty_columns_in_range(std_run):
    rows = std_run["rows"]
    assert [r["name"] for r in rows] == ["synthetic-seed0", "synthetic-seed1"]
    assert list(rows[0]) == ["name", *METRICS, "pixels", *UNCERTAINTY_METRICS]
    for row in rows:
        u = {m: float(row[m]) for m in UNCERTAINTY_METRICS}
        assert all(math.isfinite(v) for v in u.values()), row
        assert 0 <= u["ause"] < u["ause_random"] and 0 <= u["ause_ratio"] < 1  # better than random
        assert -1 <= u["spearman"] <= 1
        assert 0 <= u["coverage_1"] <= u["coverage_2"] <= 1
        # AUSE in mm: the random AUSE is below the RMSE (mm) of the frame, and of its order.
        assert 0.1 * float(row["rmse"]) < u["ause_random"] < float(row["rmse"])


def test_std_summary_is_the_mean_of_the_csv(std_run):
    rows, summary = std_run["rows"], std_run["summary"]
    block = summary["uncertainty"]
    assert list(block) == list(UNCERTAINTY_METRICS)
    for m in UNCERTAINTY_METRICS:
        if m != "ause_ratio":
            assert block[m] == pytest.approx(np.mean([float(r[m]) for r in rows]), rel=1e-12), m
    # The ratio of the mean areas, not the mean of the ratios.
    assert block["ause_ratio"] == pytest.approx(block["ause"] / block["ause_random"], rel=1e-12)
    assert summary["units"]["ause"] == "mm" and summary["units"]["nll"].startswith("nats")
    assert summary["frames"] == 2 and summary["metrics"]["rmse"] > 0


def test_std_table_on_stdout(std_run):
    stdout, block = std_run["stdout"], std_run["summary"]["uncertainty"]
    assert re.search(r"^\s+AUSE\s+[0-9.]+\s+mm \([0-9.]+ x random", stdout, re.MULTILINE), stdout
    assert abs(_printed(stdout, "AUSE") - block["ause"]) < 0.01  # mm
    assert abs(_printed(stdout, "within 1 std") - block["coverage_1"]) < 1e-4
    spearman = re.search(r"^\s+Spearman\(std, \|err\|\)\s+(-?[0-9.]+)", stdout, re.MULTILINE)
    assert spearman and abs(float(spearman.group(1)) - block["spearman"]) < 1e-4
    assert re.search(r"NLL Gaussian\s+-?[0-9.]+\s+nats", stdout)
    # After the depth metrics.
    assert stdout.index("d<1.25") < stdout.index("AUSE")


def test_std_metrics_match_a_direct_computation(std_run):
    """Frame 2 (the second of the batch) recomputed through the library: errors and std in
    metres, AUSE in mm."""
    sample = build_dataset("synthetic", None)[1]
    model = CRFDepth.from_pretrained(mode="superpixel", superpixels=800, refine=False)
    depth, std = complete_depth(sample.image, sparse=sample.sparse[0], K=sample.K, model=model, return_std=True)
    valid = sample.target[0] > 0
    error = (depth.double() - sample.target[0].double())[valid].numpy()
    expected = uncertainty_metrics(error, std.double()[valid].numpy())
    row = std_run["rows"][1]
    assert float(row["ause"]) == pytest.approx(1000 * expected["ause"], rel=1e-4)
    assert float(row["ause_random"]) == pytest.approx(1000 * expected["ause_random"], rel=1e-4)
    for m in ("ause_ratio", "spearman", "coverage_1", "coverage_2", "nll", "nll_laplace"):
        assert float(row[m]) == pytest.approx(expected[m], rel=1e-4, abs=1e-6), m


def test_std_without_a_std_from_the_model_exits_2_and_writes_nothing(tmp_path, monkeypatch):
    def no_std(model, image, sparse, K, *, return_std):
        depth, _ = complete_checked(model, image, sparse, K, return_std=False)
        return depth, None

    monkeypatch.setattr("crfdepth.runs.evaluation.complete_checked", no_std)
    code, stdout, stderr = _run(["evaluate", "--layout", "synthetic", "--limit", 1, "--std", *FAST_STD_MODEL,
                                 "--out-dir", tmp_path / "out"])
    assert code == 2 and stdout.startswith("model: kitti weights, superpixel graph (800 segments)")
    assert stdout.count("\n") == 1  # the model line of the started run, nothing else
    assert "--std: expected the model to return a standard deviation" in stderr and stderr.count("\n") == 1
    assert not (tmp_path / "out").exists()


def _lightning_ckpt(path: Path, **crf) -> CRFDepth:
    """A hand-made checkpoint shaped like the trainer's (CRF as ``self.model``)."""
    model = CRFDepth(**crf)
    with torch.no_grad():
        model.raw_beta += 1.0
    torch.save({"epoch": 1, "state_dict": {f"model.{k}": v for k, v in model.state_dict().items()},
                "hyper_parameters": {"crf": model.config}}, path)
    return model


def test_checkpoint_configuration_and_cli_overrides(tmp_path):
    """The checkpoint's configuration defines the model; explicit model options override it."""
    model = _lightning_ckpt(tmp_path / "last.ckpt", mode="pixel", potentials=("colour", "normal"))
    argv = ["evaluate", "--layout", "synthetic", "--limit", 1, "--checkpoint", tmp_path / "last.ckpt"]
    code, _, stderr = _run([*argv, "--out-dir", tmp_path / "as-stored"])
    assert code == 0, stderr
    stored = json.loads((tmp_path / "as-stored" / "summary.json").read_text())
    assert stored["model_config"] == model.config  # mode pixel, colour + normal

    code, _, stderr = _run([*argv, "--mode", "superpixel", "--superpixels", 800, "--no-refine",
                            "--out-dir", tmp_path / "overridden"])
    assert code == 0, stderr
    overridden = json.loads((tmp_path / "overridden" / "summary.json").read_text())
    assert overridden["model_config"] == CRFDepth(model.config, mode="superpixel", superpixels=800,
                                                  refine=False).config
    assert overridden["weights"] == pytest.approx(stored["weights"])  # the checkpoint's weights
    assert overridden["metrics"]["rmse"] != pytest.approx(stored["metrics"]["rmse"], abs=1.0)


def test_evaluate_works_without_lightning(tmp_path):
    """``lightning`` and ``pytorch_lightning`` made unimportable before crfdepth is imported."""
    _lightning_ckpt(tmp_path / "last.ckpt", mode="pixel")
    script = (
        "import sys\n"
        "sys.modules['lightning'] = None\n"  # any `import lightning` now raises ImportError
        "sys.modules['pytorch_lightning'] = None\n"
        "try:\n"
        "    import lightning\n"
        "    sys.exit(99)\n"
        "except ImportError:\n"
        "    pass\n"
        "from crfdepth.cli import main\n"
        "sys.exit(main(['evaluate', '--layout', 'synthetic', '--limit', '1', '--checkpoint', 'last.ckpt']))\n"
    )
    done = subprocess.run([sys.executable, "-c", script], cwd=tmp_path, capture_output=True, text=True,
                          timeout=120, env={**os.environ, "OMP_NUM_THREADS": "1"})
    assert done.returncode == 0, done.stdout + done.stderr
    summary = json.loads((tmp_path / "evaluation" / "summary.json").read_text())  # default --out-dir
    assert summary["frames"] == 1 and summary["model_config"]["structure"]["mode"] == "pixel"
    assert summary["checkpoint"] == str((tmp_path / "last.ckpt").resolve())
    assert "RMSE" in done.stdout


# --------------------------------------------------------------------------- bad input


def _fake_test_layout(val_dir: Path, root: Path, frames: int = 3) -> Path:
    """A ``test_depth_completion_anonymous`` folder: the val frames under anonymous names
    (``0000000000.png`` ...; the two val frames repeat), no ground truth."""
    folder = root / "test_depth_completion_anonymous"
    sources = sorted((val_dir / "velodyne_raw").glob("*.png"))
    for sub in ("image", "velodyne_raw", "intrinsics"):
        (folder / sub).mkdir(parents=True)
    for i in range(frames):
        sparse = sources[i % len(sources)]
        image_stem = sparse.stem.replace("_velodyne_raw_", "_image_", 1)
        name = f"{i:010d}"
        shutil.copy(sparse, folder / "velodyne_raw" / f"{name}.png")
        shutil.copy(val_dir / "image" / f"{image_stem}.png", folder / "image" / f"{name}.png")
        shutil.copy(val_dir / "intrinsics" / f"{image_stem}.txt", folder / "intrinsics" / f"{name}.txt")
    return folder


def _empty_val_layout(root: Path) -> Path:
    for sub in ("image", "velodyne_raw", "groundtruth_depth", "intrinsics"):
        (root / "empty" / sub).mkdir(parents=True)
    return root / "empty"


BAD_INPUT = {
    "missing data folder": (lambda val, tmp: ["--layout", "val_selection", "--data", tmp / "nowhere"],
                            ["dataset folder does not exist", "nowhere"]),
    "no data folder": (lambda val, tmp: ["--layout", "val_selection"], ["--data: a dataset folder is needed"]),
    "unknown layout": (lambda val, tmp: ["--layout", "kitti", "--data", val], ["got 'kitti'"]),
    "folder of another layout": (lambda val, tmp: ["--layout", "val_selection", "--data",
                                                   val.parents[1] / "depth_completion"],
                                 ["does not match the KittiValSelection layout"]),
    "layout with zero frames": (lambda val, tmp: ["--layout", "val_selection", "--data", _empty_val_layout(tmp)],
                                ["found no frames", "empty"]),
    "not a checkpoint": (lambda val, tmp: ["--layout", "val_selection", "--data", val, "--checkpoint",
                                           _text_file(tmp / "notes.ckpt")],
                         ["--checkpoint", "notes.ckpt", "is not a torch state dict"]),
    "missing checkpoint": (lambda val, tmp: ["--layout", "val_selection", "--data", val, "--checkpoint",
                                             tmp / "none.ckpt"], ["--checkpoint", "none.ckpt"]),
    "test layout": (lambda val, tmp: ["--layout", "test_selection", "--data", _fake_test_layout(val, tmp, 1)],
                    ["no ground truth", "nothing to evaluate", "crfdepth complete --input-dir"]),
    "option of another layout": (lambda val, tmp: ["--layout", "val_selection", "--data", val, "--split", "val"],
                                 ["--split: only applies to --layout depth_completion"]),
    "bad holdout fraction": (lambda val, tmp: ["--layout", "raw", "--data", val, "--holdout-fraction", "1.5"],
                             ["expected a number in (0, 1)"]),
    "out-dir is a file": (lambda val, tmp: ["--layout", "synthetic", "--out-dir", _text_file(tmp / "out")],
                          ["--out-dir: expected a folder, got a file"]),
}


def _text_file(path: Path) -> Path:
    path.write_text("not a checkpoint\n")
    return path


@pytest.mark.kitti
@pytest.mark.parametrize("case", list(BAD_INPUT))
def test_bad_input_exits_2_and_writes_nothing(val_dir, tmp_path, case):
    make, words = BAD_INPUT[case]
    argv = make(val_dir, tmp_path)
    out_dir = tmp_path / "results"
    if "--out-dir" not in argv:
        argv += ["--out-dir", out_dir]
    code, stdout, stderr = _run(["evaluate", *argv])
    assert code == 2 and stdout == ""
    assert all(w in stderr for w in words), stderr
    assert stderr.count("\n") == 1 or "usage:" in stderr  # one line (argparse adds its usage)
    assert not out_dir.exists()
    assert not list(tmp_path.rglob("*.csv")) and not list(tmp_path.rglob("*.json"))


# --------------------------------------------------------------------------- submission export


@pytest.mark.kitti
def test_complete_exports_a_kitti_submission(val_dir, tmp_path):
    """``crfdepth complete --input-dir`` on the test layout writes one uint16 PNG per input,
    with the input's name and size. The real benchmark folder holds 1000 frames
    (``0000000000.png`` ... ``0000000999.png``); three are enough to check the naming."""
    folder = _fake_test_layout(val_dir, tmp_path, frames=3)
    out = tmp_path / "submission"
    code, _, stderr = _run(["complete", "--input-dir", folder, "--out-dir", out,
                            "--no-refine", "--potentials", "colour", "--quiet"])
    assert code == 0, stderr
    # what the KITTI server takes (zip *.png leaves hidden files out): the PNGs, nothing else; hidden, the run
    # record alone (no lock, no temporary file)
    names = sorted(p.name for p in out.iterdir())
    assert [n for n in names if not n.startswith(".")] == ["0000000000.png", "0000000001.png", "0000000002.png"]
    assert [n for n in names if n.startswith(".")] == [RUN_RECORD]
    for png in sorted(out.glob("*.png")):
        raw = cv2.imread(str(png), cv2.IMREAD_UNCHANGED)
        sparse = read_depth_png(folder / "velodyne_raw" / png.name)
        assert raw.dtype == np.uint16 and raw.shape == sparse.shape == (352, 1216)
        assert raw.min() > 0  # dense: every pixel has a depth
        hits = sparse > 0  # the completion agrees with the LiDAR where there is LiDAR
        assert np.median(np.abs(raw[hits] / 256.0 - sparse[hits])) < 0.5
    # Frames 0 and 2 are the same input: the same output.
    np.testing.assert_array_equal(read_depth_png(out / "0000000000.png"), read_depth_png(out / "0000000002.png"))
