"""Front-door details of issue 25: what a new user sees from the README's commands.

- warnings in the CLI are one clean line (``crfdepth complete: warning: ...``), not Python's
  ``file:line: UserWarning`` with the source line;
- the files the README's commands write into the repository are ignored by git;
- ``benchmarks/model.py`` says what it is doing while it runs.
"""

from __future__ import annotations

import re
import shlex
import shutil
import subprocess
import warnings
from pathlib import Path

import numpy as np
import pytest

from crfdepth import cli
from crfdepth.cli import warnings_as_lines
from crfdepth.io.kitti import read_depth_png
from crfdepth.io.pointcloud import read_points
from tests.documents import DOCUMENTS, ROOT

EXAMPLE = ROOT / "docs" / "example"


# ----------------------------------------------------------------------------- warnings


@pytest.fixture
def main(monkeypatch):
    monkeypatch.setattr(cli, "_COMMANDS", ("crfdepth.cli.complete",))
    return cli.main


def test_nan_points_warning_is_one_clean_line(main, tmp_path, capsys):
    points = read_points(EXAMPLE / "scan.pcd")
    nan_rows = np.full((3, points.shape[1]), np.nan, dtype=points.dtype)
    with_nan = np.concatenate([nan_rows[:1], points[:100], nan_rows[1:], points[100:]])
    np.save(tmp_path / "scan_nan.npy", with_nan)
    np.save(tmp_path / "scan.npy", points)
    common = ["complete", "--image", str(EXAMPLE / "image.png"), "--calib", str(EXAMPLE / "rig.yaml"),
              "--weights", "paper", "--quiet"]

    original = warnings.showwarning
    assert main([*common, "--points", str(tmp_path / "scan_nan.npy"), "--out", str(tmp_path / "nan.png")]) == 0
    err = capsys.readouterr().err
    assert err.splitlines() == [
        f"crfdepth complete: warning: points: dropped 3 of {len(with_nan)} point(s) with NaN or infinite "
        "coordinates (no-return placeholders of an organised cloud?)"]
    assert "UserWarning" not in err and "warnings.warn" not in err and ".py" not in err
    assert warnings.showwarning is original  # restored after the command

    # The NaN rows were dropped and nothing else: the same depth as the clean cloud (same process).
    assert main([*common, "--points", str(tmp_path / "scan.npy"), "--out", str(tmp_path / "clean.png")]) == 0
    assert capsys.readouterr().err == ""
    np.testing.assert_array_equal(read_depth_png(tmp_path / "nan.png"), read_depth_png(tmp_path / "clean.png"))


def test_other_libraries_warnings_keep_their_kind(capsys):
    with warnings_as_lines("demo"), warnings.catch_warnings():
        warnings.simplefilter("always")
        warnings.warn("old API\nuse the new one", DeprecationWarning, stacklevel=1)
        warnings.warn("plain", UserWarning, stacklevel=1)
    assert capsys.readouterr().err.splitlines() == [
        "crfdepth demo: warning: DeprecationWarning: old API use the new one",
        "crfdepth demo: warning: plain"]


def test_python_312_fork_warning_of_dataloader_workers_is_not_printed(capsys):
    # Python 3.12+ warns when a multi-threaded process forks (DataLoader's --workers do, from a
    # process holding torch's thread pools); other DeprecationWarnings still print.
    with warnings.catch_warnings():
        warnings.simplefilter("default")  # as pytest and python -W default set them, before the command
        with warnings_as_lines("complete"):
            warnings.warn("This process (pid=4962) is multi-threaded, use of fork() may lead to deadlocks in the child.",
                          DeprecationWarning, stacklevel=1)
            warnings.warn("This process is old", DeprecationWarning, stacklevel=1)
    assert capsys.readouterr().err.splitlines() == ["crfdepth complete: warning: DeprecationWarning: This process is old"]


def test_warning_filters_still_apply(capsys):
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        with warnings_as_lines("complete"), pytest.raises(UserWarning, match="as an error"):
            warnings.warn("as an error", UserWarning, stacklevel=1)
    assert capsys.readouterr().err == ""


# ----------------------------------------------------------------------------- README outputs

_OUTPUT_FLAGS = ("--out", "--out-std", "--out-dir", "--out-std-dir", "--out-bag")
# Where a README command writes without an output option (each command's default).
_DEFAULT_OUTPUTS = {("crfdepth", "demo"): "crfdepth_demo/", ("crfdepth", "evaluate"): "evaluation/",
                    ("python", "benchmarks/accuracy.py"): "accuracy_results/", ("python", "-m", "train"): "lightning_logs/"}


def _readme_commands() -> list[list[str]]:
    """Every ``crfdepth ...`` / ``python ...`` command of README.md and the pages: bash blocks and inline code."""
    texts = []
    for path in DOCUMENTS:
        readme = path.read_text()
        for block in re.findall(r"^```bash\n(.*?)^```", readme, flags=re.S | re.M):
            texts += block.replace("\\\n", " ").splitlines()
        texts += [" ".join(span.split()) for span in re.findall(r"`([^`]+)`", re.sub(r"```.*?```", "", readme, flags=re.S))]
    commands = []
    for text in texts:
        for part in re.split(r"&&|;", text):
            if not part.split() or part.split()[0] not in ("crfdepth", "python", "python3"):
                continue  # prose in code spans (a prime, an apostrophe) is not a command
            words = shlex.split(part, comments=True)
            if words and words[0] in ("crfdepth", "python", "python3") and len(words) > 1:
                commands.append(words)
    return commands


