"""``complete --input-dir --resume``: a run stopped part-way and resumed writes the same files as one
uninterrupted run, byte for byte, for any batch size; the frames an earlier run finished are not done
again; another model or other options than the earlier run's, stopped or finished, are refused; a
finished folder resumed with its own options is left byte for byte as it is; a frame that fails when
completed is listed in failed.csv (and, with --skip-bad, the others are completed)."""

from __future__ import annotations

import filecmp
import json
import os

import pytest

from crfdepth.errors import InputError
from crfdepth.runs import folder as complete_folder
from crfdepth.runs import folder_frames
from crfdepth.runs.resume import RUN_RECORD
from tests.cli.frames import FAST, files, png, run, write_folder

COUNT = 5


@pytest.fixture(scope="module")
def folder(tmp_path_factory):
    return write_folder(tmp_path_factory.mktemp("resume") / "val_selection_cropped", COUNT)


def _argv(data, out, *extra, quiet: bool = True) -> list:
    return ["complete", "--input-dir", data, "--out-dir", out / "d", "--out-std-dir", out / "s", "--vis", out / "v",
            *extra, *(FAST if quiet else [f for f in FAST if f != "--quiet"])]


def _stop_after(monkeypatch, batches: int) -> list:
    """The model step raises KeyboardInterrupt on call ``batches + 1``; returns the list of the batches' names."""
    return _batches_seen(monkeypatch, stop_after=batches)


def _batches_seen(monkeypatch, stop_after: int | None = None) -> list:
    """The names of each batch the folder run takes to the model, in order; with ``stop_after``, KeyboardInterrupt
    as batch ``stop_after + 1`` would go to the model."""
    real, seen = folder_frames.frame_batches, []

    def batches(*args, **kwargs):
        for batch in real(*args, **kwargs):
            if len(seen) == stop_after:
                raise KeyboardInterrupt
            seen.append(list(batch.names))
            yield batch

    monkeypatch.setattr(folder_frames, "frame_batches", batches)
    return seen


def _snapshot(out) -> dict:
    """Every file under ``out`` (hidden ones included) with its bytes and modification time."""
    return {name: ((out / name).read_bytes(), (out / name).stat().st_mtime_ns) for name in files(out)}


def _same_tree(a, b) -> None:
    assert files(a) == files(b)
    for name in files(a):
        if name.endswith(".png"):
            assert filecmp.cmp(a / name, b / name, shallow=False), name


@pytest.mark.parametrize("batch_size", [1, 2])
def test_stopped_and_resumed_equals_uninterrupted_file_for_file(folder, tmp_path, monkeypatch, batch_size):
    whole, parts = tmp_path / "whole", tmp_path / "parts"
    assert run(_argv(folder, whole, "--batch-size", batch_size))[0] == 0
    seen = _stop_after(monkeypatch, 1)
    code, _, err = run(_argv(folder, parts, "--batch-size", batch_size))
    assert code == 130 and f"after {batch_size} of {COUNT} frame(s) written" in err
    monkeypatch.undo()
    done_first = set(seen[0])
    seen = _batches_seen(monkeypatch)
    code, _, _ = run(_argv(folder, parts, "--batch-size", batch_size, "--resume"))
    assert code == 0
    assert not done_first & {name for names in seen for name in names}  # the finished frames are not done again
    assert sum(len(names) for names in seen) == COUNT - batch_size
    for sub in ("d", "s", "v"):
        _same_tree(whole / sub, parts / sub)


def test_a_batch_cut_short_is_done_again_whole(folder, tmp_path, monkeypatch):
    """Stopped between the frames of a batch of 2: the batch is redone with its partner, as it was planned."""
    out = tmp_path / "o"
    assert run(_argv(folder, out, "--batch-size", "2"))[0] == 0
    (out / "s" / png(3)).unlink()  # frame 3 lost its std PNG: frames 2-3 (one batch) are unfinished
    seen = _batches_seen(monkeypatch)
    code, stdout, _ = run(_argv(folder, out, "--batch-size", "2", "--resume", quiet=False))
    assert code == 0 and [len(names) for names in seen] == [2] and (out / "s" / png(3)).is_file()
    assert f"{COUNT - 1} of {COUNT} frame(s) were finished by an earlier run (--resume); 1 of them done again" in stdout


