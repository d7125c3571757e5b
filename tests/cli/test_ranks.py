"""``complete --input-dir --num-nodes 2``: two ranks joined as torchrun joins them (its environment, gloo)
write what one process writes; rank 0's refusal of a bad frame stops every rank alike; a run without the
launcher's environment, or with a group of another size, is refused in one line."""

from __future__ import annotations

import json

import pytest

from crfdepth.cli.evaluate import CSV_NAME, JSON_NAME
from tests.cli.frames import FAST, run, same_pngs, write_folder
from tests.cli.launching import two_ranks

COUNT = 5


@pytest.fixture(scope="module")
def folder(tmp_path_factory):
    return write_folder(tmp_path_factory.mktemp("ranks") / "val_selection_cropped", COUNT)


def _argv(data, out, *extra) -> list:
    return ["complete", "--input-dir", data, "--out-dir", out / "d", "--out-std-dir", out / "s", *extra, *FAST]


def test_two_nodes_write_what_one_process_writes(folder, tmp_path):
    assert run(_argv(folder, tmp_path / "one", "--batch-size", "2"))[0] == 0
    ranks = two_ranks(_argv(folder, tmp_path / "two", "--batch-size", "2", "--num-nodes", "2"))
    assert [r.returncode for r in ranks] == [0, 0], [r.stderr for r in ranks]
    for sub in ("d", "s"):
        same_pngs(tmp_path / "one" / sub, tmp_path / "two" / sub)  # the same files: no lock or record left


def test_a_bad_frame_stops_every_rank_alike(folder, tmp_path):
    bad = write_folder(tmp_path / "bad" / "val_selection_cropped", 3, bad={1: "zero sparse"})
    ranks = two_ranks(_argv(bad, tmp_path / "o", "--num-nodes", "2"))
    assert [r.returncode for r in ranks] == [2, 2]
    assert ranks[0].stderr.splitlines()[-1] == ranks[1].stderr.splitlines()[-1]
    assert "every pixel is 0 (no LiDAR point)" in ranks[1].stderr and "nothing written" in ranks[1].stderr
    assert not (tmp_path / "o").exists()


def test_num_nodes_needs_the_launcher_and_a_group_of_its_size(folder, tmp_path, monkeypatch):
    for name in ("WORLD_SIZE", "RANK", "MASTER_ADDR", "MASTER_PORT"):
        monkeypatch.delenv(name, raising=False)
    code, _, err = run(_argv(folder, tmp_path / "o", "--num-nodes", "2"))
    assert code == 2 and err.startswith("crfdepth complete: error: --num-nodes 2: start the command on every node "
                                        "with torchrun")
    monkeypatch.setenv("WORLD_SIZE", "3")
    code, _, err = run(_argv(folder, tmp_path / "o", "--num-nodes", "2"))
    assert code == 2 and "--num-nodes 2 --devices 1: expected 2 process(es) in all, the launcher started 3" in err
    assert not (tmp_path / "o").exists()


def test_evaluate_on_two_nodes_reports_what_one_process_reports(folder, tmp_path):
    argv = ["evaluate", "--layout", "val_selection", "--data", folder, "--std", "--potentials", "colour", "--quiet"]
    code, _, err = run([*argv, "--out-dir", tmp_path / "one"])
    assert code == 0, err
    ranks = two_ranks([*argv, "--out-dir", tmp_path / "two", "--num-nodes", "2"])
    assert [r.returncode for r in ranks] == [0, 0], [r.stderr for r in ranks]
    one = json.loads((tmp_path / "one" / JSON_NAME).read_text())
    two = json.loads((tmp_path / "two" / JSON_NAME).read_text())
    assert two.keys() == one.keys() and two["frames"] == one["frames"] == COUNT
    for group in ("metrics", "uncertainty"):
        assert two[group].keys() == one[group].keys()
        for key, value in one[group].items():
            assert two[group][key] == pytest.approx(value, rel=1e-6, abs=1e-9), (group, key)
    rows = [(tmp_path / d / CSV_NAME).read_text().splitlines() for d in ("one", "two")]
    assert [r.split(",")[0] for r in rows[0]] == [r.split(",")[0] for r in rows[1]]  # frames in input order
