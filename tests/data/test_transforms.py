"""Tests for crfdepth.data.sample and crfdepth.data.transforms."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch
from torch.utils.data import DataLoader

from crfdepth.data.sample import Batch, Sample, collate_samples
from crfdepth.data.transforms import BottomCenterCrop, Compose, HorizontalFlip, SubsampleSparse, frame_seed
from crfdepth.errors import InputError
from crfdepth.io.kitti import read_intrinsics, read_raw_calibration

FX, FY, CX, CY = 721.5377, 721.5377, 609.5593, 172.854  # KITTI 2011_09_26, camera 2


def make_sample(height: int = 375, width: int = 1242, name: str = "frame", density: float = 0.05,
                seed: int = 0) -> Sample:
    """A synthetic frame: random image, sparse depth on ``density`` of pixels, dense target."""
    g = torch.Generator().manual_seed(seed)
    image = torch.rand(3, height, width, generator=g)
    depth = 1.0 + 79.0 * torch.rand(1, height, width, generator=g)
    sparse = torch.where(torch.rand(1, height, width, generator=g) < density, depth, torch.zeros(()))
    K = torch.tensor([[FX, 0.0, CX], [0.0, FY, CY], [0.0, 0.0, 1.0]])
    return Sample(image=image, sparse=sparse, target=depth.clone(), K=K, name=name)


def project(K: torch.Tensor, point: torch.Tensor) -> torch.Tensor:
    """Pixel (u, v) of a camera-frame point."""
    uvw = K.to(torch.float64) @ point.to(torch.float64)
    return uvw[:2] / uvw[2]


# --------------------------------------------------------------------------- Sample / Batch


def test_sample_rejects_mismatched_shapes():
    s = make_sample(8, 10)
    with pytest.raises(InputError, match=r"Sample.sparse: expected a \(1, 8, 10\)"):
        dataclasses.replace(s, sparse=torch.zeros(1, 8, 11))
    with pytest.raises(InputError, match=r"Sample.image: expected a \(3, H, W\)"):
        dataclasses.replace(s, image=torch.zeros(1, 8, 10))
    with pytest.raises(InputError, match=r"Sample.K: expected a \(3, 3\)"):
        dataclasses.replace(s, K=torch.eye(4))
    assert s.size == (8, 10)


def test_collate_stacks_and_dataloader_uses_it():
    samples = [make_sample(16, 24, name=f"f{i}", seed=i) for i in range(3)]
    samples[2] = dataclasses.replace(samples[2], target=torch.zeros(1, 16, 24), has_target=False)
    batch = collate_samples(samples)
    assert isinstance(batch, Batch) and len(batch) == 3
    assert batch.image.shape == (3, 3, 16, 24) and batch.sparse.shape == (3, 1, 16, 24)
    assert batch.target.shape == (3, 1, 16, 24) and batch.K.shape == (3, 3, 3)
    assert batch.K.dtype == torch.float32
    assert batch.names == ["f0", "f1", "f2"]
    assert batch.has_target.tolist() == [True, True, False]
    torch.testing.assert_close(batch.sparse[1], samples[1].sparse, rtol=0, atol=0)

    loader = DataLoader(samples, batch_size=2, collate_fn=collate_samples)
    sizes = [len(b) for b in loader]
    assert sizes == [2, 1]
    moved = batch.to(torch.float64)
    assert moved.image.dtype == torch.float64 and moved.has_target.dtype == torch.bool


def test_collate_errors_name_sizes():
    with pytest.raises(InputError, match="empty list"):
        collate_samples([])
    with pytest.raises(InputError, match=r"'a' is \(8, 10\) but 'b' is \(8, 12\)"):
        collate_samples([make_sample(8, 10, name="a"), make_sample(8, 12, name="b")])


# --------------------------------------------------------------------------- BottomCenterCrop


def test_bottom_center_crop_pixels_and_intrinsics():
    s = make_sample(375, 1242)
    out = BottomCenterCrop(352, 1216)(s)
    top, left = 375 - 352, (1242 - 1216) // 2
    assert (top, left) == (23, 13) == BottomCenterCrop().offsets((375, 1242))
    assert out.size == (352, 1216)
    assert torch.equal(out.image, s.image[:, top:, left:left + 1216])
    assert torch.equal(out.sparse, s.sparse[:, top:, left:left + 1216])
    assert torch.equal(out.target, s.target[:, top:, left:left + 1216])
    assert out.K[0, 2].item() == pytest.approx(CX - 13, abs=1e-4)
    assert out.K[1, 2].item() == pytest.approx(CY - 23, abs=1e-4)
    assert torch.equal(out.K[0, 0], s.K[0, 0]) and torch.equal(out.K[1, 1], s.K[1, 1])
    # K follows the pixels: a 3D point lands at the same image content before and after.
    point = torch.tensor([2.0, 0.5, 10.0])
    torch.testing.assert_close(project(out.K, point), project(s.K, point) - torch.tensor([13.0, 23.0], dtype=torch.float64),
                               atol=1e-4, rtol=0)
    # The input sample is not modified.
    assert s.size == (375, 1242) and s.K[0, 2].item() == pytest.approx(CX, abs=1e-4)


def test_bottom_center_crop_odd_margin_and_errors():
    out = BottomCenterCrop(4, 5)(make_sample(10, 12))
    assert out.size == (4, 5)
    assert out.K[0, 2].item() == pytest.approx(CX - 3, abs=1e-4)  # (12 - 5) // 2 = 3
    assert out.K[1, 2].item() == pytest.approx(CY - 6, abs=1e-4)
    with pytest.raises(InputError, match=r"'small' is 300x1242 \(HxW\), smaller than the crop 352x1216"):
        BottomCenterCrop()(make_sample(300, 1242, name="small"))
    with pytest.raises(InputError, match="height and width > 0"):
        BottomCenterCrop(0, 10)


@pytest.mark.kitti
def test_crop_of_raw_intrinsics_equals_val_selection_intrinsics(kitti_root):
    """The benchmark crop applied to the raw 1242x375 K gives val_selection's K (cx-13, cy-23)."""
    val = kitti_root / "depth_selection" / "val_selection_cropped" / "intrinsics"
    for camera in (2, 3):
        calib = read_raw_calibration(kitti_root / "raw" / "2011_09_26", camera=camera)
        assert calib.image_size == (375, 1242)
        s = make_sample(*calib.image_size)
        s = dataclasses.replace(s, K=torch.from_numpy(calib.K))  # float64 K is kept as given
        cropped = BottomCenterCrop()(s)
        expected = read_intrinsics(val / f"2011_09_26_drive_0001_sync_image_0000000005_image_0{camera}.txt")
        np.testing.assert_allclose(cropped.K.numpy(), expected, atol=1e-6)
        np.testing.assert_allclose(expected[:2, 2], calib.K[:2, 2] - [13, 23], atol=1e-6)


