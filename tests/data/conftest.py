"""A synthetic Sample factory shared by the tests of crfdepth.data.sample and crfdepth.data.transforms."""

from __future__ import annotations

import pytest
import torch

from crfdepth.data.sample import Sample

FX, FY, CX, CY = 721.5377, 721.5377, 609.5593, 172.854  # KITTI 2011_09_26, camera 2


def _make_sample(height: int = 375, width: int = 1242, name: str = "frame", density: float = 0.05,
                seed: int = 0) -> Sample:
    """A synthetic frame: random image, sparse depth on ``density`` of pixels, dense target."""
    g = torch.Generator().manual_seed(seed)
    image = torch.rand(3, height, width, generator=g)
    depth = 1.0 + 79.0 * torch.rand(1, height, width, generator=g)
    sparse = torch.where(torch.rand(1, height, width, generator=g) < density, depth, torch.zeros(()))
    K = torch.tensor([[FX, 0.0, CX], [0.0, FY, CY], [0.0, 0.0, 1.0]])
    return Sample(image=image, sparse=sparse, target=depth.clone(), K=K, name=name)


@pytest.fixture
def make_sample():
    """``make_sample(height=375, width=1242, name="frame", density=0.05, seed=0)``: a random
    Sample with KITTI's camera-2 intrinsics (``FX, FY, CX, CY`` of this conftest)."""
    return _make_sample
