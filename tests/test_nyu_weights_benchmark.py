"""benchmarks/nyu_weights.py: indoor weights learned on real NYU frames, scored on a held-out scene."""

from __future__ import annotations

import json

import pytest

from crfdepth.model import CRFDepth
from tests.benchmark_scripts import load_benchmark


@pytest.fixture(scope="module")
def bench():
    return load_benchmark("nyu_weights")


@pytest.mark.slow
def test_leave_one_scene_out_and_the_written_file(bench, nyu_root, tmp_path, capsys):
    out_file = tmp_path / "nyu.json"
    result = bench.main(["--nyu-root", str(nyu_root), "--epochs", "1", "--repeats", "1", "--rooms", "2", "--write",
                         str(out_file)])
    lines = capsys.readouterr().out.splitlines()
    assert json.loads(lines[-1])["rows"] == result["rows"] and result["rooms"] == 2
    assert [(r["held_out"], r["samples"]) for r in result["rows"]] == [
        ("basement", 500), ("basement", 200), ("dining", 500), ("dining", 200)]
    for r in result["rows"]:
        # every CRF is well ahead of the nearest fill on these frames (0.64-0.93 x in the shipped file's run)
        assert max(r["learned"], r["kitti"], r["scattered"]) < r["nearest"]
        # the default routes the real indoor frames to its indoor regime: the weights fitted without the scene
        assert r["default"] == pytest.approx(r["learned"], rel=1e-5)
        assert r["learned_vs_kitti"] == pytest.approx(r["learned"] / r["kitti"])
    for r in result["summary"]:  # the four held-out frames: 3 of the basement, 1 of the dining room
        rs = [x for x in result["rows"] if x["samples"] == r["samples"]]
        assert r["frames"] == 4
        assert r["default"] == pytest.approx((3 * rs[0]["default"] + rs[1]["default"]) / 4)
        assert r["default_vs_paper"] == pytest.approx(r["default"] / r["paper"])
    stored = json.loads(out_file.read_text())
    model = CRFDepth.from_stored(stored["config"], {})
    assert model.settings.structure.coarse == 6 and not model.settings.gate.enabled
    assert "--rooms 2" in stored["about"]["recipe"]


def test_a_folder_without_the_scenes_exits_2(bench, tmp_path, capsys):
    with pytest.raises(SystemExit) as stop:
        bench.main(["--nyu-root", str(tmp_path)])
    assert stop.value.code not in (0, None) and "--nyu-root" in capsys.readouterr().err + str(stop.value.code)


def test_room_draws_are_three_per_room_of_the_protocol_size(bench):
    draws = bench.room_draws(2)
    assert len(draws) == 6 and all(d.image.shape[1:] == (228, 304) for d in draws)
    # one draw of each count; the draw's input pixels are not in its target
    assert sorted(int((d.sparse > 0).sum()) for d in draws[:3]) == [200, 500, 1000]
    assert all(not bool(((d.sparse > 0) & (d.target > 0)).any()) for d in draws)


@pytest.mark.parametrize("value", ["-1", "x", "1001"])
def test_a_bad_room_count_exits_2_naming_it(bench, value, capsys):
    with pytest.raises(SystemExit) as stop:
        bench.main(["--rooms", value])
    assert stop.value.code == 2 and "--rooms" in capsys.readouterr().err
