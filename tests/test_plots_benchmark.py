"""benchmarks/plots.py: the documentation's figures drawn from benchmark JSON, and its refusals."""

from __future__ import annotations

import json

import cv2
import numpy as np
import pytest

from tests.benchmark_scripts import load_benchmark
from tests.documents import ROOT, page


@pytest.fixture(scope="module")
def bench():
    return load_benchmark("plots")


def _accuracy_lines(std: bool = True) -> str:
    lines = ["[   3 s] protocol a"]  # a benchmark's printed output is accepted as it is
    for protocol, rmse in (("a", 1000.0), ("c", 4000.0)):
        for method, factor in (("ipbasic", 1.0), ("hand-set", 0.9), ("learned", 0.8)):
            record = {"protocol": protocol, "method": method, "rmse": rmse * factor}
            if std and method == "learned":
                record |= {"coverage_1_std": 0.7, "coverage_2_std": 0.9, "ause_ratio_std": 0.2}
            lines.append(json.dumps(record))
    return "\n".join(lines) + "\n"


def _speed_line() -> str:
    rows = [{"config": c, "std": s, "size": [352, 1216], "seconds": t * (1.2 if s else 1.0)}
            for c, t in (("default", 0.07), ("ip-basic", 0.04)) for s in (False, True) if not (c == "ip-basic" and s)]
    rows.append({"config": "default", "std": False, "size": [3000, 4000], "seconds": 7.5})
    return "table\n" + json.dumps({"device": "cpu", "rows": rows}) + "\n"


def test_the_three_figures_are_drawn_from_the_json(bench, tmp_path, capsys):
    (tmp_path / "acc.jsonl").write_text(_accuracy_lines())
    (tmp_path / "speed.txt").write_text(_speed_line())
    paths = bench.main(["--accuracy", str(tmp_path / "acc.jsonl"), "--speed", str(tmp_path / "speed.txt"),
                        "--out-dir", str(tmp_path / "plots")])
    assert [p.name for p in paths] == ["accuracy.png", "speed.png", "std.png"]
    for path in paths:
        image = cv2.imread(str(path))
        assert image is not None and image.shape[0] > 200 and image.shape[1] > 500
        assert np.unique(image.reshape(-1, 3), axis=0).shape[0] > 10  # something is drawn, not a blank canvas
    assert capsys.readouterr().out.count("plot: ") == 3


def test_the_tables_read_what_the_figures_need(bench):
    records = [json.loads(line) for line in _accuracy_lines().splitlines()[1:]]
    table = bench.accuracy_table(records)
    assert sorted(table) == ["a", "c"] and table["c"]["learned"]["rmse"] == pytest.approx(3200.0)
    assert bench.std_protocols(table) == ["a", "c"]
    rows = bench.speed_rows([json.loads(_speed_line().splitlines()[1])])
    assert {r["config"] for r in rows} == {"default", "ip-basic"} and len(rows) == 3  # the large frame left out


@pytest.mark.parametrize("accuracy, speed, message", [
    (None, _speed_line(), "--accuracy: cannot read"),
    ("no json here\n", _speed_line(), "--accuracy: expected JSON lines"),
    (json.dumps({"protocol": "a", "method": "learned", "rmse": 1.0}) + "\n", _speed_line(),
     "--accuracy: expected rows of the methods"),
    (_accuracy_lines(std=False), _speed_line(), "--accuracy: expected the learned model's std figures"),
    (_accuracy_lines(), json.dumps({"rows": []}) + "\n", "--speed: expected rows of a 1216 x 352 frame"),
])
def test_bad_inputs_exit_2_with_one_line_and_write_nothing(bench, tmp_path, capsys, accuracy, speed, message):
    if accuracy is not None:
        (tmp_path / "acc.jsonl").write_text(accuracy)
    (tmp_path / "speed.txt").write_text(speed)
    with pytest.raises(SystemExit) as exit_info:
        bench.main(["--accuracy", str(tmp_path / "acc.jsonl"), "--speed", str(tmp_path / "speed.txt"),
                    "--out-dir", str(tmp_path / "plots")])
    err = capsys.readouterr().err
    assert exit_info.value.code == 2 and err.startswith(f"plots.py: error: {message}") and err.count("\n") == 1
    assert not (tmp_path / "plots").exists()



