"""benchmarks/train_step.py: one training step of the shipped recipe timed on a small synthetic crop, the crop's
intrinsics, the trainer's model, and its refusals."""

from __future__ import annotations

import json

import pytest
import torch

from crfdepth.data.synthetic import make_scene
from crfdepth.linalg.diagnostics import GRAD_RTOL
from tests.benchmark_scripts import load_benchmark

KEYS = {"frame", "crop", "threads", "forward_ms", "backward_ms", "total_ms", "iterations", "rtol", "loss_m", "repeats"}


@pytest.fixture(scope="module")
def bench():
    return load_benchmark("train_step")


@pytest.fixture
def keep_threads():
    """main sets torch's thread count: give the other tests theirs back."""
    threads = torch.get_num_threads()
    yield
    torch.set_num_threads(threads)


def test_a_step_on_a_synthetic_crop_reports_forward_and_backward(bench, tmp_path, capsys, keep_threads):
    # an empty --kitti-root: the synthetic street, cropped to a small bottom-centre window
    assert bench.main(["--kitti-root", str(tmp_path), "--crop", "64", "160", "--repeats", "2", "--threads", "2"]) == 0
    out = capsys.readouterr().out.splitlines()
    assert out[0].startswith("note: no KITTI frame under")
    result = json.loads(out[-1])
    assert KEYS <= set(result)
    assert result["synthetic"] and result["crop"] == [64, 160] and result["threads"] == 2 and result["repeats"] == 2
    assert result["forward_ms"] > 0 and result["backward_ms"] > 0
    # each step's total is its forward plus its backward: the median total is at least either median
    assert result["total_ms"] >= max(result["forward_ms"], result["backward_ms"]) * (1 - 1e-9)
    low, high = result["total_spread_ms"]
    assert 0 < low <= result["total_ms"] <= high
    iterations = result["iterations"]
    # the shipped pixel grid with normals and distances: two solves, each with its adjoint solve in backward
    assert len(iterations["forward"]) == len(iterations["adjoint"]) == 2
    assert all(i > 0 for i in iterations["forward"] + iterations["adjoint"])
    # the training path: forward solves to the differentiated tolerance, adjoints to the model's rtol
    assert result["rtol"]["forward"] == [GRAD_RTOL] * 2 and result["rtol"]["adjoint"] == [1e-5] * 2
    assert result["converged"] and result["loss_m"] > 0


def test_the_crop_is_the_bottom_centre_window_with_its_intrinsics(bench, tmp_path):
    samples, note = bench.load_samples(tmp_path, (320, 896))
    scene = make_scene(0).to_tensors()
    assert note is not None and len(samples) == 1
    s = samples[0]
    top, left = 352 - 320, (1216 - 896) // 2
    assert s.image.shape == (3, 320, 896) and s.sparse.shape == s.target.shape == (1, 320, 896)
    assert torch.equal(s.sparse, scene["sparse"][:, top:, left:left + 896])
    expected = scene["K"].clone()
    expected[0, 2] -= left
    expected[1, 2] -= top
    assert torch.equal(s.K, expected)


def test_the_model_is_the_trainers(bench):
    model = bench.training_model()
    assert model.training
    trained = {n for n, p in model.named_parameters() if p.requires_grad}
    # what CRFDepthModule(loss="l1", nll_weight=0) trains of the shipped model: the potentials and the gate
    assert {"raw_alpha", "log_confidence", "log_gate_threshold"} <= trained
    assert not any(n.startswith("std_head") or n in ("log_std_scale", "log_refine_prior") for n in trained)
    assert model.solve_settings.rtol == 1e-5


def test_a_crop_larger_than_the_frame_is_one_line(bench, tmp_path, capsys, keep_threads):
    assert bench.sa.run_script(bench.main, "train_step.py", ["--kitti-root", str(tmp_path), "--crop", "400", "100"]) == 2
    err = capsys.readouterr().err.splitlines()
    assert err == ["train_step.py: error: --crop: expected HEIGHT WIDTH within the frame's 352 x 1216 (HxW), got 400 100"]


@pytest.mark.parametrize("args, message", [
    (["--repeats", "0"], "--repeats: expected an integer in [1, 2147483647], got '0'"),
    (["--threads", "-1"], "--threads: expected an integer in [1, 1024], got '-1'"),
    (["--crop", "4", "100"], "--crop: expected an integer in [8, 4096] (pixels), got '4'"),
    (["--crop", "64"], "--crop: expected 2 value(s), got fewer"),
    (["--kitti-root", "/no/such/folder"], "--kitti-root: expected the KITTI sample folder, got '/no/such/folder'"),
])
def test_a_bad_option_is_one_line(bench, args, message, capsys):
    with pytest.raises(SystemExit) as info:
        bench.main(args)
    err = capsys.readouterr().err.splitlines()
    assert info.value.code == 2 and len(err) == 1 and err[0].startswith(f"train_step.py: error: {message}"), err


@pytest.mark.kitti
def test_the_official_frame_is_cropped_as_the_recipe(bench, kitti_root):
    samples, note = bench.load_samples(kitti_root, bench.RECIPE_CROP)
    s = samples[0]
    assert note is None and s.name.startswith("2011_09_26_drive_0001_sync_velodyne_raw_0000000005")
    assert s.image.shape[-2:] == (320, 896) and bool((s.target > 0).any())
    assert s.K[0, 2].item() == pytest.approx(596.5593 - 160, abs=1e-3)
    assert s.K[1, 2].item() == pytest.approx(149.8540 - 32, abs=1e-3)
