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

ROOT = Path(__file__).resolve().parents[1]
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


def test_warning_filters_still_apply(capsys):
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        with warnings_as_lines("complete"), pytest.raises(UserWarning, match="as an error"):
            warnings.warn("as an error", UserWarning, stacklevel=1)
    assert capsys.readouterr().err == ""
