"""Output folders are locked by the run that writes them (crfdepth.io.files.lock_folder,
crfdepth.runs.outputs.output_folders): a second ``complete`` / ``evaluate`` run into a folder that
another run is writing is refused naming that run; a lock left by a run that is gone is taken
over; the lock is removed when the run ends, whatever the reason.

"Another run" is simulated in this process: a run holds its lock while its model computes, so
the second run is started from inside the first run's model call (the same pid, which counts as
running), or a lock file is written for a process that is running (``sleep``) or gone.
"""

from __future__ import annotations

import json
import logging
import os
import socket
import subprocess
import sys
from pathlib import Path

import pytest

from crfdepth.io.files import LOCK_NAME, FolderLockedError, lock_folder
from crfdepth.runs import folder_frames
from crfdepth.runs.resume import RUN_RECORD
from crfdepth.runs.skip_bad import FAILED_CSV
from tests.cli.frames import FAST, files, png, run, write_folder


@pytest.fixture(scope="module")
def folder(tmp_path_factory) -> Path:
    return write_folder(tmp_path_factory.mktemp("frames") / "val_selection_cropped", 3)


def _lock_of(pid: int, host: str | None = None, command: str = "crfdepth complete --input-dir A --out-dir B") -> str:
    return json.dumps({"pid": pid, "host": host or socket.gethostname(), "started": "2024-05-01T12:00:03+00:00",
                       "command": command, "token": "x"})


@pytest.fixture
def sleeper():
    """A running process that is not this one."""
    process = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(60)"])
    yield process.pid
    process.kill()
    process.wait()


def _dead_pid() -> int:
    process = subprocess.Popen([sys.executable, "-c", "pass"])
    process.wait()
    return process.pid


def test_second_run_into_the_same_out_dir_is_refused_naming_the_first(folder, tmp_path, monkeypatch):
    """While run 1 computes, run 2 into its --out-dir exits 2 naming run 1; run 1 then finishes normally,
    writes every frame and leaves no lock."""
    out = tmp_path / "out"
    monkeypatch.setattr(sys, "argv", ["/usr/bin/crfdepth", "complete", "--input-dir", "A", "--out-dir", "B"])
    inner = {}
    real = folder_frames.complete_checked

    def first_run_computing(*args, **kwargs):
        if not inner:  # once, while run 1 holds its folders
            inner["lock"] = json.loads((out / LOCK_NAME).read_text())
            inner["result"] = run(["complete", "--input-dir", folder, "--out-dir", out, *FAST])
            inner["files"] = files(out)
        return real(*args, **kwargs)

    monkeypatch.setattr(folder_frames, "complete_checked", first_run_computing)
    code, _, err = run(["complete", "--input-dir", folder, "--out-dir", out, *FAST])
    assert code == 0, err
    second_code, second_out, second_err = inner["result"]
    assert second_code == 2 and second_out == ""
    lock = inner["lock"]
    assert lock["pid"] == os.getpid() and lock["host"] == socket.gethostname()
    assert lock["command"] == "crfdepth complete --input-dir A --out-dir B"
    assert second_err == (f"crfdepth complete: error: --out-dir: the folder {out} is being written by another "
                          f"crfdepth run (pid {os.getpid()} on {socket.gethostname()}, started {lock['started']}: "
                          f"crfdepth complete --input-dir A --out-dir B); wait for it to finish or choose another "
                          f"folder; if that run is gone, delete {out / LOCK_NAME}\n")
    assert inner["files"] == [LOCK_NAME]  # run 2 wrote nothing (run 1 had not written its first frame yet)
    assert files(out) == sorted([png(i) for i in range(3)] + [RUN_RECORD])  # run 1 complete, its lock removed


@pytest.mark.parametrize("flag", ["--out-dir", "--out-std-dir", "--vis"])
def test_a_folder_locked_by_a_running_process_is_refused(folder, tmp_path, sleeper, flag):
    targets = {"--out-dir": tmp_path / "out", "--out-std-dir": tmp_path / "std", "--vis": tmp_path / "vis"}
    targets[flag].mkdir()
    (targets[flag] / LOCK_NAME).write_text(_lock_of(sleeper))
    code, out, err = run(["complete", "--input-dir", folder, *[a for kv in targets.items() for a in kv], *FAST])
    assert code == 2 and out == ""
    assert err.splitlines()[0].startswith(f"crfdepth complete: error: {flag}: the folder {targets[flag]} is being "
                                          f"written by another crfdepth run (pid {sleeper} on ")
    assert "started 2024-05-01T12:00:03+00:00: crfdepth complete --input-dir A --out-dir B" in err
    assert err.endswith(f"if that run is gone, delete {targets[flag] / LOCK_NAME}\n")
    for name, target in targets.items():  # nothing written anywhere; the other run's lock untouched
        assert (files(target) if target.exists() else []) == ([LOCK_NAME] if name == flag else [])
    assert json.loads((targets[flag] / LOCK_NAME).read_text())["pid"] == sleeper


