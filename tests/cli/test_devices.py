"""``complete --input-dir --devices N``: N processes (CPU here) write the files one process writes; a process
that fails on a frame does not lose the other processes' frames, and ``--resume`` completes the rest; a
``--devices`` beyond the machine is refused in one line."""

from __future__ import annotations

import csv
import io
import json
import os

import pytest

from crfdepth.cli.arguments import MAX_DEVICES
from crfdepth.cli.evaluate import CSV_NAME, JSON_NAME
from crfdepth.runs import folder as complete_folder
from tests.cli.frames import FAST, files, png, run, same_pngs, same_report, stem, write_folder

COUNT = 5


@pytest.fixture(scope="module")
def folder(tmp_path_factory):
    return write_folder(tmp_path_factory.mktemp("devices") / "val_selection_cropped", COUNT)


def _argv(data, out, *extra) -> list:
    return ["complete", "--input-dir", data, "--out-dir", out / "d", "--out-std-dir", out / "s", *extra, *FAST]


@pytest.mark.skipif(len(os.sched_getaffinity(0)) < 2, reason="needs 2 CPU cores")
@pytest.mark.parametrize("batch_size", [1, 2])
def test_two_processes_write_what_one_writes(folder, tmp_path, batch_size):
    one, two = tmp_path / "one", tmp_path / "two"
    assert run(_argv(folder, one, "--batch-size", batch_size))[0] == 0
    code, _, err = run(_argv(folder, two, "--batch-size", batch_size, "--devices", "2"))
    assert code == 0, err
    for sub in ("d", "s"):
        same_pngs(one / sub, two / sub)


@pytest.mark.skipif(len(os.sched_getaffinity(0)) < 2, reason="needs 2 CPU cores")
def test_a_process_failing_on_a_frame_keeps_the_others_work(folder, tmp_path, monkeypatch):
    """Frame 2's image goes away after the check pass: the process dealt frames 0, 2, 4 stops at frame 2; the
    other writes frames 1 and 3; frame 2 is listed in failed.csv, and --resume completes frames 2 and 4."""
    image = folder / "image" / f"{stem('image', 2)}.png"
    hidden = image.with_suffix(".bak")
    real = complete_folder.in_processes

    def after_the_checks(*args, **kwargs):
        image.rename(hidden)
        return real(*args, **kwargs)

    monkeypatch.setattr(complete_folder, "in_processes", after_the_checks)
    out = tmp_path / "o"
    try:
        code, _, err = run(_argv(folder, out, "--devices", "2"))
    finally:
        hidden.rename(image)
    assert code == 2 and err.startswith("crfdepth complete: error: process 1/2: ")
    assert "[1 process(es) stopped; 3 of 5 frame(s) written to" in err and "--resume completes the others" in err
    assert [f for f in files(out / "d") if f.endswith(".png")] == [png(0), png(1), png(3)]
    failed = (out / "d" / "failed.csv").read_text().splitlines()
    assert len(failed) == 2 and failed[1].startswith(stem("velodyne_raw", 2))
    monkeypatch.undo()
    assert run(_argv(folder, out, "--devices", "2", "--resume"))[0] == 0
    whole = tmp_path / "whole"
    assert run(_argv(folder, whole))[0] == 0
    for sub in ("d", "s"):
        same_pngs(whole / sub, out / sub)


@pytest.mark.skipif(len(os.sched_getaffinity(0)) >= MAX_DEVICES, reason=f"{MAX_DEVICES} or more CPU cores")
def test_more_devices_than_the_machine_has_is_refused(folder, tmp_path):
    code, _, err = run(_argv(folder, tmp_path / "o", "--devices", str(MAX_DEVICES)))
    assert code == 2 and err.startswith(f"crfdepth complete: error: --devices {MAX_DEVICES}: with --device cpu each "
                                        "process needs a CPU core of its own and this machine has ")
    code, _, err = run(_argv(folder, tmp_path / "o", "--devices", "4096"))
    assert code == 2 and err == f"crfdepth complete: error: --devices: expected an integer in [1, {MAX_DEVICES}], got '4096'\n"
    assert not (tmp_path / "o").exists()
    code, _, err = run(["complete", "--image", "a.png", "--sparse", "b.png", "--intrinsics", "k.txt", "--out",
                        tmp_path / "o.png", "--devices", "2"])
    assert code == 2 and "--devices 2: applies to --input-dir" in err


@pytest.mark.skipif(len(os.sched_getaffinity(0)) < 2, reason="needs 2 CPU cores")
@pytest.mark.parametrize("batch_size", [1, 2])
def test_evaluate_with_two_processes_reports_what_one_reports(folder, tmp_path, batch_size):
    """Same CSV rows in input order and the same JSON (means over all frames), within float tolerance."""
    reports = {}
    for devices in (1, 2):
        out = tmp_path / f"e{devices}"
        code, _, err = run(["evaluate", "--layout", "val_selection", "--data", folder, "--out-dir", out, "--std",
                            "--batch-size", batch_size, "--devices", devices, "--potentials", "colour", "--quiet"])
        assert code == 0, err
        reports[devices] = (json.loads((out / JSON_NAME).read_text()),
                            list(csv.DictReader(io.StringIO((out / CSV_NAME).read_text()))))
    (one, one_rows), (two, two_rows) = reports[1], reports[2]
    assert [r["name"] for r in two_rows] == [r["name"] for r in one_rows] and len(one_rows) == COUNT
    for a, b in zip(one_rows, two_rows):
        for key in a:
            if key != "name":
                assert float(b[key]) == pytest.approx(float(a[key]), rel=1e-6, abs=1e-9), key
    assert same_report(two, one)
