"""Tests of crfdepth.checks and crfdepth.plausibility for the camera and the LiDAR: K against the
image, rigid transforms, and the units of a sparse depth map (oracle: the real KITTI
sparse maps, in metres once divided by 256, and hand-made maps in other units)."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
import torch

from crfdepth.checks import check_choice, check_rigid
from crfdepth.errors import InputError
from crfdepth.intrinsics import check_intrinsics
from crfdepth.plausibility import MAX_LIDAR_DEPTH_M, check_sparse_units

KITTI_K = [[721.5377, 0.0, 596.5593], [0.0, 721.5377, 149.854], [0.0, 0.0, 1.0]]


def _sparse(median_m: float, count: int = 500, shape=(60, 80), seed=0) -> np.ndarray:
    """A sparse map with ``count`` LiDAR pixels around ``median_m`` metres."""
    rng = np.random.default_rng(seed)
    depth = np.zeros(shape)
    depth.flat[rng.choice(depth.size, count, replace=False)] = median_m * rng.uniform(0.5, 1.5, count)
    return depth


# --------------------------------------------------------------------------- sparse units


@pytest.mark.parametrize("median", [2.0, 14.0, 80.0, 120.0])
def test_metres_pass(median):
    """The same map in metres passes and in millimetres is refused: the check tells them apart."""
    with pytest.raises(InputError, match="millimetres"):
        check_sparse_units("sparse", _sparse(median) * 1000)
    check_sparse_units("sparse", _sparse(median))
    check_sparse_units("sparse", torch.from_numpy(_sparse(median)).float())
    if median <= 80:  # whole metres in an integer map, all below 300
        check_sparse_units("sparse", np.round(_sparse(median)).astype(np.int32))


def test_empty_and_nan_maps_are_left_to_other_checks():
    """No returns, or no finite ones: nothing to judge the unit by, so no unit error (the
    empty-scan and non-finite checks name those faults)."""
    for sparse in (np.zeros((4, 5)), np.full((4, 5), np.nan)):
        assert check_sparse_units("sparse", sparse) is None
    with pytest.raises(InputError, match="millimetres"):  # one millimetre-scale return is enough to judge
        check_sparse_units("sparse", np.where(np.arange(20).reshape(4, 5) == 7, 14000.0, 0.0))


def test_raw_png_codes_are_named_with_the_fix():
    codes = np.round(_sparse(14.0) * 256).astype(np.uint16)
    with pytest.raises(InputError) as info:
        check_sparse_units("sparse", codes)
    message = str(info.value)
    median = np.median(codes[codes > 0])
    assert message.startswith(f"sparse: expected depth in metres (a median of at most 300 m, the reach of a "
                              f"LiDAR), got a median {median:.4g} m over 500 return(s); that looks like the raw codes "
                              f"of a KITTI depth PNG (metres * 256")
    assert "divide by 256" in message


def test_plain_metres_read_as_kitti_and_half_metre_medians_are_refused():
    with pytest.raises(InputError, match=r"at most 50% of the returns nearer than 1 m\), got 100% of them"):
        check_sparse_units("sparse", _sparse(0.5))


def test_integer_map_with_large_values_is_refused_even_with_a_small_median():
    """A near scene read raw (median 1 m = code 256 < 300) still holds codes far beyond any range."""
    codes = np.round(_sparse(1.0) * 256).astype(np.uint16)
    codes[0, :10] = 20 * 256
    assert np.median(codes[codes > 0]) < MAX_LIDAR_DEPTH_M
    with pytest.raises(InputError, match="divide by 256"):
        check_sparse_units("--sparse", codes)


def test_millimetres_are_named_with_the_fix():
    with pytest.raises(InputError) as info:
        check_sparse_units("sparse", _sparse(14.0) * 1000.0)
    message = str(info.value)
    assert message.startswith("sparse: expected depth in metres")
    assert "that looks like millimetres: divide by 1000" in message
    with pytest.raises(InputError, match="millimetres: divide by 1000"):
        check_sparse_units("sparse", torch.from_numpy(_sparse(14.0) * 1000.0))


@pytest.mark.kitti
def test_every_shared_kitti_sparse_map_passes_in_metres_and_fails_raw(kitti_root):
    """The val_selection_cropped maps: medians 14.2-14.4 m, at most 78 m once divided by 256."""
    paths = sorted((kitti_root / "depth_selection" / "val_selection_cropped" / "velodyne_raw").glob("*.png"))
    assert paths
    for path in paths:
        raw = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
        assert raw.dtype == np.uint16
        check_sparse_units("sparse", raw / 256.0)
        check_sparse_units("sparse", (raw / 256.0).astype(np.float32))
        with pytest.raises(InputError, match="divide by 256"):
            check_sparse_units("sparse", raw)
        millimetres = raw / 256.0 * 1000.0
        millimetres[raw > 0] += 0.25  # not whole numbers: not PNG codes
        with pytest.raises(InputError, match="millimetres: divide by 1000"):
            check_sparse_units("sparse", millimetres)


# --------------------------------------------------------------------------- K and T


def test_principal_point_against_the_image():
    np.testing.assert_array_equal(check_intrinsics(KITTI_K, "K", (352, 1216)), KITTI_K)
    check_intrinsics(np.array(KITTI_K).ravel(), "K", (375, 1242))  # 9 numbers, the uncropped frame
    check_intrinsics(torch.tensor(KITTI_K), "K")  # no image: no principal-point check
    with pytest.raises(InputError) as info:
        check_intrinsics(KITTI_K, "--intrinsics", (9, 17))
    assert str(info.value).startswith(
        "--intrinsics: expected the principal point of the 17x9 (WxH) image within half an image of it (cx in "
        "[-8.5, 25.5], cy in [-4.5, 13.5] px), got (cx, cy) = (596.559, 149.854), far outside")
    swapped = np.array(KITTI_K)
    swapped[0, 2], swapped[1, 2] = 149.854, 596.5593
    with pytest.raises(InputError, match=r"got \(cx, cy\) = \(149.854, 596.559\).*cx and cy are swapped"):
        check_intrinsics(swapped, "K", (352, 1216))
    check_intrinsics(KITTI_K, "K", (9 * 2 + 300, 17 * 2 + 800))  # within half an image: accepted


@pytest.mark.parametrize("K, words", [
    ([[-1.0, 0, 1], [0, 1, 1], [0, 0, 1]], ["K: expected focal lengths", "fx=-1"]),
    ([[1.0, 0, 1], [0, 1, 1], [0, 1, 1]], ["K: expected the last row of K to be 0 0 1, got 0 1 1"]),
    ([1.0, 2.0], ["K: expected a 3x3 matrix or 9 numbers (row-major), got shape (2,)"]),
    ([[1.0, 0, np.nan], [0, 1, 1], [0, 0, 1]], ["K: expected finite numbers"]),
])
def test_bad_intrinsics(K, words):
    with pytest.raises(InputError) as info:
        check_intrinsics(K, "K")
    assert all(w in str(info.value) for w in words), str(info.value)


def test_check_rigid():
    T = np.eye(4)
    T[:3, 3] = [0.1, -0.2, 0.3]
    np.testing.assert_array_equal(check_rigid(torch.from_numpy(T)), T)
    scaled = T.copy()
    scaled[:3, :3] *= 1000
    with pytest.raises(InputError, match=r"^T_cam_lidar: expected a rigid transform .* not orthonormal"):
        check_rigid(scaled)
    with pytest.raises(InputError, match=r"^T: expected a rotation part with determinant \+1, got -1"):
        check_rigid(np.diag([1.0, -1.0, 1.0, 1.0]), "T")


# --------------------------------------------------------------------------- choices


def test_check_choice():
    assert check_choice("mode", "pixel", ("superpixel", "pixel")) == "pixel"
    with pytest.raises(InputError, match=r"^mode: expected one of 'superpixel', 'pixel', got 'voxel'$"):
        check_choice("mode", "voxel", ("superpixel", "pixel"))
    for odd in ([1], np.array(["pixel", "pixel"]), None):  # unhashable, elementwise ==, not a string
        with pytest.raises(InputError, match=r"^mode: expected one of 'superpixel', 'pixel', got "):
            check_choice("mode", odd, ("superpixel", "pixel"))
