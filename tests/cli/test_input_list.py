"""``complete --input-list FILE``: every input of the list completed into its own subfolder, each line
checked before anything runs (a missing or unreadable path named with its line number), a failing input
stopping the run or, with --skip-bad, left out while the others go on; two ranks (as torchrun starts them)
write what one process writes, and go on or stop alike."""

from __future__ import annotations

import json

import pytest

from crfdepth.runs.resume import RUN_RECORD
from tests.cli.frames import FAST, files, png, run, same_pngs, write_folder
from tests.cli.launching import two_ranks


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
    assert files(tmp_path / "out") == [f"{name}/{leaf}" for name in ("drive1", "val_selection_cropped")
                                       for leaf in (RUN_RECORD, png(0), png(1))]  # each folder's run finished
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
        (empty / sub).mkdir(parents=True)  # a folder of the layout without frames: refused before any input runs
    listing = _listing(tmp_path, [str(folders[0]), str(empty), str(folders[1])])
    code, _, err = run(["complete", "--input-list", listing, "--out-dir", tmp_path / "a", *FAST])
    assert code == 2 and err.startswith(f"crfdepth complete: error: --input-list line 2 ({empty}): ")
    assert "[every line is checked before any input is completed; nothing written]" in err
    assert not (tmp_path / "a").exists()
    code, stdout, err = run(["complete", "--input-list", listing, "--out-dir", tmp_path / "b", "--skip-bad",
                             *[f for f in FAST if f != "--quiet"]])
    assert code == 0, err
    assert "completed 2 of 3 input(s)" in stdout and f"failed: --input-list line 2 ({empty}): " in stdout
    assert [f for f in files(tmp_path / "b") if f.endswith(".png")] == [
        f"{name}/{png(i)}" for name in ("val_selection_cropped-1", "val_selection_cropped-3") for i in range(2)]


def _mixed_list(folders, tmp_path):
    """A good folder, one with a bad frame, one without frames (refused when its turn comes), a good folder."""
    bad = write_folder(tmp_path / "bad" / "val_selection_cropped", 3, bad={1: "zero sparse"})
    empty = tmp_path / "empty" / "val_selection_cropped"
    for sub in ("image", "velodyne_raw", "intrinsics", "groundtruth_depth"):
        (empty / sub).mkdir(parents=True)
    return _listing(tmp_path, [str(folders[0]), str(bad), str(empty), str(folders[1])]), empty


def test_two_ranks_complete_the_list_as_one_process_and_skip_bad_alike(folders, tmp_path):
    listing, empty = _mixed_list(folders, tmp_path)
    argv = ["complete", "--input-list", listing, "--skip-bad", "--potentials", "colour"]
    code, stdout, err = run([*argv, "--out-dir", tmp_path / "one"])
    assert code == 0, err
    ranks = two_ranks(["-v", *argv, "--out-dir", tmp_path / "two", "--num-nodes", "2"])
    assert [r.returncode for r in ranks] == [0, 0], [r.stderr for r in ranks]
    assert ranks[0].stderr.count("joined the group as rank") == 1  # once for the whole list
    same_pngs(tmp_path / "one", tmp_path / "two")  # the bad frame left out, listed in its skipped.csv
    skipped = "val_selection_cropped-2/skipped.csv"
    assert (tmp_path / "two" / skipped).read_text() == (tmp_path / "one" / skipped).read_text()
    assert len(files(tmp_path / "two")) == 2 + 2 + 2 + 1 + 3  # PNGs, skipped.csv, a run record per folder
    for name in ("val_selection_cropped-1", "val_selection_cropped-2", "val_selection_cropped-4"):
        record = json.loads((tmp_path / "two" / name / RUN_RECORD).read_text())  # written once, by rank 0
        assert record == json.loads((tmp_path / "one" / name / RUN_RECORD).read_text()) and record["finished"]
    summary = f"completed 3 of 4 input(s) of --input-list {listing} into {tmp_path / 'two'}"
    assert summary in ranks[0].stdout and f"failed: --input-list line 3 ({empty}): " in ranks[0].stdout
    assert ranks[1].stdout == ""  # rank 0 reports for the group


def test_two_ranks_stop_the_list_alike_at_a_bad_input(folders, tmp_path):
    listing, _ = _mixed_list(folders, tmp_path)
    ranks = two_ranks(["complete", "--input-list", listing, "--out-dir", tmp_path / "o", "--num-nodes", "2", *FAST])
    assert [r.returncode for r in ranks] == [2, 2]
    last = [r.stderr.splitlines()[-1] for r in ranks]
    assert last[0] == last[1] and last[0].startswith("crfdepth complete: error: --input-list line 3 (")
    assert "[every line is checked before any input is completed; nothing written]" in last[0]
    assert not (tmp_path / "o").exists()  # the folder without frames (line 3) is refused before line 1 runs


def test_two_ranks_complete_a_recording_of_the_list_on_rank_0(folders, tmp_path):
    pytest.importorskip("rosbags")
    from tests.io.ros.bags import IMAGE_TOPIC, POINTS_TOPIC, write_bag

    recording = write_bag(tmp_path / "drive_bag", "mcap", count=2).path  # a ROS 2 bag: a folder
    listing = _listing(tmp_path, [str(recording), str(folders[0])])
    argv = ["complete", "--input-list", listing, "--image-topic", IMAGE_TOPIC, "--points-topic", POINTS_TOPIC,
            *FAST]
    code, _, err = run([*argv, "--out-dir", tmp_path / "one"])
    assert code == 0, err
    ranks = two_ranks([*argv, "--out-dir", tmp_path / "two", "--num-nodes", "2"])
    assert [r.returncode for r in ranks] == [0, 0], [r.stderr for r in ranks]
    same_pngs(tmp_path / "one", tmp_path / "two")
    assert len([f for f in files(tmp_path / "two") if f.startswith("drive_bag/") and f.endswith(".png")]) == 2
