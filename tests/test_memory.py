"""Up-front memory estimates and refusals (crfdepth.memory), and the speed benchmark's measurements of them."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest
import torch

from crfdepth.data.synthetic import make_scene
from crfdepth.errors import InputError
from crfdepth.memory import BYTES_PER_PIXEL, OVERHEAD_BYTES, check_memory, device_memory, estimate_bytes
from crfdepth.model import CRFDepth

SCRIPT = Path(__file__).resolve().parents[1] / "benchmarks" / "speed.py"


def test_estimate_is_linear_in_pixels_and_doubles_in_float64():
    one = estimate_bytes("pixel", 1_000_000, True, "predictive") - OVERHEAD_BYTES
    assert estimate_bytes("pixel", 2_000_000, True, "predictive") - OVERHEAD_BYTES == 2 * one
    assert one == 1_000_000 * BYTES_PER_PIXEL[("pixel", True)]
    assert estimate_bytes("pixel", 1_000_000, True, "predictive", element_size=8) - OVERHEAD_BYTES == 2 * one
    # the posterior std's sample solves have their own budget on top
    assert estimate_bytes("pixel", 1_000_000, True, "posterior") > estimate_bytes("pixel", 1_000_000, True, "predictive")


def test_refusal_names_the_limit_and_states_the_estimate():
    with pytest.raises(InputError) as err:
        check_memory("pixel", 8, 3000, 4000, True, "predictive", torch.float32, torch.device("cpu"), 8.0)
    message = str(err.value)
    assert "memory_limit_gb" in message and "8 frame(s) of 4000x3000" in message
    estimate = estimate_bytes("pixel", 8 * 3000 * 4000, True, "predictive")
    assert f"about {estimate / 1e9:.1f} GB" in message
    assert check_memory("pixel", 1, 352, 1216, True, "predictive", torch.float32, torch.device("cpu"), 8.0) < 8e9


def test_device_memory_is_this_machines():
    total = device_memory(torch.device("cpu"))
    assert total is not None and total > 2**30


def test_model_refuses_before_allocating_and_checks_the_argument():
    scene = make_scene(0, height=64, width=160).to_tensors()
    model = CRFDepth(mode="pixel", memory_limit_gb=0.01)  # below the fixed overhead
    with pytest.raises(InputError, match="memory_limit_gb"):
        model(scene["image"][None], scene["sparse"][None], scene["K"])
    out = CRFDepth(mode="pixel", memory_limit_gb=1.0)(scene["image"][None], scene["sparse"][None], scene["K"])
    assert out.depth.shape == (1, 1, 64, 160)
    for bad in (0, -1.0, "8", float("nan"), True):
        with pytest.raises(InputError, match="memory_limit_gb"):
            CRFDepth(memory_limit_gb=bad)


@pytest.mark.slow
def test_speed_benchmark_measures_every_configuration_within_the_estimates(tmp_path):
    """The benchmark on a small 'large' frame: every row timed and measured, peaks under the estimates."""
    result = subprocess.run([sys.executable, str(SCRIPT), "--repeats", "1", "--large", "640x480"],
                            capture_output=True, text=True, timeout=1200)
    assert result.returncode == 0, result.stderr[-2000:]
    report = json.loads(result.stdout.strip().splitlines()[-1])
    rows = report["rows"]
    assert {(r["config"], r["std"]) for r in rows} == {
        (c, s) for c in ("default", "pixel", "superpixel", "no-refine") for s in (False, True)} | {
        ("ip-basic", False), ("ip-basic-opencv", False)}
    assert len(rows) == 20  # ten at 1216x352, ten at 640x480
    for r in rows:
        assert r["seconds"] > 0 and r["fps"] > 0 and r["peak_bytes"] > 0, r
        if r["config"] not in ("ip-basic", "ip-basic-opencv"):
            mode = "pixel" if r["config"] in ("default", "pixel") else "superpixel"
            pixels = r["size"][0] * r["size"][1]
            assert r["peak_bytes"] <= estimate_bytes(mode, pixels, r["std"], "predictive"), r
            assert r["iterations"] and all(i > 0 for i in r["iterations"])
    assert set(report["verdicts"]) >= {"default_ms", "default_vs_classical", "moonshot_ms", "large_peak_gb"}
    assert "default_ms" in result.stdout and "met" in result.stdout.lower()


def test_speed_benchmark_times_every_grid_solve_of_a_forward():
    """--solvers captures the default model's two grid solves and the superpixel refinement (it captured
    none after the solves moved to crfdepth.inference) and times each with every preconditioner."""
    from tests.benchmark_scripts import load_benchmark

    speed = load_benchmark("speed")
    t = make_scene(0, height=96, width=320).to_tensors()
    frame = dict(image=t["image"][None].float(), sparse=t["sparse"][None].float(), K=t["K"].float(), name="s")
    rows = speed.measure_solvers(frame, "cpu", repeats=1)
    assert [r["solve"] for r in rows] == ["default solve 1", "default solve 2", "superpixel refinement"]
    for r in rows:
        assert r["size"] == [96, 320]
        for pre in ("jacobi", "multigrid", "auto"):
            assert r[pre]["iterations"] > 0 and r[pre]["seconds"] > 0, r
