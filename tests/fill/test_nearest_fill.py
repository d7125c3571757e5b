"""Tests for crfdepth.fill.nearest.nearest_fill."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from crfdepth.errors import InputError
from crfdepth.fill.nearest import nearest_fill


def test_hand_made_map():
    sparse = torch.zeros(5, 6)
    sparse[0, 0] = 2.0
    sparse[3, 5] = 7.0
    sparse[2, 3] = 4.0
    before = sparse.clone()
    dense = nearest_fill(sparse)
    # No pixel has two equally near LiDAR pixels, e.g. (3, 0): 9 to (0, 0), 10 to (2, 3);
    # (4, 0): 16, 13, 26; (1, 5): 26, 5, 4 (squared distances to the three sources).
    want = torch.tensor(
        [
            [2.0, 2.0, 2.0, 4.0, 4.0, 4.0],
            [2.0, 2.0, 4.0, 4.0, 4.0, 7.0],
            [2.0, 4.0, 4.0, 4.0, 4.0, 7.0],
            [2.0, 4.0, 4.0, 4.0, 7.0, 7.0],
            [4.0, 4.0, 4.0, 4.0, 7.0, 7.0],
        ]
    )
    assert torch.equal(dense, want)
    assert torch.equal(sparse, before)  # input untouched


def test_matches_brute_force_nearest_and_keeps_shapes():
    gen = torch.Generator().manual_seed(0)
    sparse = torch.rand(3, 1, 20, 30, generator=gen) * 50 + 1
    sparse[torch.rand(3, 1, 20, 30, generator=gen) > 0.05] = 0
    sparse[:, :, 0, 0] = 3.0  # at least one valid pixel per frame
    dense = nearest_fill(sparse)
    assert dense.shape == sparse.shape and dense.dtype == sparse.dtype
    assert bool((dense > 0).all())
    rows, cols = np.mgrid[0:20, 0:30]
    for b in range(3):
        s = sparse[b, 0].numpy()
        vr, vc = np.nonzero(s)
        d2 = (rows[..., None] - vr) ** 2 + (cols[..., None] - vc) ** 2  # (H, W, N)
        nearest = d2.min(axis=-1)
        # The chosen source must be at the minimum distance (ties allowed).
        got = dense[b, 0].numpy()
        ok = (d2 == nearest[..., None]) & (s[vr, vc] == got[..., None])
        assert ok.any(axis=-1).all()
    assert torch.equal(nearest_fill(sparse[1]), dense[1])  # (1, H, W)
    assert torch.equal(nearest_fill(sparse[1, 0]), dense[1, 0])  # (H, W)


def test_empty_frame_raises_naming_it():
    sparse = torch.zeros(3, 1, 4, 4)
    sparse[0, 0, 1, 1] = 5.0
    sparse[2, 0, 3, 3] = 5.0
    with pytest.raises(InputError, match=r"frame\(s\) \[1\]"):
        nearest_fill(sparse)
    with pytest.raises(InputError, match="sparse"):
        nearest_fill(torch.zeros(4, 4))


@pytest.mark.parametrize("bad", [torch.full((4, 4), -1.0), torch.full((4, 4), float("nan")), torch.ones(2, 4, 4)])
def test_bad_input(bad):
    with pytest.raises(InputError, match=r"^sparse: expected"):
        nearest_fill(bad)


@pytest.mark.kitti
def test_real_frame_fill_is_dense_and_keeps_lidar(kitti_root):
    from crfdepth.data.kitti import KittiValSelection

    sample = KittiValSelection(kitti_root / "depth_selection" / "val_selection_cropped")[0]
    dense = nearest_fill(sample.sparse)
    valid = sample.sparse > 0
    assert bool((dense > 0).all())
    assert torch.equal(dense[valid], sample.sparse[valid])
    # docs/design.md section 6 reports 1386 mm RMSE for this baseline averaged over both frames.
    gt = sample.target > 0
    rmse_mm = 1000 * torch.sqrt(((dense[gt] - sample.target[gt]) ** 2).mean()).item()
    assert 800 < rmse_mm < 2000
