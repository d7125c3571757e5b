"""Every benchmark script refuses a bad option in one line, ``<script>: error: --option: ...``, exit status 2,
before any work: no traceback, no usage block (benchmarks/script_args.py). The benchmarks themselves are not run."""

from __future__ import annotations

import subprocess
import sys

import pytest

from tests.benchmark_scripts import BENCHMARKS, load_benchmark

BIG = "99999999999999999999"


def _refused(name: str, args: list[str], capsys) -> list[str]:
    bench = load_benchmark(name)
    with pytest.raises(SystemExit) as info:
        bench.main(args)
    err = capsys.readouterr().err.splitlines()
    assert info.value.code == 2, err
    assert len(err) == 1 and "Traceback" not in err[0] and not err[0].startswith("usage:"), err
    return err


@pytest.mark.parametrize("name, args, first_line", [
    ("accuracy", ["--threads", "0"], "--threads: expected an integer in [1, 1024], got '0'"),
    ("accuracy", ["--max-frames", "-1"], "--max-frames: expected an integer in [1, 2147483647], got '-1'"),
    ("accuracy", ["--fit-epochs", BIG], f"--fit-epochs: expected an integer in [1, 2147483647], got '{BIG}'"),
    ("accuracy", ["--fractions", "nan"], "--fractions: expected a number in (0, 1] (share of the LiDAR points), got 'nan'"),
    ("accuracy", ["--fractions", "0"], "--fractions: expected a number in (0, 1] (share of the LiDAR points), got '0'"),
    ("accuracy", ["--device", "tpu"], "--device: expected cpu, cuda, cuda:K or mps, got 'tpu'"),
    ("accuracy", ["--protocols", "zz"], "--protocols: expected one of 'a', "),
    ("accuracy", ["--posterior-samples", "0"], "--posterior-samples: expected an integer in [1, 4096], got '0'"),
    ("crossval", ["--seed", BIG], f"--seed: expected an integer in [0, 4294967295] (a seed), got '{BIG}'"),
    ("crossval", ["--seed", "-1"], "--seed: expected an integer in [0, 4294967295] (a seed), got '-1'"),
    ("crossval", ["--workers", "-1"], "--workers: expected an integer in [0, 64], got '-1'"),
    ("crossval", ["--epochs", "0"], "--epochs: expected an integer in [1, 2147483647], got '0'"),
    ("crossval", ["--recipes", "nope"], "--recipes: expected one of 'l1', "),
    ("layer_example", ["--steps", "0"], "--steps: expected an integer in [1, 2147483647], got '0'"),
    ("layer_example", ["--beams", "999"], "--beams: expected an integer in [1, 128] (LiDAR beams), got '999'"),
    ("layer_example", ["--seed", "nan"], "--seed: expected an integer in [0, 4294967295] (a seed), got 'nan'"),
    ("layer_example", ["--bogus"], "--bogus: expected an option of this script (--help lists them), got an unknown one"),
    ("model", ["--frame", "-1"], "--frame: expected an integer in [0, 2147483647], got '-1'"),
    ("model", ["--repeats", "0"], "--repeats: expected an integer in [1, 2147483647], got '0'"),
    ("model", ["--superpixels", BIG], f"--superpixels: expected an integer in [1, 1000000] (superpixels per frame), got '{BIG}'"),
    ("plots", [], "--accuracy, --speed: expected a value, got none (required)"),
    ("scale", ["--size", "0", "5"], "--size: expected an integer in [8, 8192] (pixels), got '0'"),
    ("scale", ["--devices", BIG], f"--devices: expected an integer in [1, 64], got '{BIG}'"),
    ("scale", ["--workers", "-3"], "--workers: expected an integer in [0, 64], got '-3'"),
    ("scale", ["--frames", "0"], "--frames: expected an integer in [1, 1000000], got '0'"),
    ("solver", ["--systems", "foo"], "--systems: expected one of 'superpixel', 'pixel', got 'foo'"),
    ("solver", ["--unrolled-cap", "-4"], "--unrolled-cap: expected an integer in [1, 100000], got '-4'"),
    ("solver", ["--dtype", "float16"], "--dtype: expected one of 'float64', 'float32', got 'float16'"),
    ("speed", ["--large", "0x0"], "--large: expected WIDTHxHEIGHT such as 4000x3000, each in [8, 20000] pixels, got '0x0'"),
    ("speed", ["--large", "abc"], "--large: expected WIDTHxHEIGHT such as 4000x3000, each in [8, 20000] pixels, got 'abc'"),
    ("speed", ["--batch", "nan"], "--batch: expected an integer in [1, 1024], got 'nan'"),
    ("speed", ["--threads", "-2"], "--threads: expected an integer in [1, 1024], got '-2'"),
    ("speed", ["--kitti-root", ""], "--kitti-root: expected the KITTI sample folder, got '' (no such folder)"),
    ("stereo_check", ["--seeds", "-1"], "--seeds: expected an integer in [0, 4294967295] (a seed), got '-1'"),
    ("stereo_check", ["--size", "1", "1"], "--size: expected an integer in [64, 4096] (pixels), got '1'"),
    ("stereo_check", ["--threads", "0"], "--threads: expected an integer in [1, 1024], got '0'"),
    ("target_residuals", ["--top", "1"], "--top: expected a number in (0, 1) (share of the target pixels), got '1'"),
    ("target_residuals", ["--far", "nan"], "--far: expected a finite number of metres > 0, got 'nan'"),
    ("target_residuals", ["--far", "-1"], "--far: expected a finite number of metres > 0, got '-1'"),
    ("target_residuals", ["--every", "0"], "--every: expected an integer in [1, 2147483647], got '0'"),
    ("train_data", ["--workers", "-1"], "--workers: expected an integer in [0, 64], got '-1'"),
    ("train_data", ["--frames", "1"], "--frames: expected an integer in [2, 2147483647], got '1'"),
    ("train_data", ["--config", "/no/such.yaml"], "--config: expected a trainer config (YAML), got '/no/such.yaml' (no such file)"),
    ("weights_compare", ["--protocols", "zz"], "--protocols: expected one of 'a', "),
])
def test_a_bad_option_is_one_line(name, args, first_line, capsys):
    err = _refused(name, args, capsys)
    assert err[0].startswith(f"{name}.py: error: {first_line}"), err


