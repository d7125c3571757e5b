"""Tests for the Sample transforms (crfdepth/data/transforms.py)."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch

from crfdepth.data.transforms import (
    BottomCenterCrop,
    Compose,
    HorizontalFlip,
    RandomCrop,
    RandomThinning,
    SubsampleSparse,
    frame_seed,
)
from crfdepth.errors import InputError
from crfdepth.io.calibration import read_raw_calibration
from crfdepth.io.kitti import read_intrinsics

CX, CY = 609.5593, 172.854  # principal point of make_sample's K (KITTI 2011_09_26, camera 2)


def project(K: torch.Tensor, point: torch.Tensor) -> torch.Tensor:
    """Pixel (u, v) of a camera-frame point."""
    uvw = K.to(torch.float64) @ point.to(torch.float64)
    return uvw[:2] / uvw[2]


# --------------------------------------------------------------------------- BottomCenterCrop


def test_bottom_center_crop_pixels_and_intrinsics(make_sample):
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


def test_bottom_center_crop_odd_margin_and_errors(make_sample):
    out = BottomCenterCrop(4, 5)(make_sample(10, 12))
    assert out.size == (4, 5)
    assert out.K[0, 2].item() == pytest.approx(CX - 3, abs=1e-4)  # (12 - 5) // 2 = 3
    assert out.K[1, 2].item() == pytest.approx(CY - 6, abs=1e-4)
    with pytest.raises(InputError, match=r"'small' is 300x1242 \(HxW\), smaller than the crop 352x1216"):
        BottomCenterCrop()(make_sample(300, 1242, name="small"))
    with pytest.raises(InputError, match="height and width > 0"):
        BottomCenterCrop(0, 10)


@pytest.mark.kitti
def test_crop_of_raw_intrinsics_equals_val_selection_intrinsics(kitti_root, make_sample):
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


def test_horizontal_flip_twice_is_identity_and_k_follows(make_sample):
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


def test_horizontal_flip_probability_and_generator(make_sample):
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


def test_subsample_sparse_keeps_exact_fraction_of_valid_pixels(make_sample):
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


def test_subsample_sparse_is_deterministic_per_frame(make_sample):
    s = make_sample(40, 50, density=0.3, name="a")
    t = SubsampleSparse(0.5, seed=1)
    assert torch.equal(t(s).sparse, t(s).sparse)
    other_name = dataclasses.replace(s, name="b")
    assert not torch.equal(t(s).sparse, t(other_name).sparse)
    assert not torch.equal(t(s).sparse, SubsampleSparse(0.5, seed=2)(s).sparse)
    assert frame_seed(1, "a") == frame_seed(1, "a") != frame_seed(1, "b")
    with pytest.raises(InputError, match=r"fraction must be in \[0, 1\]"):
        SubsampleSparse(1.2)


def test_compose_applies_in_order(make_sample):
    s = make_sample(375, 1242)
    out = Compose([BottomCenterCrop(), HorizontalFlip(p=1.0)])(s)
    expected = HorizontalFlip(p=1.0)(BottomCenterCrop()(s))
    assert torch.equal(out.image, expected.image) and torch.equal(out.K, expected.K)
    # crop then flip: cx' = 1215 - (cx - 13)
    assert out.K[0, 2].item() == pytest.approx(1215 - (CX - 13), abs=1e-4)


# --------------------------------------------------------------------------- RandomCrop, RandomThinning


def test_random_crop_moves_the_principal_point_with_the_window(make_sample):
    s = make_sample(60, 90)
    gen = torch.Generator().manual_seed(0)
    corners = set()
    for _ in range(20):
        out = RandomCrop(40, 50, generator=gen)(s)
        assert out.size == (40, 50)
        left, top = round(s.K[0, 2].item() - out.K[0, 2].item()), round(s.K[1, 2].item() - out.K[1, 2].item())
        assert 0 <= top <= 20 and 0 <= left <= 40
        corners.add((top, left))
        assert torch.equal(out.image, s.image[:, top:top + 40, left:left + 50])
        assert torch.equal(out.sparse, s.sparse[:, top:top + 40, left:left + 50])
        assert torch.equal(out.target, s.target[:, top:top + 40, left:left + 50])
        # K follows the pixels: a point lands on the same content.
        point = torch.tensor([0.3, 0.1, 8.0])
        torch.testing.assert_close(project(out.K, point),
                                   project(s.K, point) - torch.tensor([left, top], dtype=torch.float64),
                                   atol=1e-3, rtol=0)
    assert len(corners) > 10                              # the window moves
    assert torch.equal(RandomCrop(60, 90)(s).image, s.image)  # a full-size crop is the frame


def test_random_crop_bad_input(make_sample):
    with pytest.raises(InputError, match=r"RandomCrop: expected height and width integers > 0, got \(0, 5\)"):
        RandomCrop(0, 5)
    with pytest.raises(InputError, match=r"RandomCrop: sample 'frame' is 30x40 \(HxW\), smaller than the crop 32x40"):
        RandomCrop(32, 40)(make_sample(30, 40))


def test_random_thinning_keeps_a_fraction_in_range(make_sample):
    s = make_sample(100, 120, density=0.5)
    n = int((s.sparse > 0).sum())
    gen = torch.Generator().manual_seed(1)
    shares = []
    for _ in range(30):
        out = RandomThinning(0.4, 0.8, generator=gen)(s)
        kept = out.sparse > 0
        assert not (kept & (s.sparse <= 0)).any()
        assert torch.equal(out.sparse[kept], s.sparse[kept])
        assert torch.equal(out.target, s.target) and torch.equal(out.image, s.image)
        shares.append(kept.sum().item() / n)
    assert 0.35 < min(shares) and max(shares) < 0.85      # within [low, high] up to sampling noise
    assert max(shares) - min(shares) > 0.15               # a fresh fraction each call
    assert RandomThinning(1.0)(s) is s
    with pytest.raises(InputError, match=r"RandomThinning: expected 0 < low <= high <= 1, got low=0.9, high=0.5"):
        RandomThinning(0.9, 0.5)
