"""Folder runs check every frame before writing anything, and ``--skip-bad``; output locations
checked before any computation (``--out`` under /proc, a read-only folder); ``--input-dir``
given a file. Bag runs: tests/cli/test_complete_bag.py (``test_bad_frame_midway_writes_nothing``,
``test_skip_bad_completes_the_other_frames``)."""

from __future__ import annotations

import csv
import os
from pathlib import Path

import pytest

from crfdepth import api
from crfdepth.cli import complete_one, model_options
from crfdepth.runs.resume import RUN_RECORD
from crfdepth.runs.skip_bad import LISTED_BAD
from tests.cli.frames import FAST, files, png, run, stem, write_folder


def _skipped(out: Path) -> list[dict]:
    with open(out / "skipped.csv", newline="") as handle:
        return list(csv.DictReader(handle))


@pytest.fixture
def no_model(monkeypatch):
    """Fail the test if the model is ever built or run (the check must come before any computation)."""
    def refuse(*args, **kwargs):
        raise AssertionError("the model was used before the output was checked")

    monkeypatch.setattr(complete_one, "build_model", refuse)
    monkeypatch.setattr(api, "complete_depth", refuse)
    monkeypatch.setattr(model_options, "build_model", refuse)


def test_a_bad_frame_in_the_middle_writes_nothing(tmp_path):
    data = write_folder(tmp_path / "val_selection_cropped", 3, bad={1: "zero sparse"})
    out, std, vis = tmp_path / "out", tmp_path / "std", tmp_path / "vis"
    code, stdout, err = run(["complete", "--input-dir", data, "--out-dir", out, "--out-std-dir", std, "--vis", vis,
                             *FAST])
    assert code == 2 and stdout == ""
    assert err == (f"crfdepth complete: error: frame 2/3 {stem('velodyne_raw', 1)} (velodyne_raw/"
                   f"{stem('velodyne_raw', 1)}.png): every pixel is 0 (no LiDAR point); the CRF needs at least one "
                   f"depth measurement [1 of 3 frame(s) of --input-dir {data} bad; nothing written; fix them, or "
                   f"give --skip-bad to complete the others]\n")
    assert not out.exists() and not std.exists() and not vis.exists()


def test_every_bad_frame_is_listed(tmp_path):
    bad = {1: "zero sparse", 2: "unreadable image", 4: "zero sparse"}
    data = write_folder(tmp_path / "val_selection_cropped", 5, bad=bad)
    code, _, err = run(["complete", "--input-dir", data, "--out-dir", tmp_path / "out", *FAST])
    lines = err.splitlines()
    assert code == 2 and len(lines) == 3
    assert lines[0].startswith(f"crfdepth complete: error: frame 2/5 {stem('velodyne_raw', 1)} (velodyne_raw/")
    assert lines[0].endswith(f"[3 of 5 frame(s) of --input-dir {data} bad, listed below; nothing written; fix them, "
                             f"or give --skip-bad to complete the others]")
    assert lines[1].startswith(f"  frame 3/5 {stem('velodyne_raw', 2)}: image: ") and "not a readable image" in lines[1]
    assert lines[2].startswith(f"  frame 5/5 {stem('velodyne_raw', 4)} (velodyne_raw/") and "no LiDAR point" in lines[2]
    assert not (tmp_path / "out").exists()


def test_at_most_listed_bad_frames_are_listed(tmp_path, monkeypatch):
    monkeypatch.setattr("crfdepth.runs.skip_bad.LISTED_BAD", 2)
    data = write_folder(tmp_path / "val_selection_cropped", 4, bad={i: "zero sparse" for i in range(4)})
    code, _, err = run(["complete", "--input-dir", data, "--out-dir", tmp_path / "out", *FAST])
    lines = err.splitlines()
    assert code == 2 and len(lines) == 3 and lines[2] == "  ... and 2 more"
    assert LISTED_BAD == 20  # the shipped limit


@pytest.mark.parametrize("workers", [0, 2])
def test_skip_bad_completes_the_others_and_lists_the_bad_ones(tmp_path, workers):
    data = write_folder(tmp_path / "val_selection_cropped", 4, bad={1: "zero sparse", 2: "unreadable image"})
    out = tmp_path / "out"
    code, stdout, err = run(["complete", "--input-dir", data, "--out-dir", out, "--skip-bad", "--workers", workers,
                             "--batch-size", 2, "--potentials", "colour"])
    assert code == 0, err
    assert files(out) == sorted([png(0), png(3), "skipped.csv", RUN_RECORD])  # the run finished, frames 1, 2 left out
    skipped = _skipped(out)
    assert [r["frame"] for r in skipped] == [stem("velodyne_raw", 1), stem("velodyne_raw", 2)]
    assert "no LiDAR point" in skipped[0]["reason"] and "not a readable image" in skipped[1]["reason"]
    lines = stdout.splitlines()
    assert lines[0].startswith("model: kitti weights, pixel grid")  # the model line (build_model)
    assert lines[1].startswith(f"wrote 2 depth PNG(s) to {out} in ")
    assert lines[2] == f"skipped 2 bad frame(s) of 4 (--skip-bad), listed with the reasons in {out / 'skipped.csv'}"


