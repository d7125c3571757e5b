"""benchmarks/converged.py: the shipped model's depth against its float64, tightly converged solution, on a small
synthetic crop; the differences on hand-made depths; the reference against itself; and its refusals."""

from __future__ import annotations

import json

import pytest
import torch

from crfdepth.model import CRFDepth
from tests.benchmark_scripts import load_benchmark

DIFF_KEYS = ("max_m", "p99_m", "over_5cm", "gt_max_m", "gt_p99_m", "gt_over_5cm")


@pytest.fixture(scope="module")
def bench():
    return load_benchmark("converged")


@pytest.fixture
def keep_threads():
    """main sets torch's thread count: give the other tests theirs back."""
    threads = torch.get_num_threads()
    yield
    torch.set_num_threads(threads)


@pytest.fixture(scope="module")
def small(bench, tmp_path_factory):
    """The synthetic street's bottom-centre 64 x 192 window (no KITTI folder given)."""
    samples, note = bench.load_samples(tmp_path_factory.mktemp("no_kitti"), (64, 192))
    assert note is not None and bool((samples[0].target > 0).any()) and bool((samples[0].sparse > 0).any())
    return samples[0]


def test_the_run_on_a_synthetic_crop(bench, tmp_path, capsys, keep_threads):
    assert bench.main(["--kitti-root", str(tmp_path), "--crop", "64", "192", "--threads", "2"]) == 0
    out = capsys.readouterr().out.splitlines()
    assert out[0].startswith("note: no KITTI frame under")
    result = json.loads(out[-1])
    assert result["synthetic"] and result["crop"] == [64, 192] and result["rtol"] == 1e-10
    assert result["shipped_rtol"] == 1e-5 and len(result["frames"]) == 1
    row = result["frames"][0]
    assert set(DIFF_KEYS) | {"rmse_mm", "reference_rmse_mm", "reference_error_m", "default", "reference"} <= set(row)
    assert row["max_m"] >= row["p99_m"] >= 0 and row["gt_max_m"] >= row["gt_p99_m"] >= 0
    assert 0 <= row["over_5cm"] <= 1 and 0 <= row["gt_over_5cm"] <= 1 and row["gt_pixels"] > 0
    assert row["gt_max_m"] <= row["max_m"]  # the ground-truth pixels are some of all the pixels
    assert row["rmse_mm"] > 0 and row["reference_rmse_mm"] > 0
    reference = row["reference"]
    assert reference["dtype"] == "float64" and reference["rtol"] == 1e-10 and reference["converged"]
    assert all(r <= 1e-10 for r in reference["rel_residual"]) and all(i > 0 for i in reference["iterations"])
    assert row["default"]["dtype"] == "float32" and row["default"]["rtol"] == 1e-5
    assert row["reference_error_m"] < 1e-3  # the reference at 1e-10 against one at 1e-12


def test_differences_on_hand_made_depths(bench):
    reference = torch.full((1, 1, 10, 10), 10.0, dtype=torch.float64)
    depth = reference.clone().float()
    depth[0, 0, 0, :10] += torch.arange(10, dtype=torch.float32) * 0.02  # 0 .. 0.18 m off along the first row
    target = torch.zeros(1, 1, 10, 10)
    target[0, 0, 0, :2] = 9.0  # ground truth at the pixels 0 and 0.02 m off
    d = bench.differences(depth, reference, target)
    assert d["max_m"] == pytest.approx(0.18, abs=1e-5)
    assert d["over_5cm"] == pytest.approx(7 / 100)  # 0.06 .. 0.18
    assert 0.1 < d["p99_m"] <= d["max_m"]
    assert d["gt_max_m"] == pytest.approx(0.02, abs=1e-5) and d["gt_over_5cm"] == 0.0 and d["gt_pixels"] == 2
    none = bench.differences(depth, reference, torch.zeros_like(target))
    assert none["gt_max_m"] is None and none["gt_pixels"] == 0


def test_the_reference_equals_itself(bench, small, keep_threads):
    model = CRFDepth.from_pretrained("kitti")
    reference = bench.reference_model(model, 1e-10, 20000)
    first, infos, _ = bench.run(reference, small, torch.float64)
    second, _, _ = bench.run(bench.reference_model(model, 1e-10, 20000), small, torch.float64)
    assert first.dtype == torch.float64 and all(bool(i.converged.all()) for i in infos)
    d = bench.differences(first, second, small.target)
    assert d["max_m"] < 1e-6 and d["p99_m"] < 1e-6 and d["over_5cm"] == 0.0
    # the shipped float32 model itself: further from the reference than the reference from itself
    depth, _, _ = bench.run(model, small, torch.float32)
    assert bench.differences(depth, first, small.target)["max_m"] > d["max_m"]


def test_the_reference_is_the_same_model_in_float64(bench):
    model = CRFDepth.from_pretrained("kitti")
    reference = bench.reference_model(model, 1e-10, 20000)
    assert reference.solve_settings.rtol == 1e-10 and reference.solve_settings.max_iter == 20000
    assert model.solve_settings.rtol == 1e-5 and next(model.parameters()).dtype == torch.float32  # untouched
    assert {k: v for k, v in reference.config.items() if k != "solver"} == \
        {k: v for k, v in model.config.items() if k != "solver"}
    for (name, a), (_, b) in zip(model.state_dict().items(), reference.state_dict().items()):
        assert b.dtype == (torch.float64 if a.is_floating_point() else a.dtype)
        assert torch.equal(a.double() if a.is_floating_point() else a, b), name


def test_a_crop_larger_than_the_frame_is_one_line(bench, tmp_path, capsys, keep_threads):
    assert bench.sa.run_script(bench.main, "converged.py", ["--kitti-root", str(tmp_path), "--crop", "64", "2000"]) == 2
    err = capsys.readouterr().err.splitlines()
    assert err == ["converged.py: error: --crop: expected HEIGHT WIDTH within the frame's 352 x 1216 (HxW), got 64 2000"]


@pytest.mark.parametrize("args, message", [
    (["--rtol", "0"], "--rtol: expected a number in (0, 1) (the reference's relative residual), got '0'"),
    (["--rtol", "nan"], "--rtol: expected a number in (0, 1) (the reference's relative residual), got 'nan'"),
    (["--max-iter", "0"], "--max-iter: expected an integer in [1, 2147483647], got '0'"),
    (["--threads", "0"], "--threads: expected an integer in [1, 1024], got '0'"),
    (["--crop", "64", "x"], "--crop: expected an integer in [8, 4096] (pixels), got 'x'"),
    (["--bogus"], "--bogus: expected an option of this script (--help lists them), got an unknown one"),
])
def test_a_bad_option_is_one_line(bench, args, message, capsys):
    with pytest.raises(SystemExit) as info:
        bench.main(args)
    err = capsys.readouterr().err.splitlines()
    assert info.value.code == 2 and len(err) == 1 and err[0].startswith(f"converged.py: error: {message}"), err


def test_a_file_as_the_kitti_root_is_refused(bench, tmp_path, capsys):
    a_file = tmp_path / "a_file"
    a_file.write_text("x")
    with pytest.raises(SystemExit) as info:
        bench.main(["--kitti-root", str(a_file)])
    err = capsys.readouterr().err.splitlines()
    assert info.value.code == 2
    assert err == [f"converged.py: error: --kitti-root: expected the KITTI sample folder, got '{a_file}' (which is a file)"]
