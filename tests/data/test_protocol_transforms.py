"""Tests of Resize, CenterCrop, SparseSamples and the published protocols (crfdepth/data/sampling.py)."""

from __future__ import annotations

import dataclasses

import pytest
import torch

from crfdepth.data.sample import Sample
from crfdepth.data.sampling import CenterCrop, Resize, SparseSamples, kitti_table4, nyu_protocol, resized_intrinsics
from crfdepth.data.transforms import BottomCenterCrop, Compose
from crfdepth.errors import InputError


def _frame(height=48, width=64, name="frame", seed=0, density=0.3) -> Sample:
    g = torch.Generator().manual_seed(seed)
    target = torch.where(torch.rand(1, height, width, generator=g) < 0.9,
                         0.5 + 5 * torch.rand(1, height, width, generator=g), torch.zeros(()))
    sparse = torch.where(torch.rand(1, height, width, generator=g) < density, target, torch.zeros(()))
    K = torch.tensor([[50.0, 0.0, width / 2 + 0.3], [0.0, 51.0, height / 2 - 0.7], [0.0, 0.0, 1.0]])
    return Sample(image=torch.rand(3, height, width, generator=g), sparse=sparse, target=target, K=K, name=name)


def _project(K: torch.Tensor, point: torch.Tensor) -> torch.Tensor:
    uvw = K.to(torch.float64) @ point
    return uvw[:2] / uvw[2]


# --------------------------------------------------------------------------- Resize


def test_resize_halves_with_nearest_depth_and_k_following_pixel_centres():
    s = _frame(48, 64)
    out = Resize(24, 32)(s)
    assert out.size == (24, 32)
    # nearest-exact: output pixel d takes the input pixel whose centre is nearest, 2 d + 1
    assert torch.equal(out.sparse, s.sparse[:, 1::2, 1::2]) and torch.equal(out.target, s.target[:, 1::2, 1::2])
    assert out.image.min() >= 0 and out.image.max() <= 1
    # the image: PIL's antialiased bilinear (a triangle filter over 4 x 4 input pixels when halving: weights
    # 1, 3, 3, 1 / 8 per axis), the resize of the Sparse-to-Dense protocol; checked away from the border
    taps = torch.tensor([1.0, 3.0, 3.0, 1.0]) / 8
    kernel = (taps[:, None] * taps[None, :]).expand(3, 1, 4, 4)
    oracle = torch.nn.functional.conv2d(s.image[None], kernel, stride=2, padding=1, groups=3)[0]
    torch.testing.assert_close(out.image[:, 1:-1, 1:-1], oracle[:, 1:-1, 1:-1], atol=1e-5, rtol=0)
    point = torch.tensor([0.4, -0.3, 2.5], dtype=torch.float64)
    u, u2 = _project(s.K, point), _project(out.K, point)
    torch.testing.assert_close(u2, (u + 0.5) * 0.5 - 0.5, atol=1e-4, rtol=0)
    assert out.K[0, 0].item() == pytest.approx(25.0) and out.K[1, 1].item() == pytest.approx(25.5)
    assert s.size == (48, 64) and s.K[0, 0].item() == 50.0  # the input is not modified


def test_resize_invents_no_depth_between_surfaces():
    s = _frame(30, 40)
    for size in [(17, 23), (45, 71)]:
        out = Resize(*size)(s)
        assert out.size == size
        assert set(out.target.unique().tolist()) <= set(s.target.unique().tolist())
        assert set(out.sparse.unique().tolist()) <= set(s.sparse.unique().tolist())


def test_resized_intrinsics_scale_and_shift():
    K = torch.tensor([[518.86, 0.0, 325.58], [0.0, 519.47, 253.74], [0.0, 0.0, 1.0]])
    half = resized_intrinsics(K, 0.5, 0.5)
    expected = torch.tensor([[259.43, 0.0, 162.54], [0.0, 259.735, 126.62], [0.0, 0.0, 1.0]])
    torch.testing.assert_close(half, expected, atol=1e-4, rtol=0)
    torch.testing.assert_close(resized_intrinsics(half, 2.0, 2.0), K, atol=1e-4, rtol=0)


def test_resize_to_the_same_size_returns_the_sample_and_bad_sizes_are_refused():
    s = _frame(8, 10)
    assert Resize(8, 10)(s) is s
    for bad in [(0, 10), (8, -1), (8.5, 10), (True, 10)]:
        with pytest.raises(InputError, match=r"^Resize: expected height and width integers > 0"):
            Resize(*bad)


# --------------------------------------------------------------------------- CenterCrop


