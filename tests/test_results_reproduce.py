"""The shipped weights reproduce the numbers that README.md and crfdepth/weights/README.md
state for them on the official frames (protocol a of benchmarks/accuracy.py), within 1 mm.

The numbers are read from the two READMEs themselves, so a retrained ``kitti.json`` whose
documentation was not updated turns this red.
"""

from __future__ import annotations

import re
from pathlib import Path

import pytest
import torch

from crfdepth.data.factory import build_dataset
from crfdepth.metrics import average_metrics, depth_metrics
from crfdepth.model import CRFDepth

ROOT = Path(__file__).resolve().parents[1]
TOLERANCE_MM = 1.0


def _stated() -> dict[str, tuple[float, float]]:
    """(RMSE, MAE) in mm on (a) as the evaluation page and the weights README state them for the shipped weights."""
    readme = (ROOT / "docs" / "evaluation.md").read_text(encoding="utf-8")
    row = re.search(r"^\| \*{0,2}crfdepth, shipped learned weights[^|]*\| (\d+) / (\d+) \|", readme, flags=re.M)
    weights = (ROOT / "crfdepth" / "weights" / "README.md").read_text(encoding="utf-8")
    line = re.search(r"these weights score\s+RMSE / MAE (\d+) / (\d+) mm", weights)
    assert row, "docs/evaluation.md: no row '| crfdepth, shipped learned weights ... | RMSE / MAE |'"
    assert line, "crfdepth/weights/README.md: no 'these weights score RMSE / MAE x / y mm'"
    return {"docs/evaluation.md": (float(row[1]), float(row[2])),
            "crfdepth/weights/README.md": (float(line[1]), float(line[2]))}


@pytest.mark.kitti
def test_shipped_weights_reproduce_the_stated_official_frame_numbers(kitti_root):
    stated = _stated()
    frames = build_dataset("val_selection", kitti_root / "depth_selection" / "val_selection_cropped")
    model = CRFDepth.from_pretrained("kitti")
    per_image = []
    with torch.no_grad():
        for s in frames:
            depth = model(s.image[None], s.sparse[None], s.K[None]).depth.clamp_min(1e-3)
            per_image.append(depth_metrics(depth, s.target[None]))
    got = average_metrics({k: torch.cat([m[k] for m in per_image]) for k in per_image[0]})
    assert len(frames) == 2
    for where, (rmse, mae) in stated.items():
        assert abs(got["rmse"] - rmse) <= TOLERANCE_MM and abs(got["mae"] - mae) <= TOLERANCE_MM, (
            f"{where} states {rmse:.0f} / {mae:.0f} mm; the shipped weights give "
            f"{got['rmse']:.1f} / {got['mae']:.1f} mm")