@pytest.mark.parametrize("name, option", [("accuracy", "--out-dir"), ("accuracy", "--targets-root"),
                                          ("plots", "--out-dir"), ("stereo_check", "--pictures"),
                                          ("target_residuals", "--targets-root")])
def test_a_file_where_an_output_folder_is_expected_is_refused(name, option, tmp_path, capsys):
    a_file = tmp_path / "a_file"
    a_file.write_text("x")
    extra = ["--accuracy", str(a_file), "--speed", str(a_file)] if name == "plots" else []
    err = _refused(name, [*extra, option, str(a_file)], capsys)
    assert err[0] == f"{name}.py: error: {option}: expected a folder to write into, got '{a_file}', which is a file"


@pytest.mark.parametrize("name, option, what", [
    ("model", "--kitti-root", "the KITTI sample folder"), ("speed", "--kitti-root", "the KITTI sample folder"),
    ("train_data", "--data", "the KITTI folder (raw/, object/, ...)"),
    ("target_residuals", "--val-selection", "a val_selection_cropped folder"),
])
def test_a_file_where_a_data_folder_is_expected_is_refused(name, option, what, tmp_path, capsys):
    a_file = tmp_path / "a_file"
    a_file.write_text("x")
    err = _refused(name, [option, str(a_file)], capsys)
    assert err[0] == f"{name}.py: error: {option}: expected {what}, got '{a_file}' (which is a file)"


def test_target_residuals_refuses_reversed_frames(tmp_path, capsys):
    err = _refused("target_residuals", ["--raw-root", str(tmp_path), "--frames", "5", "1"], capsys)
    assert err[0] == "target_residuals.py: error: --frames: expected FIRST <= LAST, got 5 1"


def test_the_safety_net_turns_a_late_bad_input_into_one_line(capsys):
    from crfdepth.errors import InputError

    bench = load_benchmark("solver")

    def main(argv):
        raise InputError("--weights: expected a weights file, got nothing")

    assert bench.sa.run_script(main, "solver.py", []) == 2
    assert capsys.readouterr().err.splitlines() == ["solver.py: error: --weights: expected a weights file, got nothing"]


@pytest.mark.kitti
def test_a_frame_beyond_the_folder_is_one_line(capsys, kitti_root):
    bench = load_benchmark("model")
    assert bench.sa.run_script(bench.main, "model.py", ["--kitti-root", str(kitti_root), "--frame", "999"]) == 2
    err = capsys.readouterr().err.splitlines()
    assert len(err) == 1 and err[0].startswith("model.py: error: --frame: expected an index in [0, ")


@pytest.mark.parametrize("name, args, first_line", [
    ("solver", ["--systems", "foo"], "solver.py: error: --systems: expected one of 'superpixel', 'pixel', got 'foo'"),
    ("speed", ["--device", "cuda:7"], "speed.py: error: --device: expected a device this machine has"),
])
def test_python_benchmarks_script_prints_one_line(tmp_path, name, args, first_line):
    proc = subprocess.run([sys.executable, str(BENCHMARKS / f"{name}.py"), *args], cwd=tmp_path, capture_output=True,
                          text=True, timeout=300)
    assert proc.returncode == 2, proc.stderr[-2000:]
    assert proc.stderr.splitlines()[0].startswith(first_line) and len(proc.stderr.splitlines()) == 1
