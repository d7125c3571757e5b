"""Shared pytest fixtures."""

import os
from pathlib import Path

import numpy as np
import pytest


@pytest.fixture(scope="session", autouse=True)
def native_kernels_built():
    """crfdepth's compiled kernels built (or found missing) once, before any test: the first build takes up to a
    minute and logs one line, which must not land in the output of whichever test happens to be first."""
    from crfdepth import native

    native.kernels()


@pytest.fixture
def kernels():
    """crfdepth's compiled kernels, or a skip where they cannot be built here (the reason is logged)."""
    from crfdepth import native

    module = native.kernels()
    if module is None:
        pytest.skip("crfdepth's compiled kernels cannot be built here (see the logged reason)")
    return module


def _shared_data(name: str, what: str) -> Path:
    """``../shared/data/<name>`` next to the repository; skipped where it is missing, a failure under CI."""
    root = Path(__file__).resolve().parents[1].parent / "shared" / "data" / name
    if not root.is_dir():
        if os.environ.get("CI"):  # CI always has ../shared: a missing folder is a failure
            pytest.fail(f"{what} sample data not found at {root} (CI=true)")
        pytest.skip(f"{what} sample data not found at {root}")
    return root


@pytest.fixture(scope="session")
def kitti_root() -> Path:
    """The real KITTI sample frames, ``../shared/data/kitti`` next to the repository."""
    return _shared_data("kitti", "KITTI")


@pytest.fixture(scope="session")
def nyu_root() -> Path:
    """The real NYU Depth v2 sample frames, ``../shared/data/nyu`` next to the repository."""
    return _shared_data("nyu", "NYU")


@pytest.fixture
def mast_map():
    """A camera 8 m up a mast over a flat ground, looking level: the ground's returns in the image's
    bottom quarter lie 8 m below it, and the median return is beyond 20 m."""
    height, width, f = 480, 640, 600.0  # a 56-degree lens: the nearest ground seen is 22 m away
    K = np.array([[f, 0, width / 2], [0, f, height / 2], [0, 0, 1]])
    v = np.arange(height)[:, None] + 0.5
    ground = np.where(v > height / 2 + 20, 8.0 * f / np.maximum(v - height / 2, 1e-6), 0.0)
    sparse = np.zeros((height, width), np.float32)
    sparse[::4, ::4] = np.broadcast_to(ground, (height, width))[::4, ::4]
    sparse[sparse > 150] = 0
    return sparse, K
