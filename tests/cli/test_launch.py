"""``--strategy``: ``ddp`` without a launcher starts the ``--devices`` ranks itself (torch's elastic launcher),
which write the files and the report of one process, a bad frame surfacing as rank 0's one-line error
(exit 2); ``spawn`` under a launcher or across nodes, and an unknown strategy, are refused in one line."""

from __future__ import annotations

import json
import os
import signal
from types import SimpleNamespace

import pytest

from crfdepth.cli.evaluate import JSON_NAME
from crfdepth.errors import InputError
from crfdepth.runs import launch, ranks
from tests.cli.frames import FAST, run, same_pngs, same_report, write_folder
from tests.cli.launching import alone

COUNT = 5
two_cores = pytest.mark.skipif(len(os.sched_getaffinity(0)) < 2, reason="needs 2 CPU cores")


@pytest.fixture(scope="module")
def folder(tmp_path_factory):
    return write_folder(tmp_path_factory.mktemp("launch") / "val_selection_cropped", COUNT)


@pytest.fixture
def no_launcher(monkeypatch):
    for name in ("WORLD_SIZE", "RANK", "MASTER_ADDR", "MASTER_PORT"):
        monkeypatch.delenv(name, raising=False)


def _argv(data, out, *extra) -> list:
    return ["complete", "--input-dir", data, "--out-dir", out / "d", "--out-std-dir", out / "s", *extra, *FAST]


@two_cores
def test_ddp_without_a_launcher_starts_two_ranks_that_write_what_one_process_writes(folder, tmp_path):
    assert run(_argv(folder, tmp_path / "one", "--batch-size", "2"))[0] == 0
    done = alone(["-v", *_argv(folder, tmp_path / "two", "--batch-size", "2", "--strategy", "ddp", "--devices", "2")])
    assert done.returncode == 0, done.stderr
    assert "crfdepth complete: info: joined the group as rank 1/2 (process 1/2 of this node)" in done.stderr
    for sub in ("d", "s"):
        same_pngs(tmp_path / "one" / sub, tmp_path / "two" / sub)  # the same files: no lock or record left


@two_cores
def test_ddp_ranks_refuse_a_bad_frame_in_one_line_with_exit_status_2(tmp_path):
    bad = write_folder(tmp_path / "bad" / "val_selection_cropped", 3, bad={1: "zero sparse"})
    done = alone(_argv(bad, tmp_path / "o", "--strategy", "ddp", "--devices", "2"))
    assert done.returncode == 2
    lines = done.stderr.splitlines()
    assert len(lines) == 1 and lines[0].startswith("crfdepth complete: error: frame 2/3 ")
    assert "every pixel is 0 (no LiDAR point)" in lines[0] and "nothing written" in lines[0]
    assert not (tmp_path / "o").exists()


@two_cores
def test_evaluate_with_ddp_ranks_reports_what_one_process_reports(folder, tmp_path):
    argv = ["evaluate", "--layout", "val_selection", "--data", folder, "--std", "--potentials", "colour", "--quiet"]
    code, _, err = run([*argv, "--out-dir", tmp_path / "one"])
    assert code == 0, err
    done = alone([*argv, "--out-dir", tmp_path / "two", "--strategy", "ddp", "--devices", "2"])
    assert done.returncode == 0, done.stderr
    one, two = (json.loads((tmp_path / d / JSON_NAME).read_text()) for d in ("one", "two"))
    assert two["frames"] == COUNT and same_report(two, one)


def test_ddp_on_one_device_runs_in_this_process(folder, tmp_path, no_launcher, monkeypatch):
    def no_ranks(args):
        raise AssertionError("ranks started for --devices 1")

    monkeypatch.setattr(ranks, "launch_ranks", no_ranks)
    code, _, err = run(_argv(folder, tmp_path / "o", "--strategy", "ddp"))
    assert code == 0, err
    assert len(list((tmp_path / "o" / "d").glob("*.png"))) == COUNT


def test_spawn_is_refused_across_nodes_and_under_a_launcher(folder, tmp_path, no_launcher, monkeypatch):
    for command in (_argv(folder, tmp_path / "o"), ["evaluate", "--layout", "val_selection", "--data", folder,
                                                      "--out-dir", tmp_path / "o", *FAST]):
        code, _, err = run([*command, "--strategy", "spawn", "--num-nodes", "2"])
        name = command[0]
        assert code == 2 and err == (f"crfdepth {name}: error: --strategy spawn: starts the --devices processes on "
                                     f"this machine only, got --num-nodes 2; give --strategy ddp (or auto) and start "
                                     f"the command on every node with torchrun\n")
    monkeypatch.setenv("WORLD_SIZE", "2")
    code, _, err = run([*_argv(folder, tmp_path / "o"), "--strategy", "spawn", "--devices", "2"])
    assert code == 2 and err.count("\n") == 1
    assert err.startswith("crfdepth complete: error: --strategy spawn: expected a command started alone") \
        and "got WORLD_SIZE=2 from a launcher" in err
    assert not (tmp_path / "o").exists()


def test_an_unknown_strategy_or_one_without_a_folder_is_refused(folder, tmp_path):
    code, _, err = run([*_argv(folder, tmp_path / "o"), "--strategy", "fsdp"])
    assert code == 2 and err == "crfdepth complete: error: --strategy: expected one of 'auto', 'spawn', 'ddp', got 'fsdp'\n"
    code, _, err = run(["complete", "--image", "a.png", "--sparse", "b.png", "--intrinsics", "k.txt", "--out",
                        tmp_path / "o.png", "--strategy", "ddp"])
    assert code == 2 and err == ("crfdepth complete: error: --strategy ddp: applies to --input-dir and --input-list "
                                 "(folders of frames)\n")
    assert not (tmp_path / "o").exists()


def _failure(exitcode: int, local_rank: int):
    return SimpleNamespace(exitcode=exitcode, local_rank=local_rank,
                           signal_name=lambda: signal.Signals(-exitcode).name if exitcode < 0 else "")


def test_the_exit_status_is_rank_0s_or_the_failed_ranks_with_its_output_where_rank_0_cannot_report(tmp_path, capsys):
    """The launcher stops the other ranks when one fails: rank 0's status when it ended by itself; the failed
    rank's status when its error is one every rank raises (2, 130: rank 0 printed it); else that rank's logged
    output (a bug's traceback) is shown, or a rank killed by a signal is named."""
    log = tmp_path / "run_1" / "attempt_0" / "1" / "stderr.log"
    log.parent.mkdir(parents=True)
    log.write_text("Traceback (most recent call last):\nRuntimeError: a bug\n")
    assert launch._exit_status({0: _failure(2, 0), 1: _failure(2, 1)}, 2, tmp_path) == 2
    assert launch._exit_status({0: _failure(-15, 0), 1: _failure(130, 1)}, 2, tmp_path) == 130
    assert capsys.readouterr().err == ""
    assert launch._exit_status({0: _failure(-15, 0), 1: _failure(1, 1)}, 2, tmp_path) == 1
    assert capsys.readouterr().err == "Traceback (most recent call last):\nRuntimeError: a bug\n"
    with pytest.raises(InputError, match=r"^--strategy ddp: rank 2/2 ended without reporting \(SIGKILL\)"):
        launch._exit_status({0: _failure(-15, 0), 1: _failure(-9, 1)}, 2, tmp_path)