def test_resume_refuses_the_unfinished_run_of_another_model_or_options(folder, tmp_path, monkeypatch):
    out = tmp_path / "o"
    _stop_after(monkeypatch, 2)
    assert run(_argv(folder, out))[0] == 130
    monkeypatch.undo()
    record = json.loads((out / "d" / RUN_RECORD).read_text())  # the stopped run says what it was
    assert record["batch_size"] == 1 and record["std"] is True and len(record["weights_sha256"]) == 64
    code, _, err = run(_argv(folder, out, "--resume", "--batch-size", "2"))
    assert code == 2 and err.startswith(f"crfdepth complete: error: --resume: {out / 'd'} holds the unfinished run "
                                        f"of another model or options (batch_size 1 -> 2; ")
    code, _, err = run(_argv(folder, out, "--resume", "--weights", "paper"))
    assert code == 2 and "of another model or options (model, weights_sha256 " in err
    assert run(_argv(folder, out, "--resume"))[0] == 0
    # finished: the record stays, marked so (hidden: zip *.png of the folder, a submission, leaves it out)
    assert json.loads((out / "d" / RUN_RECORD).read_text()) == {**record, "finished": True}
    assert [name for name in files(out / "d") if name.startswith(".")] == [RUN_RECORD]


def _other_potentials(data, out, *extra) -> list:
    """:func:`_argv` with ``--potentials colour,normal`` instead of FAST's ``colour``."""
    argv = _argv(data, out, *extra)
    return [*argv[:argv.index("--potentials")], "--potentials", "colour,normal", "--quiet"]


@pytest.mark.parametrize(("other", "what"), [
    (lambda data, out: _argv(data, out, "--resume", "--weights", "paper"), "model, weights_sha256 "),
    (lambda data, out: _other_potentials(data, out, "--resume"), "model"),
    (lambda data, out: _argv(data, out, "--resume", "--batch-size", "3"), "batch_size 1 -> 3; "),
], ids=["weights", "potentials", "batch-size"])
def test_resume_refuses_the_finished_run_of_another_model_or_options(folder, tmp_path, monkeypatch, other, what):
    """As for a stopped run: another model or options than the finished run's are refused, and nothing is written."""
    out = tmp_path / "o"
    assert run(_argv(folder, out))[0] == 0
    before = {sub: _snapshot(out / sub) for sub in ("d", "s", "v")}
    monkeypatch.setattr(folder_frames, "complete_checked", None)  # must not be called
    code, stdout, err = run(other(folder, out))
    assert code == 2 and stdout == ""
    assert err.splitlines()[0].startswith(f"crfdepth complete: error: --resume: {out / 'd'} holds the finished run of "
                                          f"another model or options ({what}")
    assert f"{out / 'd' / RUN_RECORD}); resume with its options, or complete into another --out-dir" in err
    assert {sub: _snapshot(out / sub) for sub in ("d", "s", "v")} == before  # nothing written, no lock left


def test_a_finished_folder_is_left_as_it_is(folder, tmp_path, monkeypatch):
    """--resume with the finished run's own options: nothing to do, and no byte of any file changes."""
    out = tmp_path / "o"
    assert run(_argv(folder, out))[0] == 0
    record = json.loads((out / "d" / RUN_RECORD).read_text())
    assert record["finished"] is True and record["batch_size"] == 1 and len(record["weights_sha256"]) == 64
    before = {sub: _snapshot(out / sub) for sub in ("d", "s", "v")}
    monkeypatch.setattr(folder_frames, "complete_checked", None)  # must not be called
    code, stdout, _ = run(_argv(folder, out, "--resume", quiet=False))
    assert code == 0 and f"{COUNT} of {COUNT} frame(s) were finished by an earlier run" in stdout
    assert {sub: _snapshot(out / sub) for sub in ("d", "s", "v")} == before


