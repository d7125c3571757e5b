"""K must be a plausible pinhole matrix everywhere it enters (crfdepth.intrinsics.check_intrinsics),
``CRFDepth.forward`` included: finite, upper triangular with K[2][2] = 1, non-singular, positive focal
lengths, a skew of at most 0.1 fx, the principal point within half an image of the image and a field of
view in (1, 170) degrees. Oracle: KITTI's K (cameras 2 of 2011_09_26) passes, each hand-broken copy fails
with the one-line message naming the argument."""

from __future__ import annotations

import re

import numpy as np
import pytest
import torch

from crfdepth.errors import InputError
from crfdepth.intrinsics import (
    INTRINSICS_TOLERANCE,
    MAX_INTRINSICS_CONDITION,
    MAX_SKEW_RATIO,
    PRINCIPAL_POINT_MARGIN,
    check_intrinsics,
)
from crfdepth.model import CRFDepth

KITTI_K = np.array([[721.5377, 0.0, 609.5593], [0.0, 721.5377, 172.854], [0.0, 0.0, 1.0]])
SIZE = (375, 1242)  # (height, width) of the uncropped KITTI frame


def _broken(**entries) -> np.ndarray:
    """KITTI_K with ``K21=...`` style entries replaced."""
    K = KITTI_K.copy()
    for name, value in entries.items():
        K[int(name[1]), int(name[2])] = value
    return K


def test_the_stated_constants():
    assert (INTRINSICS_TOLERANCE, MAX_SKEW_RATIO, MAX_INTRINSICS_CONDITION, PRINCIPAL_POINT_MARGIN) == \
        (1e-6, 0.1, 1e10, 0.5)


def test_kitti_k_and_near_misses_pass():
    np.testing.assert_array_equal(check_intrinsics(KITTI_K, "K", SIZE), KITTI_K)
    check_intrinsics(_broken(K01=0.1 * 721.5377), "K", SIZE)  # skew at the limit
    check_intrinsics(_broken(K10=1e-7 * 721.5377, K20=1e-7, K21=-1e-7, K22=1 + 1e-7), "K", SIZE)  # rounding
    check_intrinsics(torch.tensor(KITTI_K, dtype=torch.float32).reshape(9), "K", SIZE)  # 9 numbers, float32
    # principal point at the edges of the allowed band: the image extended by half its size on each side
    check_intrinsics(_broken(K02=-0.5 * 1242, K12=1.5 * 375), "K")
    for cx, cy in ((-0.5 * 1242, 172.854), (1.5 * 1242, 172.854), (609.5593, -0.5 * 375), (609.5593, 1.5 * 375)):
        check_intrinsics(_broken(K02=cx, K12=cy), "K", SIZE)


@pytest.mark.parametrize("K, message", [
    (_broken(K10=5.0), "--intrinsics: expected an upper-triangular K, K[1][0] = 0 (within 1e-06 fy), got K[1][0]=5: "
                       "K is mistyped, or a rotation is mixed into it"),
    (_broken(K20=0.01), "--intrinsics: expected the last row of K to be 0 0 1, got 0.01 0 1 (tolerance 1e-06)"),
    (_broken(K21=-0.001), "--intrinsics: expected the last row of K to be 0 0 1, got 0 -0.001 1 (tolerance 1e-06)"),
    (_broken(K22=2.0), "--intrinsics: expected the last row of K to be 0 0 1, got 0 0 2 (tolerance 1e-06)"),
    (KITTI_K.T.copy(), "--intrinsics: expected the last row of K to be 0 0 1, got 609.559 172.854 1 (tolerance 1e-06): "
                       "K looks transposed (cx and cy belong in the last column)"),
    (_broken(K01=80.0), "--intrinsics: expected a skew |K[0][1]| <= 0.1 fx = 72.1538 px (pixel grids are rectangular: "
                        "0 or nearly), got K[0][1]=80 (0.111 fx): K is mistyped, or a rotation is mixed into it"),
    (_broken(K00=0.0), "--intrinsics: expected focal lengths fx = K[0][0] > 0 and fy = K[1][1] > 0 (pixels), got "
                       "fx=0, fy=721.538"),
    (_broken(K11=-721.5377), "--intrinsics: expected focal lengths fx = K[0][0] > 0 and fy = K[1][1] > 0 (pixels), "
                             "got fx=721.538, fy=-721.538"),
    (_broken(K00=1e-9, K11=1e-9), "--intrinsics: expected a non-singular K (condition number <= 1e+10), got condition "
                                  "number "),
    (_broken(K02=np.inf), "--intrinsics: expected finite numbers, got "),
    (_broken(K02=1242 * 1.5 + 1), "--intrinsics: expected the principal point of the 1242x375 (WxH) image within half "
                                  "an image of it (cx in [-621, 1863], cy in [-187.5, 562.5] px), got (cx, cy) = "
                                  "(1864, 172.854), far outside"),
    (_broken(K12=-0.5 * 375 - 1), "--intrinsics: expected the principal point of the 1242x375 (WxH) image within half"),
    (_broken(K00=4.0, K11=4.0), "--intrinsics: expected a field of view below 170 degrees over the 1242x375 (WxH) "
                                "image, got 179.3 x 177.5 degrees (fx=4, fy=4 px)"),
    (_broken(K00=1e5, K11=1e5), "--intrinsics: expected a field of view above 1 degree over the 1242x375 (WxH) image"),
])
def test_implausible_k_is_refused(K, message):
    with pytest.raises(InputError, match="^" + re.escape(message)) as info:
        check_intrinsics(K, "--intrinsics", SIZE)
    assert "\n" not in str(info.value)


