"""The per-stage timer of a forward (crfdepth/output.py)."""

from __future__ import annotations

import time

from crfdepth.output import Stages


def test_stages_accumulate_seconds_per_name_and_report_each_start():
    started = []
    stage = Stages(None, started.append)
    for _ in range(2):
        with stage("solve"):
            time.sleep(0.01)
    with stage("fill"):
        pass
    assert started == ["solve", "solve", "fill"]
    assert set(stage.seconds) == {"solve", "fill"} and stage.seconds["solve"] >= 0.015
    assert stage.seconds["fill"] < stage.seconds["solve"]
