"""``complete --input-list FILE``: every input of the list completed into its own subfolder, each line
checked before anything runs (a missing or unreadable path named with its line number), a failing input
stopping the run or, with --skip-bad, left out while the others go on."""

from __future__ import annotations

import pytest

from tests.cli.frames import FAST, files, png, run, write_folder


@pytest.fixture(scope="module")
def folders(tmp_path_factory):
    root = tmp_path_factory.mktemp("inputs")
    return [write_folder(root / f"drive{k}" / "val_selection_cropped", 2) for k in range(2)]


def _listing(tmp_path, lines: list[str]):
    path = tmp_path / "inputs.txt"
    path.write_text("\n".join(lines) + "\n")
    return path


def test_every_input_is_completed_into_its_own_folder(folders, tmp_path):
    listing = _listing(tmp_path, ["# two KITTI folders", str(folders[0]), "", str(folders[1].parent)])
    code, stdout, err = run(["complete", "--input-list", listing, "--out-dir", tmp_path / "out",
                             *[f for f in FAST if f != "--quiet"]])
    assert code == 0, err
    assert files(tmp_path / "out") == [f"{name}/{png(i)}" for name in ("drive1", "val_selection_cropped")
                                       for i in range(2)]
    assert f"completed 2 of 2 input(s) of --input-list {listing}" in stdout


def test_a_missing_or_unreadable_line_is_named_before_anything_runs(folders, tmp_path):
    missing = tmp_path / "nowhere"
    listing = _listing(tmp_path, [str(folders[0]), "# comment", str(missing)])
    code, _, err = run(["complete", "--input-list", listing, "--out-dir", tmp_path / "out", *FAST])
    assert code == 2 and err == (f"crfdepth complete: error: --input-list {listing}, line 3: {missing}: no such file "
                                 f"or folder\n")
    assert not (tmp_path / "out").exists()
    text = tmp_path / "notes.txt"
    text.write_text("x")
    listing = _listing(tmp_path, [str(text)])
    code, _, err = run(["complete", "--input-list", listing, "--out-dir", tmp_path / "out", *FAST])
    assert code == 2 and (f"line 1: {text}: expected a KITTI depth-completion folder, a KITTI raw drive folder or "
                          f"a ROS recording") in err
    code, _, err = run(["complete", "--input-list", tmp_path / "none.txt", "--out-dir", tmp_path / "out", *FAST])
    assert code == 2 and "--input-list: no such file" in err


def test_a_failing_input_stops_the_run_or_is_left_out_with_skip_bad(folders, tmp_path):
    empty = tmp_path / "empty" / "val_selection_cropped"
    for sub in ("image", "velodyne_raw", "intrinsics", "groundtruth_depth"):
        (empty / sub).mkdir(parents=True)  # a folder of the layout without frames: refused when its turn comes
    listing = _listing(tmp_path, [str(folders[0]), str(empty), str(folders[1])])
    code, _, err = run(["complete", "--input-list", listing, "--out-dir", tmp_path / "a", *FAST])
    assert code == 2 and err.startswith(f"crfdepth complete: error: --input-list line 2 ({empty}): ")
    assert "[1 of 3 input(s) completed before it; --resume continues]" in err
    code, stdout, err = run(["complete", "--input-list", listing, "--out-dir", tmp_path / "b", "--skip-bad",
                             *[f for f in FAST if f != "--quiet"]])
    assert code == 0, err
    assert "completed 2 of 3 input(s)" in stdout and f"failed: --input-list line 2 ({empty}): " in stdout
    assert [f for f in files(tmp_path / "b") if f.endswith(".png")] == [
        f"{name}/{png(i)}" for name in ("val_selection_cropped-1", "val_selection_cropped-3") for i in range(2)]