def test_a_lock_of_another_host_is_respected(folder, tmp_path):
    """The pid of another machine (a shared folder) cannot be checked: the lock holds."""
    (tmp_path / "out").mkdir()
    (tmp_path / "out" / LOCK_NAME).write_text(_lock_of(_dead_pid(), host="elsewhere.example"))
    code, _, err = run(["complete", "--input-dir", folder, "--out-dir", tmp_path / "out", *FAST])
    assert code == 2 and "pid" in err and "on elsewhere.example" in err
    assert files(tmp_path / "out") == [LOCK_NAME]


def test_a_stale_lock_is_taken_over_with_a_warning(folder, tmp_path, caplog):
    out = tmp_path / "out"
    out.mkdir()
    dead = _dead_pid()
    (out / LOCK_NAME).write_text(_lock_of(dead))
    with caplog.at_level(logging.WARNING, logger="crfdepth.io.files"):
        code, _, err = run(["complete", "--input-dir", folder, "--out-dir", out, *FAST])
    assert code == 0, err
    warnings = [r.getMessage() for r in caplog.records if r.name == "crfdepth.io.files"]
    assert len(warnings) == 1 and warnings[0].startswith(f"--out-dir: taking over the lock of crfdepth run (pid {dead} ")
    assert "no longer running" in warnings[0]
    assert files(out) == sorted([png(i) for i in range(3)] + [RUN_RECORD])  # completed, and the lock removed


def test_an_unreadable_lock_counts_as_held(folder, tmp_path):
    (tmp_path / "out").mkdir()
    (tmp_path / "out" / LOCK_NAME).write_text("")
    code, _, err = run(["complete", "--input-dir", folder, "--out-dir", tmp_path / "out", *FAST])
    assert code == 2
    assert "is being written by a crfdepth run whose lock file cannot be read" in err.splitlines()[0]


def test_lock_folder_is_exclusive_and_released(tmp_path):
    with lock_folder(tmp_path, "--out-dir") as lock:
        assert lock == tmp_path / LOCK_NAME and json.loads(lock.read_text())["pid"] == os.getpid()
        with pytest.raises(FolderLockedError, match=r"^--out-dir: the folder .* is being written by another"):
            with lock_folder(tmp_path, "--out-dir"):
                pass  # pragma: no cover
        assert lock.exists()  # the refused attempt leaves the holder's lock alone
    assert not (tmp_path / LOCK_NAME).exists()
    with pytest.raises(RuntimeError):
        with lock_folder(tmp_path, "--out-dir"):
            raise RuntimeError("a failing run")
    assert list(tmp_path.iterdir()) == []


def test_lock_released_and_new_folder_removed_after_a_bad_frame(folder, tmp_path, monkeypatch):
    """A failure while writing (here a non-finite model output in frame 2) releases the lock."""
    real = folder_frames.complete_checked
    calls = []

    def nan_second(*args, **kwargs):
        calls.append(1)
        depth, std = real(*args, **kwargs)
        return (depth * float("nan"), std) if len(calls) == 2 else (depth, std)

    monkeypatch.setattr(folder_frames, "complete_checked", nan_second)
    code, _, err = run(["complete", "--input-dir", folder, "--out-dir", tmp_path / "out", *FAST])
    assert code == 2 and "non-finite" in err and "1 of 3 frame(s) written" in err and "--resume completes" in err
    # no lock left; the failed frame listed, and the record of the unfinished run for --resume
    assert files(tmp_path / "out") == sorted([png(0), RUN_RECORD, FAILED_CSV])
    assert (tmp_path / "out" / FAILED_CSV).read_text().splitlines()[1].startswith(png(1)[:-4])


def test_evaluate_out_dir_is_locked(folder, tmp_path, sleeper):
    out = tmp_path / "evaluation"
    out.mkdir()
    (out / LOCK_NAME).write_text(_lock_of(sleeper, command="crfdepth evaluate --layout val_selection"))
    code, _, err = run(["evaluate", "--layout", "val_selection", "--data", folder, "--out-dir", out,
                        "--potentials", "colour", "--quiet"])
    assert code == 2
    assert err.splitlines()[0].startswith(f"crfdepth evaluate: error: --out-dir: the folder {out} is being written "
                                          f"by another crfdepth run (pid {sleeper} ")
    assert files(out) == [LOCK_NAME]