def test_a_rerun_without_resume_replaces_the_finished_record(folder, tmp_path):
    """Completing again into a finished folder, without --resume, replaces its files and its record: --resume then
    goes with the new run's options, and refuses the first run's."""
    out = tmp_path / "o"
    assert run(_argv(folder, out))[0] == 0
    first = json.loads((out / "d" / RUN_RECORD).read_text())
    assert run(_argv(folder, out, "--weights", "paper"))[0] == 0
    second = json.loads((out / "d" / RUN_RECORD).read_text())
    assert second["finished"] is True and second["weights_sha256"] != first["weights_sha256"]
    code, _, err = run(_argv(folder, out, "--resume"))
    assert code == 2 and f"{out / 'd'} holds the finished run of another model or options (model, " in err
    assert run(_argv(folder, out, "--resume", "--weights", "paper"))[0] == 0


@pytest.mark.skipif(len(os.sched_getaffinity(0)) < 2, reason="--devices 2 needs 2 CPU cores")
def test_a_run_stopped_before_its_first_frame_puts_the_finished_record_back(folder, tmp_path, monkeypatch):
    """A --devices run writes its record before its processes start; stopped before any frame is written, it puts
    back the record of the finished run whose files the folder still holds, so that --resume still knows them."""
    out = tmp_path / "o"
    assert run(_argv(folder, out))[0] == 0
    before = (out / "d" / RUN_RECORD).read_bytes()

    def stopped(*args, **kwargs):
        assert (out / "d" / RUN_RECORD).read_bytes() != before  # this run's record, written before its processes
        raise KeyboardInterrupt

    monkeypatch.setattr(complete_folder, "in_processes", stopped)
    code, _, err = run(_argv(folder, out, "--weights", "paper", "--devices", "2"))
    assert code == 130 and "interrupted" in err
    assert (out / "d" / RUN_RECORD).read_bytes() == before
    monkeypatch.undo()
    code, _, err = run(_argv(folder, out, "--resume", "--weights", "paper"))
    assert code == 2 and "holds the finished run of another model or options (model, " in err


def test_resume_applies_to_a_folder_only(tmp_path):
    code, _, err = run(["complete", "--image", "a.png", "--sparse", "b.png", "--intrinsics", "k.txt", "--out",
                        tmp_path / "o.png", "--resume"])
    assert code == 2 and "--resume: applies to --input-dir" in err


def test_a_frame_that_fails_is_listed_and_the_others_completed(folder, tmp_path, monkeypatch):
    real, calls = folder_frames.complete_checked, []

    def step(*args, **kwargs):  # one frame a call, in order: the third is frame 2
        calls.append(1)
        if len(calls) == 3:
            raise InputError("the model returned 3 non-finite depth value(s)")
        return real(*args, **kwargs)

    monkeypatch.setattr(folder_frames, "complete_checked", step)
    out = tmp_path / "o"
    code, stdout, _ = run(_argv(folder, out, "--skip-bad", quiet=False))
    assert code == 0 and "1 frame(s) failed (--skip-bad)" in stdout
    failed = (out / "d" / "failed.csv").read_text().splitlines()
    assert failed[0] == "frame,reason" and len(failed) == 2 and failed[1].startswith(png(2)[:-4])
    assert not (out / "d" / png(2)).exists() and len([f for f in files(out / "d") if f.endswith(".png")]) == COUNT - 1
    monkeypatch.undo()
    code, stdout, _ = run(_argv(folder, out, "--resume", quiet=False))  # fixed: the failed frame alone is completed
    assert code == 0 and f"{COUNT - 1} of {COUNT} frame(s) were finished by an earlier run" in stdout
    assert (out / "d" / png(2)).is_file() and not (out / "d" / "failed.csv").exists()