@pytest.mark.parametrize("value, got", [
    ("x" * 1_000_000, "'xxxxxxxxxxxxxxxxx...xxxxxxxxxxxxxxxxxx'"),
    ([[1, 2, 3], [4, 5], list(range(1_000_000))], "[[1, 2, 3], [4, 5], [0, 1, 2, 3, ...]]"),
    ({"fx": 1}, "{'fx': 1}"),
    (10 ** 5000, "int"),
], ids=["long string", "ragged lists", "mapping", "int of 5000 digits"])
def test_a_value_that_is_no_matrix_is_quoted_briefly(value, got):
    with pytest.raises(InputError) as info:
        check_intrinsics(value, "K (rig.yaml)")
    assert str(info.value) == f"K (rig.yaml): expected a 3x3 matrix of numbers, got {got}"


# --------------------------------------------------------------------------- CRFDepth.forward


def _frames(batch: int = 1, height: int = 12, width: int = 16):
    g = torch.Generator().manual_seed(0)
    image = torch.rand(batch, 3, height, width, generator=g, dtype=torch.float64)
    sparse = torch.where(torch.rand(batch, 1, height, width, generator=g) < 0.3,
                         8 + torch.rand(batch, 1, height, width, generator=g, dtype=torch.float64),
                         torch.zeros((), dtype=torch.float64))
    K = torch.tensor([[20.0, 0, width / 2], [0, 20.0, height / 2], [0, 0, 1]], dtype=torch.float64)
    return image, sparse, K


@pytest.fixture(scope="module")
def model():
    return CRFDepth(mode="pixel").double()


@pytest.mark.parametrize("change, message", [
    (lambda K: K.index_put_((torch.tensor(0), torch.tensor(1)), torch.tensor(5.0, dtype=K.dtype)),
     "K: expected a skew |K[0][1]| <= 0.1 fx = 2 px"),
    (lambda K: K.index_put_((torch.tensor(1), torch.tensor(0)), torch.tensor(0.5, dtype=K.dtype)),
     "K: expected an upper-triangular K, K[1][0] = 0"),
    (lambda K: K.index_put_((torch.tensor(2), torch.tensor(2)), torch.tensor(2.0, dtype=K.dtype)),
     "K: expected the last row of K to be 0 0 1, got 0 0 2"),
    (lambda K: K.index_put_((torch.tensor(0), torch.tensor(2)), torch.tensor(400.0, dtype=K.dtype)),
     "K: expected every pixel of the 16x12 (WxH) image within 85 degrees of the optical axis"),
    (lambda K: K * torch.tensor([[0.01, 1, 1], [1, 0.01, 1], [1, 1, 1]], dtype=K.dtype),
     "K: expected a field of view below 170 degrees over the 16x12 (WxH) image"),
])
def test_forward_refuses_an_implausible_k(model, change, message):
    image, sparse, K = _frames()
    with pytest.raises(InputError, match="^" + re.escape(message)):
        model(image, sparse, change(K.clone()))


def test_forward_takes_a_crop_far_from_the_principal_point(model):
    """A training crop of a wide frame: the principal point lies outside the crop, several crop widths away;
    forward takes it (the file readers, given a whole image, would refuse it)."""
    image, sparse, K = _frames()
    K[0, 2], K[1, 2] = -60.0, 30.0  # the crop's pixels 3-4 crop widths right of and below the axis: < 80 degrees
    out = model(image, sparse, K)
    assert bool(torch.isfinite(out.depth).all())
    with pytest.raises(InputError, match=r"^--intrinsics: expected the principal point of the 16x12"):
        check_intrinsics(K, "--intrinsics", (12, 16))


def test_a_crop_must_lie_within_85_degrees_of_the_axis():
    """crop=True drops the principal-point band, not the pinhole: a 4000-pixel-wide crop 8000 px right of a
    721 px lens's axis sees rays 86.6 degrees off it (its field of view, 1.7 degrees, passes)."""
    K = np.array([[721.5, 0, -8000.0], [0, 721.5, 150.0], [0, 0, 1]])
    with pytest.raises(InputError, match=r"^K: expected every pixel of the 4000x300 \(WxH\) image within 85 degrees "
                                         r"of the optical axis \(a pinhole image\), got a corner 86\.6 degrees off it"):
        check_intrinsics(K, "K", (300, 4000), crop=True)
    K[0, 2] = -3000.0  # 81 degrees: a plausible crop
    check_intrinsics(K, "K", (300, 4000), crop=True)


def test_forward_names_the_frame_of_a_batched_k(model):
    image, sparse, K = _frames(batch=3)
    Ks = K.expand(3, 3, 3).clone()
    Ks[1, 0, 1] = 5.0  # frame 1 only
    with pytest.raises(InputError, match=r"^K\[1\]: expected a skew \|K\[0\]\[1\]\| <= 0\.1 fx"):
        model(image, sparse, Ks)
    out = model(image, sparse, K.expand(3, 3, 3).clone())  # one K per frame, all plausible
    assert out.depth.shape == (3, 1, 12, 16) and bool(torch.isfinite(out.depth).all())
    with pytest.raises(InputError, match=r"^K: expected a skew"):  # a batch of one is named K
        model(image[:1], sparse[:1], Ks[1:2])
