"""Synthetic scenes shared by the tests of crfdepth.data.synthetic (rendered once per session)."""

from __future__ import annotations

import pytest

from crfdepth.data.synthetic import SyntheticScene, make_scene


@pytest.fixture(scope="session")
def scene() -> SyntheticScene:
    return make_scene(0)


@pytest.fixture(scope="session")
def scene16() -> SyntheticScene:
    return make_scene(0, beams=16)


@pytest.fixture
def make_world():
    """A function building a :class:`World` from (kind, material, lo, hi) rows, ground at 1.65 m."""
    import numpy as np

    from crfdepth.data.synthetic.world import CAMERA_HEIGHT_M, World

    def build(rows, sun=(0.0, -1.0, 0.0)):
        kind, mat, lo, hi = zip(*rows)
        n = len(rows)
        return World(
            kind=np.array(kind, dtype=np.int64), mat=np.array(mat, dtype=np.uint8),
            lo=np.array(lo, dtype=np.float64), hi=np.array(hi, dtype=np.float64),
            albedo=np.full((n, 3), 0.5), style=np.zeros((n, 4)), ground_y=CAMERA_HEIGHT_M,
            road={"line_r": 1.75, "line_l": -5.25, "dividers": np.array([-1.75]), "dash_phase": 0.0},
            sun=np.array(sun, dtype=np.float64),
            noise=np.random.default_rng(0).random((256, 256), dtype=np.float32),
        )

    return build