def test_evaluate_holds_and_releases_its_lock(folder, tmp_path, monkeypatch):
    from crfdepth.runs import evaluation as evaluate_frames

    out = tmp_path / "evaluation"
    seen = []
    real = evaluate_frames.complete_checked

    def looking(*args, **kwargs):
        seen.append((out / LOCK_NAME).is_file())
        return real(*args, **kwargs)

    monkeypatch.setattr(evaluate_frames, "complete_checked", looking)
    code, _, err = run(["evaluate", "--layout", "val_selection", "--data", folder, "--out-dir", out,
                        "--potentials", "colour", "--quiet"])
    assert code == 0, err
    assert seen == [True] * 3
    assert files(out) == ["per_frame.csv", "summary.json"]


def test_a_folder_with_an_earlier_runs_outputs_is_replaced_in_place(folder, tmp_path, caplog):
    """Re-running into a finished run's folder is allowed: its PNGs are replaced (atomically); PNGs that this run
    does not write stay, with a warning that counts them."""
    out = tmp_path / "out"
    out.mkdir()
    (out / png(1)).write_bytes(b"an earlier run's PNG")
    (out / "other_frame.png").write_bytes(b"a PNG of other frames")
    with caplog.at_level(logging.WARNING):
        code, _, err = run(["complete", "--input-dir", folder, "--out-dir", out, *FAST])
    assert code == 0, err
    assert files(out) == sorted([png(i) for i in range(3)] + ["other_frame.png", RUN_RECORD])
    assert (out / png(1)).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"  # replaced by this run's PNG
    assert any("already holds 1 PNG file(s) that this run does not write" in r.getMessage() for r in caplog.records)


# --------------------------------------------------------------------------- bag mode


def _bag_argv(bag: Path, out: Path, *extra) -> list:
    from tests.io.ros.bags import IMAGE_TOPIC, POINTS_TOPIC

    return ["complete", "--bag", bag, "--image-topic", IMAGE_TOPIC, "--points-topic", POINTS_TOPIC, "--out-dir", out,
            *extra, *FAST]


@pytest.fixture
def bag(tmp_path) -> Path:
    pytest.importorskip("rosbags")
    from tests.io.ros.bags import write_bag

    return write_bag(tmp_path / "in", "mcap", count=2).path


def test_bag_out_dir_locked_by_a_running_process(bag, tmp_path, sleeper):
    out = tmp_path / "d"
    out.mkdir()
    (out / LOCK_NAME).write_text(_lock_of(sleeper))
    code, _, err = run(_bag_argv(bag, out, "--out-bag", tmp_path / "out"))
    assert code == 2
    assert err.splitlines()[0].startswith(f"crfdepth complete: error: --out-dir: the folder {out} is being written "
                                          f"by another crfdepth run (pid {sleeper} ")
    assert files(out) == [LOCK_NAME] and not (tmp_path / "out").exists()


def test_bag_out_dir_with_an_earlier_index_needs_overwrite(bag, tmp_path):
    """index.csv lists exactly the PNGs of one run: a folder with an earlier run's index.csv is refused (nothing
    written) unless --overwrite, which replaces the index with this run's."""
    import csv

    from tests.io.ros.bags import PERIOD_NS, START_NS

    out = tmp_path / "d"
    out.mkdir()
    (out / "index.csv").write_text("timestamp_ns,depth_png\n1,1.png\n")
    code, _, err = run(_bag_argv(bag, out))
    assert code == 2
    assert err == (f"crfdepth complete: error: --out-dir: {out} already holds the index.csv of an earlier run; give "
                   f"--overwrite to replace it (and the PNGs of the same names), or choose another folder\n")
    assert files(out) == ["index.csv"]
    code, _, err = run(_bag_argv(bag, out, "--overwrite"))
    assert code == 0, err
    with open(out / "index.csv", newline="") as handle:
        rows = list(csv.DictReader(handle))
    stamps = [str(START_NS + k * PERIOD_NS) for k in range(2)]
    assert [r["depth_png"] for r in rows] == [f"{s}.png" for s in stamps]
    assert files(out) == sorted([f"{s}.png" for s in stamps] + ["index.csv"])


def test_overwrite_needs_bag(folder, tmp_path):
    code, _, err = run(["complete", "--input-dir", folder, "--out-dir", tmp_path / "out", "--overwrite", *FAST])
    assert code == 2 and err == "crfdepth complete: error: --overwrite: bag options need --bag\n"
    assert not (tmp_path / "out").exists()
