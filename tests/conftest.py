"""Shared pytest fixtures."""

import os
from pathlib import Path

import pytest


@pytest.fixture(scope="session")
def kitti_root() -> Path:
    """The real KITTI sample frames, ``../shared/data/kitti`` next to the repository."""
    root = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "kitti"
    if not root.is_dir():
        if os.environ.get("CI"):  # CI always has ../shared: a missing folder is a failure
            pytest.fail(f"KITTI sample data not found at {root} (CI=true)")
        pytest.skip(f"KITTI sample data not found at {root}")
    return root