def test_the_committed_figures_are_redrawn_from_the_committed_json(bench, tmp_path):
    """The docs' figures (docs/results/plots) are what plots.py draws from the committed benchmark JSON: redrawn
    here, each matches the committed PNG to a mean of 3 grey levels (fonts may render a little differently)."""
    results = ROOT / "docs" / "results"
    paths = bench.main(["--accuracy", str(results / "accuracy.jsonl"), "--speed", str(results / "speed.json"),
                        "--out-dir", str(tmp_path)])
    for path in paths:
        committed = cv2.imread(str(results / "plots" / path.name), cv2.IMREAD_GRAYSCALE)
        drawn = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE)
        assert committed is not None, path.name
        assert drawn.shape == committed.shape, (path.name, drawn.shape, committed.shape)
        assert np.abs(drawn.astype(float) - committed.astype(float)).mean() <= 3.0, path.name


def test_the_evaluation_table_holds_the_committed_json(bench):
    """docs/evaluation.md's IP-Basic, hand-set (shipped structure) and learned rows give, for (a), (b) and (c),
    the RMSE of docs/results/accuracy.jsonl to the millimetre."""
    table = bench.accuracy_table(bench.read_json_lines(ROOT / "docs" / "results" / "accuracy.jsonl", "--accuracy"))
    rows = {"ipbasic": "| IP-Basic", "hand-set": "(the shipped structure)", "learned": "shipped learned weights"}
    lines = page("evaluation.md").splitlines()
    for method, marker in rows.items():
        cells = next(line for line in lines if line.startswith("|") and marker in line).split("|")[2:-1]
        for protocol, cell in zip(("a", "b", "c"), (cells[0], cells[1], cells[3])):
            assert int(cell.split("/")[0]) == round(table[protocol][method]["rmse"]), (method, protocol, cell)


def _box_means(picture: np.ndarray) -> np.ndarray:
    """8 x 8 box means: what survives any JPEG encoder (its 8 x 8 blocks, chroma subsampling and ringing)."""
    return cv2.blur(picture.astype(np.float64), (8, 8))


def test_the_front_picture_is_the_example_rig_as_the_script_draws_it(tmp_path):
    """docs/own_sensors.jpg (README, docs index, own-sensors page) is what benchmarks/front_picture.py makes of
    docs/example. The picture's array is compared before encoding, on its two 320 x 240 maps, as 8 x 8 box means:
    a JPEG encoder (quality 90, any release) moves those by a mean under 1 level and a 99th percentile under 14
    (measured: 0.47 / 3.2 on the completed depth, 1.5 / 12.8 on the scan drawn over the image); a stale picture
    does not pass (the learned weights instead of the paper's: 5.1 / 36.7 on the depth). The colour bars below
    the maps hold text drawn by OpenCV's fonts, whose placement changes between releases: only their presence
    is asserted."""
    script = load_benchmark("front_picture")
    made = script.front_picture(ROOT / "docs" / "example")
    committed = cv2.cvtColor(cv2.imread(str(ROOT / "docs" / "own_sensors.jpg")), cv2.COLOR_BGR2RGB)
    assert made.dtype == np.uint8 and made.shape == committed.shape == (284, 644, 3)
    for name, region, mean_limit, p99_limit in (("scan on the image", np.s_[:240, :320], 4.0, 32.0),
                                                 ("completed depth", np.s_[:240, 324:], 2.0, 16.0)):
        diff = np.abs(_box_means(made[region]) - _box_means(committed[region]))
        assert diff.mean() < mean_limit and np.percentile(diff, 99) < p99_limit, (name, diff.mean(),
                                                                                 np.percentile(diff, 99))
    # the left panel's map holds the scan in depth colours over the darkened image; the right one, no dark pixel
    assert (made[:240, 324:] > 20).any(-1).all()
    # each panel has a colour bar under it: saturated colours in the rows below the map
    for columns in (np.s_[:320], np.s_[324:]):
        bar = made[240:, columns].astype(np.int16)
        assert ((bar.max(-1) - bar.min(-1)) > 100).sum() > 1000
    # the script writes that array as a JPEG
    out = tmp_path / "front.jpg"
    assert script.main(["--out", str(out)]) == 0
    written = cv2.cvtColor(cv2.imread(str(out)), cv2.COLOR_BGR2RGB)
    assert written.shape == made.shape
    assert np.abs(_box_means(written) - _box_means(made)).mean() < 2.0
    with pytest.raises(SystemExit):
        script.main(["--out", str(tmp_path / "front.png")])