def test_skip_bad_with_every_frame_bad_writes_nothing(tmp_path):
    data = write_folder(tmp_path / "val_selection_cropped", 2, bad={0: "zero sparse", 1: "zero sparse"})
    code, _, err = run(["complete", "--input-dir", data, "--out-dir", tmp_path / "out", "--skip-bad", *FAST])
    assert code == 2
    assert err.startswith(f"crfdepth complete: error: --skip-bad: all 2 frame(s) of --input-dir {data} are bad (the "
                          f"first: frame 1/2 ")
    assert not (tmp_path / "out").exists()


def test_a_clean_rerun_removes_an_earlier_skipped_csv(tmp_path):
    """The folder describes the last run: a skipped.csv of an earlier --skip-bad run goes when nothing is skipped."""
    data = write_folder(tmp_path / "val_selection_cropped", 2)
    out = tmp_path / "out"
    out.mkdir()
    (out / "skipped.csv").write_text("frame,reason\nx,y\n")
    code, _, err = run(["complete", "--input-dir", data, "--out-dir", out, "--skip-bad", *FAST])
    assert code == 0, err
    assert files(out) == sorted([png(0), png(1), RUN_RECORD])


def test_skip_bad_needs_a_run_over_many_frames(tmp_path):
    code, _, err = run(["complete", "--image", "a.png", "--sparse", "b.png", "--intrinsics", "k.txt", "--out",
                        tmp_path / "d.png", "--skip-bad"])
    assert code == 2 and err == ("crfdepth complete: error: --skip-bad: applies to the runs over many frames "
                                 "(--input-dir, --bag or --input-list); a single frame is either completed or refused\n")
    assert list(tmp_path.iterdir()) == []


# --------------------------------------------------------------------------- output locations


def test_out_under_proc_is_refused_before_any_computation(tmp_path, no_model):
    data = write_folder(tmp_path / "val_selection_cropped", 1)
    image, sparse = data / "image" / f"{stem('image', 0)}.png", data / "velodyne_raw" / png(0)
    intrinsics = data / "intrinsics" / f"{stem('image', 0)}.txt"
    code, _, err = run(["complete", "--image", image, "--sparse", sparse, "--intrinsics", intrinsics, "--out",
                        "/proc/crfdepth_test.png", *FAST])
    assert code == 2
    assert err.startswith("crfdepth complete: error: --out: cannot create /proc/crfdepth_test.png: the folder /proc "
                          "does not accept new files (")
    assert ".tmp" not in err and err.count("\n") == 1
    assert not os.path.exists("/proc/crfdepth_test.png")


@pytest.mark.parametrize("flag", ["--out-dir", "--out-std-dir", "--vis"])
def test_out_dir_under_proc_is_refused_before_reading_frames(tmp_path, flag, no_model):
    data = write_folder(tmp_path / "val_selection_cropped", 1)
    targets = {"--out-dir": tmp_path / "out", "--out-std-dir": tmp_path / "std", "--vis": tmp_path / "vis",
               flag: "/proc/crfdepth_test"}
    code, _, err = run(["complete", "--input-dir", data, *[str(a) for kv in targets.items() for a in kv], *FAST])
    assert code == 2
    assert err.startswith(f"crfdepth complete: error: {flag}: output folder is not writable: /proc (creating a file "
                          f"there fails: ")
    assert not any(Path(t).exists() for t in targets.values())


def test_out_in_a_read_only_folder(tmp_path, no_model):
    locked = tmp_path / "locked"
    locked.mkdir()
    locked.chmod(0o555)
    try:
        if os.access(locked, os.W_OK):  # root: permission bits do not stop it, so there is nothing to refuse
            pytest.skip("this user can write into read-only folders (root)")
        data = write_folder(tmp_path / "val_selection_cropped", 1)
        code, _, err = run(["complete", "--input-dir", data, "--out-dir", locked / "sub", *FAST])
        assert code == 2
        assert err == (f"crfdepth complete: error: --out-dir: output folder is not writable: {locked} (creating a "
                       f"file there fails: Permission denied)\n")
        assert files(locked) == []
    finally:
        locked.chmod(0o755)


def test_input_dir_given_a_file(tmp_path, no_model):
    file = tmp_path / "frames.zip"
    file.write_bytes(b"PK")
    code, _, err = run(["complete", "--input-dir", file, "--out-dir", tmp_path / "out"])
    assert code == 2
    assert err == (f"crfdepth complete: error: --input-dir: expected a folder with image/, velodyne_raw/ and "
                   f"intrinsics/ (a KITTI val_selection_cropped or test_depth_completion_anonymous folder) or a "
                   f"KITTI raw drive folder (velodyne_points/, image_02/), got a file: {file}\n")
    assert not (tmp_path / "out").exists()


def test_input_dir_of_another_layout_names_the_flag(tmp_path, no_model):
    (tmp_path / "frames").mkdir()
    code, _, err = run(["complete", "--input-dir", tmp_path / "frames", "--out-dir", tmp_path / "out"])
    assert code == 2
    assert err.startswith(f"crfdepth complete: error: --input-dir {tmp_path / 'frames'}: KittiTestCompletion: "
                          f"expected {tmp_path / 'frames' / 'velodyne_raw'}")
