"""The example recording (crfdepth.data.example_bag): what README's "From a ROS bag" runs on."""

from __future__ import annotations

import pytest
import torch

from crfdepth import cli
from crfdepth.data.example import EXAMPLE_SEED, example_scene
from crfdepth.data.example_bag import CLOUD_DELAY_NS, EXAMPLE_TOPICS, START_NS, main, write_example_bag
from crfdepth.fill.nearest import nearest_fill
from crfdepth.io.kitti import read_depth_png
from crfdepth.metrics import depth_metrics

pytest.importorskip("rosbags")


def _rmse(depth, target) -> float:
    return float(depth_metrics(torch.as_tensor(depth), torch.as_tensor(target))["rmse"][0])


def test_readme_bag_command_completes_the_street(tmp_path, monkeypatch, capsys):
    """The README's two commands: the recording, then complete --bag; every frame beats the nearest fill."""
    monkeypatch.chdir(tmp_path)
    assert main(["street.bag", "--frames", "2"]) == 0
    monkeypatch.setattr(cli, "_COMMANDS", ("crfdepth.cli.complete",))
    assert cli.main(["complete", "--bag", "street.bag", "--image-topic", EXAMPLE_TOPICS["image"], "--points-topic",
                     EXAMPLE_TOPICS["points"], "--out-dir", "depth", "--out-bag", "street_depth.bag"]) == 0
    out = capsys.readouterr().out
    assert "wrote 2 depth PNG(s) and index.csv to depth" in out and "unpaired" not in out
    for k in range(2):
        scene = example_scene(EXAMPLE_SEED + k)
        depth = read_depth_png(tmp_path / "depth" / f"{START_NS + k * 100_000_000}.png")
        crf, nearest = _rmse(depth, scene.target()), _rmse(nearest_fill(torch.from_numpy(scene.sparse)), scene.target())
        assert crf < 0.85 * nearest, (crf, nearest)
    rows = (tmp_path / "depth" / "index.csv").read_text().splitlines()
    assert len(rows) == 3 and rows[1].split(",")[4] == f"{CLOUD_DELAY_NS / 1e6:.3f}"
    assert (tmp_path / "street_depth.bag").is_file()


def test_bad_arguments(tmp_path, capsys):
    (tmp_path / "x.bag").write_text("")
    assert main([str(tmp_path / "x.bag")]) == 2
    assert "x.bag, which exists" in capsys.readouterr().err
    with pytest.raises(Exception, match="frames: expected an integer >= 1"):
        write_example_bag(tmp_path / "y.bag", frames=0)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["x.bag"]