# --------------------------------------------------------------------------- HorizontalFlip


def test_horizontal_flip_twice_is_identity_and_k_follows():
    s = make_sample(6, 9)
    flip = HorizontalFlip(p=1.0)
    once = flip(s)
    assert torch.equal(once.image[:, :, 0], s.image[:, :, 8])
    assert torch.equal(once.sparse[:, 2, 3], s.sparse[:, 2, 9 - 1 - 3])
    assert torch.equal(once.target, s.target.flip(-1))
    assert once.K[0, 2].item() == pytest.approx(9 - 1 - CX, abs=1e-4)
    assert once.K[1, 2].item() == pytest.approx(CY, abs=1e-4)
    twice = flip(once)
    for field in ("image", "sparse", "target", "K"):
        assert torch.equal(getattr(twice, field), getattr(s, field)), field
    # The mirrored point (-x, y, z) lands on the mirrored pixel column W - 1 - u.
    point = torch.tensor([1.5, -0.3, 7.0])
    u, v = project(s.K, point)
    u_f, v_f = project(once.K, point * torch.tensor([-1.0, 1.0, 1.0]))
    assert u_f.item() == pytest.approx(9 - 1 - u.item(), abs=1e-3)
    assert v_f.item() == pytest.approx(v.item(), abs=1e-3)


def test_horizontal_flip_probability_and_generator():
    s = make_sample(2, 3)
    assert HorizontalFlip(p=0.0)(s) is s
    flip = HorizontalFlip(p=0.5, generator=torch.Generator().manual_seed(0))
    flipped = [not torch.equal(flip(s).image, s.image) for _ in range(1000)]
    assert 430 <= sum(flipped) <= 570
    a = HorizontalFlip(0.5, torch.Generator().manual_seed(7))
    b = HorizontalFlip(0.5, torch.Generator().manual_seed(7))
    assert [a(s).K[0, 2].item() for _ in range(20)] == [b(s).K[0, 2].item() for _ in range(20)]
    with pytest.raises(InputError, match=r"p must be in \[0, 1\], got 1.5"):
        HorizontalFlip(p=1.5)


# --------------------------------------------------------------------------- SubsampleSparse


def test_subsample_sparse_keeps_exact_fraction_of_valid_pixels():
    s = make_sample(40, 50, density=0.3, name="a")
    valid = s.sparse > 0
    n = int(valid.sum())
    for fraction in (0.4, 0.7):
        out = SubsampleSparse(fraction, seed=3)(s)
        kept = out.sparse > 0
        assert int(kept.sum()) == round(fraction * n)
        assert not (kept & ~valid).any()                       # a subset of the valid pixels
        assert torch.equal(out.sparse[kept], s.sparse[kept])   # values untouched
        assert torch.equal(out.image, s.image) and torch.equal(out.target, s.target)
    assert int((s.sparse > 0).sum()) == n                      # input not modified
    assert SubsampleSparse(1.0)(s) is s
    assert int((SubsampleSparse(0.0)(s).sparse > 0).sum()) == 0


def test_subsample_sparse_is_deterministic_per_frame():
    s = make_sample(40, 50, density=0.3, name="a")
    t = SubsampleSparse(0.5, seed=1)
    assert torch.equal(t(s).sparse, t(s).sparse)
    other_name = dataclasses.replace(s, name="b")
    assert not torch.equal(t(s).sparse, t(other_name).sparse)
    assert not torch.equal(t(s).sparse, SubsampleSparse(0.5, seed=2)(s).sparse)
    assert frame_seed(1, "a") == frame_seed(1, "a") != frame_seed(1, "b")
    with pytest.raises(InputError, match=r"fraction must be in \[0, 1\]"):
        SubsampleSparse(1.2)


def test_compose_applies_in_order():
    s = make_sample(375, 1242)
    out = Compose([BottomCenterCrop(), HorizontalFlip(p=1.0)])(s)
    expected = HorizontalFlip(p=1.0)(BottomCenterCrop()(s))
    assert torch.equal(out.image, expected.image) and torch.equal(out.K, expected.K)
    # crop then flip: cx' = 1215 - (cx - 13)
    assert out.K[0, 2].item() == pytest.approx(1215 - (CX - 13), abs=1e-4)
