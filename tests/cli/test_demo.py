"""crfdepth demo: the README's main command."""

import re

import cv2
import numpy as np
import pytest

from crfdepth.cli import main


def _rmse(text: str, method: str) -> float:
    return float(re.search(rf"{method}\s+RMSE ([\d.]+) mm", text).group(1))


def test_demo_on_the_builtin_scene(tmp_path, capsys):
    assert main(["demo", "--out-dir", str(tmp_path)]) == 0
    text = capsys.readouterr().out
    crf, nn = _rmse(text, "crfdepth"), _rmse(text, "nearest-neighbour")
    assert crf < nn, text
    for kind in ("input", "depth", "std", "points"):
        picture = cv2.imread(str(tmp_path / f"synthetic-seed0_{kind}.png"))
        assert picture.shape == (352, 1216, 3) and picture.std() > 5, kind
    depth16 = cv2.imread(str(tmp_path / "synthetic-seed0_depth16.png"), cv2.IMREAD_UNCHANGED)
    assert depth16.dtype == np.uint16 and int((depth16 == 0).sum()) == 0


@pytest.mark.kitti
def test_demo_on_real_frames(tmp_path, capsys, kitti_root):
    assert main(["demo", "--kitti", str(kitti_root), "--out-dir", str(tmp_path)]) == 0
    text = capsys.readouterr().out
    assert len(re.findall(r"crfdepth\s+RMSE", text)) == 2
    assert len(list(tmp_path.glob("*_points.png"))) == 2


def test_demo_bad_kitti_folder(tmp_path, capsys):
    assert main(["demo", "--kitti", str(tmp_path), "--out-dir", str(tmp_path / "out")]) == 2
    assert "--kitti: expected a folder with depth_selection/val_selection_cropped" in capsys.readouterr().err
