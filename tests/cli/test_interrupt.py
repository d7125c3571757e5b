"""Ctrl-C in a folder or bag run: exit status 130, one line saying how many frames were written and
where, a consistent folder (bag: index.csv listing exactly the PNGs written, no --out-bag), the lock
released. The interrupt is raised by the model call after N frames (monkeypatch)."""

from __future__ import annotations

import csv

import pytest

from crfdepth import api
from crfdepth.cli import complete_bag
from crfdepth.runs import folder_frames as complete_folder
from crfdepth.runs import outputs
from crfdepth.runs.resume import RUN_RECORD
from tests.cli.frames import FAST, files, png, run, write_folder


def _interrupt_after(monkeypatch, module, name: str, calls: int) -> None:
    """``module.name`` raises KeyboardInterrupt on call ``calls + 1``."""
    real, done = getattr(module, name), []

    def interrupting(*args, **kwargs):
        if len(done) == calls:
            raise KeyboardInterrupt
        done.append(1)
        return real(*args, **kwargs)

    monkeypatch.setattr(module, name, interrupting)


@pytest.mark.parametrize("batch_size", [1, 2])
def test_folder_run_reports_the_frames_written(tmp_path, monkeypatch, batch_size):
    data = write_folder(tmp_path / "val_selection_cropped", 5)
    out = tmp_path / "out"
    _interrupt_after(monkeypatch, complete_folder, "complete_checked", 2)  # in the 3rd model call
    code, stdout, err = run(["complete", "--input-dir", data, "--out-dir", out, "--batch-size", batch_size, *FAST])
    written = 2 * batch_size
    assert code == 130 and stdout == ""
    assert err == (f"crfdepth complete: interrupted after {written} of 5 frame(s) written to {out}; --resume "
                   f"completes the others\n")
    # no lock, no temporary file; the record of the unfinished run for --resume
    assert files(out) == sorted([png(i) for i in range(written)] + [RUN_RECORD])


def test_folder_run_interrupted_while_checking_writes_nothing(tmp_path, monkeypatch):
    data = write_folder(tmp_path / "val_selection_cropped", 3)
    _interrupt_after(monkeypatch, complete_folder, "_check_frame", 1)
    code, _, err = run(["complete", "--input-dir", data, "--out-dir", tmp_path / "out", *FAST])
    assert code == 130
    assert err == "crfdepth complete: interrupted while checking the frames (1 of 3 checked); nothing written\n"
    assert not (tmp_path / "out").exists()


def test_folder_run_interrupted_before_its_first_frame_leaves_no_folder(tmp_path, monkeypatch):
    data = write_folder(tmp_path / "val_selection_cropped", 2)
    out = tmp_path / "new" / "out"
    (tmp_path / "new").mkdir()
    _interrupt_after(monkeypatch, complete_folder, "complete_checked", 0)
    code, _, err = run(["complete", "--input-dir", data, "--out-dir", out, "--vis", *FAST])
    assert code == 130 and err == (f"crfdepth complete: interrupted after 0 of 2 frame(s) written to {out}; "
                                   f"--resume completes the others\n")
    assert list((tmp_path / "new").iterdir()) == []  # the empty folders it had created (out, out_vis) are gone


@pytest.fixture
def bag(tmp_path):
    pytest.importorskip("rosbags")
    from tests.io.ros.bags import write_bag

    return write_bag(tmp_path / "in", "mcap", count=4)


def _bag_argv(recorded, out, *extra) -> list:
    from tests.io.ros.bags import IMAGE_TOPIC, POINTS_TOPIC

    return ["complete", "--bag", recorded.path, "--image-topic", IMAGE_TOPIC, "--points-topic", POINTS_TOPIC,
            "--out-dir", out, *extra, *FAST]


def test_bag_run_leaves_an_index_of_the_frames_written(bag, tmp_path, monkeypatch):
    out = tmp_path / "d"
    _interrupt_after(monkeypatch, api, "complete_depth", 2)
    code, _, err = run(_bag_argv(bag, out, "--out-std-dir", tmp_path / "std", "--out-bag", tmp_path / "out"))
    assert code == 130
    assert err == (f"crfdepth complete: interrupted after 2 of 4 frame(s) written to {out} and listed in its "
                   f"index.csv; no --out-bag written\n")
    with open(out / "index.csv", newline="") as handle:
        rows = list(csv.DictReader(handle))
    names = [f"{stamp}.png" for stamp in bag.image_ns[:2]]
    assert [r["depth_png"] for r in rows] == names and [r["std_png"] for r in rows] == names
    assert files(out) == sorted(names + ["index.csv"]) and files(tmp_path / "std") == names
    assert not (tmp_path / "out").exists() and not list(tmp_path.glob(".out.*"))


def test_bag_frame_cut_short_is_not_indexed(bag, tmp_path, monkeypatch):
    """Ctrl-C inside the 2nd frame's writing, before its depth PNG lands: index.csv lists frame 1 only."""
    out = tmp_path / "d"
    _interrupt_after(monkeypatch, complete_bag, "write_frame", 1)
    code, _, err = run(_bag_argv(bag, out))
    assert code == 130 and "interrupted after 1 of 4 frame(s) written" in err
    with open(out / "index.csv", newline="") as handle:
        assert [r["depth_png"] for r in csv.DictReader(handle)] == [f"{bag.image_ns[0]}.png"]
    assert files(out) == sorted([f"{bag.image_ns[0]}.png", "index.csv"])


def test_bag_run_interrupted_while_checking_writes_nothing(bag, tmp_path, monkeypatch):
    _interrupt_after(monkeypatch, complete_bag, "points_to_sparse", 1)
    code, _, err = run(_bag_argv(bag, tmp_path / "d"))
    assert code == 130
    assert err == "crfdepth complete: interrupted while checking the frames (1 of 4 checked); nothing written\n"
    assert not (tmp_path / "d").exists()


def test_output_folders_release_on_interrupt(tmp_path):
    """The context manager itself: lock removed and the created (empty) folder removed on Ctrl-C."""
    with pytest.raises(KeyboardInterrupt):
        with outputs.output_folders([("--out-dir", str(tmp_path / "a")), ("--out-std-dir", None)]) as folders:
            assert folders[1] is None and (folders[0] / ".crfdepth.lock").is_file()
            raise KeyboardInterrupt
    assert list(tmp_path.iterdir()) == []