def test_center_crop_window_and_k():
    s = _frame(240, 320)
    out = CenterCrop(228, 304)(s)
    assert out.size == (228, 304)
    assert torch.equal(out.image, s.image[:, 6:234, 8:312]) and torch.equal(out.target, s.target[:, 6:234, 8:312])
    assert out.K[0, 2].item() == pytest.approx(s.K[0, 2].item() - 8, abs=1e-4)
    assert out.K[1, 2].item() == pytest.approx(s.K[1, 2].item() - 6, abs=1e-4)
    with pytest.raises(InputError, match=r"^CenterCrop: sample 'frame' is 240x320 \(HxW\), smaller than the crop"):
        CenterCrop(250, 304)(s)


# --------------------------------------------------------------------------- SparseSamples


def test_sparse_samples_draws_exactly_n_target_pixels():
    s = _frame(48, 64)
    out = SparseSamples(100, seed=3)(s)
    drawn = out.sparse > 0
    assert int(drawn.sum()) == 100
    assert torch.equal(out.sparse[drawn], s.target[drawn])  # each keeps its ground-truth depth exactly
    assert torch.equal(out.target, s.target) and torch.equal(out.image, s.image) and torch.equal(out.K, s.K)
    assert int((s.sparse > 0).sum()) != 100  # the input was not modified


def test_sparse_samples_are_a_function_of_seed_and_name():
    s = _frame(48, 64)
    a, b = SparseSamples(50, seed=1)(s), SparseSamples(50, seed=1)(s)
    assert torch.equal(a.sparse, b.sparse)
    assert not torch.equal(a.sparse, SparseSamples(50, seed=2)(s).sparse)
    renamed = dataclasses.replace(s, name="other")
    assert not torch.equal(a.sparse, SparseSamples(50, seed=1)(renamed).sparse)


def test_sparse_samples_without_seed_follow_torchs_generator():
    s = _frame(48, 64)
    torch.manual_seed(0)
    a = SparseSamples(50, seed=None)(s)
    b = SparseSamples(50, seed=None)(s)
    torch.manual_seed(0)
    assert torch.equal(SparseSamples(50, seed=None)(s).sparse, a.sparse) and not torch.equal(a.sparse, b.sparse)


def test_sparse_samples_from_the_sparse_map():
    s = _frame(48, 64, density=0.2)
    out = SparseSamples(30, source="sparse")(s)
    drawn = out.sparse > 0
    assert int(drawn.sum()) == 30 and bool((s.sparse[drawn] > 0).all())
    assert torch.equal(out.sparse[drawn], s.sparse[drawn])


def test_more_samples_than_valid_pixels_names_samples_and_both_numbers():
    s = _frame(8, 8)
    valid = int((s.target > 0).sum())
    with pytest.raises(InputError) as info:
        SparseSamples(valid + 1)(s)
    message = str(info.value)
    assert message.startswith(f"samples: expected at most the {valid} valid pixel(s) of the target of frame 'frame'")
    assert message.endswith(f"got {valid + 1}")
    assert int((SparseSamples(valid)(s).sparse > 0).sum()) == valid  # every valid pixel is allowed


@pytest.mark.parametrize("kwargs, start", [
    ({"count": 0}, "samples: expected an integer > 0"),
    ({"count": 2.5}, "samples: expected an integer > 0"),
    ({"count": True}, "samples: expected an integer > 0"),
    ({"count": 5, "seed": -1}, "seed: expected an integer >= 0 or None"),
    ({"count": 5, "source": "lidar"}, "source: expected one of 'target', 'sparse'"),
])
def test_bad_sparse_samples_arguments(kwargs, start):
    with pytest.raises(InputError) as info:
        SparseSamples(**kwargs)
    assert str(info.value).startswith(start)


# --------------------------------------------------------------------------- protocols


def test_nyu_protocol_steps_and_result():
    protocol = nyu_protocol(500, seed=7)
    assert isinstance(protocol, Compose)
    assert protocol.transforms == (Resize(240, 320), CenterCrop(228, 304), SparseSamples(500, 7))
    out = protocol(_frame(480, 640))
    assert out.size == (228, 304) and int((out.sparse > 0).sum()) == 500
    assert nyu_protocol(None).transforms == (Resize(240, 320), CenterCrop(228, 304))


def test_kitti_table4_crops_the_bottom_centre_and_samples_the_target():
    s = _frame(352, 1216)
    out = kitti_table4(200, seed=0)(s)
    assert out.size == (228, 912) and int((out.sparse > 0).sum()) == 200
    top, left = BottomCenterCrop(228, 912).offsets((352, 1216))
    assert (top, left) == (124, 152)
    assert torch.equal(out.target, s.target[:, top:, left:left + 912])
    assert out.K[0, 2].item() == pytest.approx(s.K[0, 2].item() - left, abs=1e-4)