def _outputs(words: list[str]) -> set[str]:
    """The relative output paths a README command names (folders end in "/")."""
    found = set()
    for flag in _OUTPUT_FLAGS:
        if flag in words[:-1]:
            path = words[words.index(flag) + 1]
            found.add(path.rstrip("/") + "/" if flag.endswith("dir") else path)
    if "--vis" in words and "--out" in words:  # a bare --vis: pictures next to --out
        stem = Path(words[words.index("--out") + 1]).with_suffix("")
        found |= {f"{stem}_vis_depth.png", f"{stem}_vis_std.png"}
    if words[1:3] == ["-m", "crfdepth.data.example_bag"] and len(words) > 3:
        found.add(words[3])
    if not any(flag in words for flag in _OUTPUT_FLAGS):
        for prefix, default in _DEFAULT_OUTPUTS.items():
            if tuple(words[:len(prefix)]) == prefix:
                found.add(default)
    # Placeholders (DEPTH.png, DIR) and absolute paths are the user's; crfdepth/weights/kitti.json
    # (python -m train.export) regenerates a committed file.
    return {p for p in found if not re.search(r"[A-Z]{2,}", p) and not p.startswith("/")
            and not (ROOT / p).parent.samefile(ROOT / "crfdepth" / "weights")}


def test_readme_outputs_are_ignored_by_git(tmp_path):
    git = shutil.which("git")
    if git is None:
        pytest.skip("git is not installed")
    outputs = set().union(*(_outputs(words) for words in _readme_commands()))
    # The parser finds the README's outputs (a README rewrite that hides them fails here).
    assert {"crfdepth_demo/", "depth.png", "std.png", "depth_vis_depth.png", "depth_vis_std.png", "street.bag",
            "depth/", "std/", "street_depth.bag", "submission/", "lightning_logs/"} <= outputs, outputs
    # git check-ignore --no-index on the project's .gitignore, in an empty repository (works
    # from a copy of the files without .git, too).
    shutil.copy(ROOT / ".gitignore", tmp_path / ".gitignore")
    subprocess.run([git, "init", "-q", str(tmp_path)], check=True)
    paths = sorted(p + "frame.png" if p.endswith("/") else p for p in outputs)
    result = subprocess.run([git, "-C", str(tmp_path), "check-ignore", "--no-index", "--verbose",
                             "--non-matching", *paths], capture_output=True, text=True)
    not_ignored = [line.split("\t")[-1] for line in result.stdout.splitlines() if line.startswith("::")]
    assert result.returncode in (0, 1) and len(result.stdout.splitlines()) == len(paths), result.stderr
    assert not_ignored == [], f"README outputs not in .gitignore: {not_ignored}"


# ----------------------------------------------------------------------------- benchmark progress


def test_model_benchmark_prints_progress_on_stderr(capsys):
    import importlib.util

    import torch

    from crfdepth.data.synthetic import make_scene

    spec = importlib.util.spec_from_file_location("model_benchmark", ROOT / "benchmarks" / "model.py")
    bench = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(bench)
    t = make_scene(0, height=64, width=224).to_tensors()
    frame = dict(image=t["image"][None], sparse=t["sparse"][None], target=t["target"][None], K=t["K"],
                 name="small")
    configs = [("pixel", None, None), ("superpixel", 150, True)]
    with torch.inference_mode():
        rows = bench.measure(configs, frame, "cpu", repeats=2, std_repeats=[0, 1])
    captured = capsys.readouterr()
    lines = [re.sub(r"^\[ *[0-9.]+ s\] ", "", line) for line in captured.err.splitlines()]
    assert lines == ["configuration 1/2: pixel (build, warm-up)",
                     "configuration 2/2: superpixel 150 refine=True (build, warm-up)",
                     "round 1/2: 2 configurations", "round 2/2: 2 configurations"], captured.err
    assert captured.out == ""  # stdout stays the table and the JSON
    assert [(r["mode"], r["superpixels"], r["std_s"] is None) for r in rows] == [
        ("pixel", None, True), ("superpixel", 150, False)]  # std timed only where std_repeats asked
    assert all(r["total_s"] > 0 for r in rows)


def test_log_messages_are_one_line_like_the_errors(tmp_path):
    """A logged warning of a command (here: a greyscale --image) reads ``crfdepth complete: warning: ...``,
    not ``WARNING crfdepth.cli.complete: ...``; checked in a fresh process, where main sets up logging."""
    import sys

    import cv2

    example = Path(__file__).resolve().parents[1] / "docs" / "example"
    grey = cv2.cvtColor(cv2.imread(str(example / "image.png")), cv2.COLOR_BGR2GRAY)
    image = tmp_path / "grey.png"
    cv2.imwrite(str(image), np.dstack([grey] * 3))
    proc = subprocess.run([sys.executable, "-m", "crfdepth", "complete", "--image", str(image), "--points",
                           str(example / "scan.pcd"), "--calib", str(example / "rig.yaml"), "--out",
                           str(tmp_path / "d.png"), "--quiet", "--weights", "paper", "--mode", "pixel"],
                          capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr
    assert proc.stderr.splitlines()[0] == f"crfdepth complete: warning: --image {image} is greyscale; the colour " \
                                          f"potential sees intensity only"
