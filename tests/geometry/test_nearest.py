"""The nearest valid pixel in torch (crfdepth.geometry.nearest) against SciPy's exact distance transform."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from scipy.ndimage import distance_transform_edt

from crfdepth.data.kitti import KittiValSelection
from crfdepth.fill.nearest import fill_on_device, nearest_fill
from crfdepth.geometry.nearest import nearest_valid
from crfdepth.uncertainty.predictive import return_distance


def _check_against_scipy(valid: torch.Tensor) -> float:
    """Assert exact squared distances and a consistent index; return the share of pixels whose pick equals SciPy's."""
    index, squared = nearest_valid(valid[None])
    distance, (rows, cols) = distance_transform_edt(~valid.numpy(), return_indices=True)
    assert np.array_equal(squared[0].numpy(), np.rint(distance ** 2).astype(np.int64))
    h, w = valid.shape
    r, c = index[0] // w, index[0] % w
    assert bool(valid[r, c].all())  # every pick is a valid pixel ...
    rr, cc = torch.meshgrid(torch.arange(h), torch.arange(w), indexing="ij")
    assert torch.equal((r - rr) ** 2 + (c - cc) ** 2, squared[0])  # ... at the stated distance
    return float(((r.numpy() == rows) & (c.numpy() == cols)).mean())


@pytest.mark.parametrize("shape, density", [((37, 53), 0.03), ((5, 80), 0.01), ((60, 7), 0.02), ((64, 64), 0.3)])
def test_squared_distances_equal_scipy_on_random_masks(shape, density):
    generator = torch.Generator().manual_seed(3)
    for _ in range(5):
        valid = torch.rand(shape, generator=generator) < density
        valid[0, 0] |= not bool(valid.any())  # at least one valid pixel
        _check_against_scipy(valid)


def test_squared_distances_equal_scipy_on_a_lidar_pattern():
    # KITTI-like: scan lines every 4 rows with gaps, nothing in the top third (the sky)
    valid = torch.zeros(90, 300, dtype=torch.bool)
    valid[30::4, ::3] = True
    valid[50:60, 100:180] = False
    same = _check_against_scipy(valid)
    assert same > 0.5  # ties aside, the same pixels are picked


def test_real_frames(kitti_root):
    frames = KittiValSelection(kitti_root / "depth_selection" / "val_selection_cropped")
    for k in range(len(frames)):
        assert _check_against_scipy(frames[k].sparse[0] > 0) > 0.8  # 0.88 measured: the rest are ties


def test_frames_without_a_valid_pixel_and_batches():
    valid = torch.rand(3, 20, 30, generator=torch.Generator().manual_seed(0)) < 0.05
    valid[1] = False
    index, squared = nearest_valid(valid)
    assert bool((index[1] == -1).all()) and bool((squared[1] == (20 + 30) ** 2 + 1).all())
    for k in (0, 2):
        alone_index, alone_squared = nearest_valid(valid[k:k + 1])
        assert torch.equal(alone_squared[0], squared[k]) and torch.equal(alone_index[0], index[k])


def test_device_fill_and_distance_agree_with_the_cpu_path():
    sparse = torch.zeros(2, 1, 40, 70)
    generator = torch.Generator().manual_seed(1)
    picks = torch.rand(2, 1, 40, 70, generator=generator) < 0.02
    sparse[picks] = 1 + 50 * torch.rand(int(picks.sum()), generator=generator)
    cpu = nearest_fill(sparse)
    device = fill_on_device(sparse[:, 0])[:, None]
    _, squared = nearest_valid(sparse[:, 0] > 0)
    # where the nearest return is unique both paths take it; everywhere the value is that of a return at the
    # exact nearest distance
    distance = return_distance(sparse)
    assert torch.allclose(distance, squared[:, None].double().sqrt().float())
    values = set(sparse[sparse > 0].tolist())
    assert set(device.unique().tolist()) <= values
    assert float((device == cpu).double().mean()) > 0.9


@pytest.mark.parametrize("max_block, entries", [(1, 1 << 25), (3, 1 << 25), (64, 500)])
def test_blocks_of_any_width_give_the_exact_distances(monkeypatch, max_block, entries):
    # shifts in blocks of 1 (the per-shift loop), of 3, and blocks narrowed by the memory cap
    # (500 candidates: one shift per block at this size); distances up to 250 pixels along a row
    import crfdepth.geometry.nearest as module
    monkeypatch.setattr(module, "_MAX_BLOCK", max_block)
    monkeypatch.setattr(module, "_BLOCK_ENTRIES", entries)
    valid = torch.zeros(6, 260, dtype=torch.bool)
    valid[2, 3] = True
    valid[5, 140] = True
    _check_against_scipy(valid)
    generator = torch.Generator().manual_seed(5)
    for _ in range(3):
        valid = torch.rand(30, 90, generator=generator) < 0.01
        valid[0, 0] |= not bool(valid.any())
        _check_against_scipy(valid)


@pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA device")
def test_cuda_gives_the_exact_distances_of_scipy():
    generator = torch.Generator().manual_seed(2)
    valid = torch.rand(3, 120, 400, generator=generator) < 0.01
    valid[1, :40] = False  # an empty band: distances of 40 rows and more
    valid[2] = False  # a frame without a return
    index, squared = nearest_valid(valid.cuda())
    for k in (0, 1):
        distance = distance_transform_edt(~valid[k].numpy())
        assert np.array_equal(squared[k].cpu().numpy(), np.rint(distance ** 2).astype(np.int64))
        assert bool(valid[k].flatten()[index[k].cpu().flatten()].all())
    assert bool((index[2] == -1).all())
