"""The status line of a long single frame (crfdepth.cli.progress; issue 25, item 6): the model's
stages on stderr, shown on a terminal or with --verbose once a frame is expected to take (or
takes) more than a few seconds; never with --quiet. The threshold is forced to 0 here."""

from __future__ import annotations

import io
import re
from pathlib import Path

import cv2
import numpy as np
import pytest

from crfdepth import cli
from crfdepth.cli import progress as progress_module
from crfdepth.cli.progress import FrameProgress
from crfdepth.io.kitti import read_depth_png, write_depth_png
from crfdepth.model import CRFDepth

H, W = 48, 64
LINE = re.compile(r"^complete: 64x48 frame: (.+), (\d+\.\d) s$")


@pytest.fixture
def main(monkeypatch):
    monkeypatch.setattr(cli, "_COMMANDS", ("crfdepth.cli.complete",))
    return cli.main


@pytest.fixture
def frame(tmp_path) -> dict[str, Path]:
    rows, cols = np.mgrid[0:H, 0:W]
    rgb = np.zeros((H, W, 3), np.uint8)
    rgb[:, : W // 2] = (200, 40, 40)
    rgb[:, W // 2:] = (40, 60, 200)
    sparse = np.zeros((H, W))
    sparse[4::5, 2::4] = np.where(cols < W // 2, 8.0 + 0.05 * rows, 20.0 - 0.1 * rows)[4::5, 2::4]
    paths = {"image": tmp_path / "rgb.png", "sparse": tmp_path / "sparse.png", "intrinsics": tmp_path / "K.txt"}
    cv2.imwrite(str(paths["image"]), rgb)
    write_depth_png(paths["sparse"], sparse)
    paths["intrinsics"].write_text("60 0 32\n0 60 24\n0 0 1\n")
    return paths


def _args(frame, out, *extra) -> list[str]:
    return ["complete", "--image", str(frame["image"]), "--sparse", str(frame["sparse"]), "--intrinsics",
            str(frame["intrinsics"]), "--out", str(out), *extra]


@pytest.mark.parametrize("mode, stages", [("pixel", ["nearest fill", "solve"]),
                                          ("superpixel", ["nearest fill", "superpixels (SLIC)", "superpixel graph",
                                                          "potentials", "solve", "painting", "pixel refinement"])])
def test_verbose_shows_each_stage_then_done(main, capsys, frame, tmp_path, monkeypatch, mode, stages):
    monkeypatch.setattr(progress_module, "SHOW_AFTER_S", 0.0)
    out = tmp_path / "depth.png"
    assert main(["--verbose", *_args(frame, out, "--mode", mode)]) == 0
    lines = [m.groups() for m in map(LINE.match, capsys.readouterr().err.splitlines()) if m]
    names = [name for name, _ in lines]
    for stage in stages:
        assert stage in names
    assert names[0] == "nearest fill" and names[-1] == "done"
    seconds = [float(s) for _, s in lines]
    assert seconds == sorted(seconds)  # elapsed time, growing
    assert read_depth_png(out).shape == (H, W)
    assert CRFDepth.progress is None  # the hook was set on the CLI's model only


def test_quiet_shows_no_progress_even_with_verbose(main, capsys, frame, tmp_path, monkeypatch):
    monkeypatch.setattr(progress_module, "SHOW_AFTER_S", 0.0)
    out = tmp_path / "depth.png"
    assert main(["--verbose", *_args(frame, out, "--mode", "pixel", "--quiet")]) == 0
    captured = capsys.readouterr()
    assert "frame:" not in captured.err and captured.out == ""
    assert out.exists()


def test_no_progress_without_a_terminal_or_verbose(main, capsys, frame, tmp_path, monkeypatch):
    monkeypatch.setattr(progress_module, "SHOW_AFTER_S", 0.0)
    out = tmp_path / "depth.png"
    assert main(_args(frame, out, "--mode", "pixel")) == 0
    assert "frame:" not in capsys.readouterr().err


def test_fast_frame_under_the_threshold_shows_nothing(main, capsys, frame, tmp_path):
    """The default threshold (seconds) is far above a 64x48 frame's expected and elapsed time."""
    assert progress_module.SHOW_AFTER_S >= 1.0
    out = tmp_path / "depth.png"
    assert main(["--verbose", *_args(frame, out, "--mode", "pixel")]) == 0
    assert "frame:" not in capsys.readouterr().err


class _Terminal(io.StringIO):
    def isatty(self) -> bool:
        return True


def test_terminal_line_is_rewritten_in_place_and_ended():
    stream = _Terminal()
    with FrameProgress(4000, 6000, "cpu", enabled=True, stream=stream) as progress:  # expected 24 s on the CPU
        progress.stage("slic")
        progress.stage("solve")
    text = stream.getvalue()
    assert text.count("\r") == 3 and text.endswith("\n") and text.count("\n") == 1
    parts = text.strip("\n").split("\r")[1:]
    assert [p.split(": ")[2].split(",")[0] for p in parts] == ["superpixels (SLIC)", "solve", "done"]
    assert all(p.startswith("complete: 6000x4000 frame: ") for p in parts)


def test_expected_time_alone_starts_the_line():
    """A large frame shows its first stage at once; a small one waits for the threshold; disabled writes nothing."""
    large, small, off = io.StringIO(), io.StringIO(), io.StringIO()
    for stream, (h, w), enabled in ((large, (4000, 6000), True), (small, (48, 64), True), (off, (4000, 6000), False)):
        with FrameProgress(h, w, "cpu", enabled=enabled, stream=stream) as progress:
            progress.stage("fill")
    assert large.getvalue().splitlines()[0].startswith("complete: 6000x4000 frame: nearest fill, 0.")
    assert small.getvalue() == "" and off.getvalue() == ""
