"""crfdepth.data.kitti.lidar_view.simulate_scan: the Velodyne's view of a camera-view depth map."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from crfdepth.data.kitti import KittiAnnotated
from crfdepth.data.kitti.lidar_view import HDL64_ELEVATIONS_DEG, lift_to_velodyne, simulate_scan
from crfdepth.errors import InputError
from crfdepth.io.calibration import Calibration

# KITTI's 2011_09_26 calibration, camera 2 (calib_cam_to_cam.txt, calib_velo_to_cam.txt)
KITTI = Calibration(
    P_rect=np.array([[721.5377, 0.0, 609.5593, 44.85728], [0.0, 721.5377, 172.854, 0.2163791],
                     [0.0, 0.0, 1.0, 0.002745884]]),
    R_rect=np.array([[0.9999239, 0.00983776, -0.00744505, 0.0], [-0.0098698, 0.9999421, -0.00427846, 0.0],
                     [0.00740253, 0.00435161, 0.9999631, 0.0], [0.0, 0.0, 0.0, 1.0]]),
    T_velo_to_cam=np.array([[7.533745e-03, -9.999714e-01, -6.166020e-04, -4.069766e-03],
                            [1.480249e-02, 7.280733e-04, -9.998902e-01, -7.631618e-02],
                            [9.998621e-01, 7.523790e-03, 1.480755e-02, -2.717806e-01], [0.0, 0.0, 0.0, 1.0]]),
)
H, W = 375, 1242
BOX = (slice(150, 301), slice(700, 901))  # rows 150-300, columns 700-900: a box 5 m away on a wall 20 m away


def _wall(depth: float = 20.0) -> np.ndarray:
    scene = np.zeros((H, W), np.float32)
    scene[120:] = depth
    return scene


def test_a_wall_returns_its_own_depth_on_the_rings():
    scan = simulate_scan(_wall(), KITTI, range_noise=0.0, generator=np.random.default_rng(0))
    returns = scan[scan > 0]
    np.testing.assert_allclose(returns, 20.0, atol=1e-4)  # no see-through without a nearer surface
    # one return per ring and azimuth step: along each ring the returns are 0.18 degrees apart, no bin empty
    v, u = np.nonzero(scan > 0)
    velo = lift_to_velodyne(v.astype(float), u.astype(float), scan[v, u].astype(float), KITTI)
    elevation = np.degrees(np.arctan2(velo[2], np.hypot(velo[0], velo[1])))
    azimuth = np.degrees(np.arctan2(velo[1], velo[0]))
    ring = np.abs(elevation[:, None] - HDL64_ELEVATIONS_DEG[None, :]).argmin(axis=1)
    assert len(np.unique(ring)) >= 40  # the wall fills the image below row 120: rings +2 to about -16 degrees
    for r in np.unique(ring):
        along = np.sort(azimuth[ring == r])
        assert along.size == pytest.approx((along[-1] - along[0]) / 0.18 + 1, rel=0.02)
    sixteen = simulate_scan(_wall(), KITTI, keep_every_ring=4, range_noise=0.0, generator=np.random.default_rng(0))
    assert (sixteen > 0).sum() == pytest.approx(0.25 * (scan > 0).sum(), rel=0.1)


def test_the_range_noise_has_its_sigma():
    scan = simulate_scan(_wall(), KITTI, range_noise=0.05, generator=np.random.default_rng(1))
    assert float(np.std(scan[scan > 0] - 20.0)) == pytest.approx(0.05, rel=0.1)


def test_see_through_returns_lie_where_the_velodyne_sees_past_the_box():
    scene = _wall()
    scene[BOX] = 5.0
    scan = simulate_scan(scene, KITTI, range_noise=0.0, generator=np.random.default_rng(0))
    box = scan[BOX]
    through = box > 10.0
    assert through.sum() >= 20
    np.testing.assert_allclose(box[through], 20.0, atol=1e-4)  # the wall behind, at its depth
    v, u = np.nonzero(through)
    # The Velodyne sits 0.27 m behind and 8 cm above the camera: it sees past the box's outer side (right of
    # the image centre) and its top, by about |p - e| 0.27 (1/5 - 1/20) pixels (e: the Velodyne's image point,
    # about 200 px below the centre), never past its inner (left) side or its bottom.
    near_right, near_top = u >= box.shape[1] - 25, v < 25
    assert (near_right | near_top).all()
    assert near_right.any() and near_top.any()
    # without the hidden background no see-through return is possible
    flat = simulate_scan(scene, KITTI, hidden_window=(1, 1), range_noise=0.0, generator=np.random.default_rng(0))
    assert (flat[BOX] > 10.0).sum() == 0


def test_a_seeded_generator_repeats_the_scan():
    scene = _wall()
    scene[BOX] = 5.0
    a = simulate_scan(scene, KITTI, generator=np.random.default_rng(3))
    b = simulate_scan(scene, KITTI, generator=np.random.default_rng(3))
    np.testing.assert_array_equal(a, b)


@pytest.mark.parametrize(("options", "message"), [
    ({"target": np.zeros((2, 3, 4), np.float32)}, r"^target: expected an \(H, W\) floating depth map"),
    ({"keep_every_ring": 0}, r"^keep_every_ring: expected an integer in \[1, 64\], got 0"),
    ({"keep_every_ring": 4, "ring_offset": 4}, r"^ring_offset: expected an integer in \[0, 4\), got 4"),
    ({"range_noise": -1.0}, r"^range_noise: expected a finite number >= 0, got -1.0"),
    ({"azimuth_step_deg": 0.0}, r"^azimuth_step_deg: expected a finite number > 0, got 0.0"),
    ({"fill_radius": "4"}, r"^fill_radius: expected a finite number >= 0, got '4'"),
    ({"hidden_window": (4, 5)}, r"^hidden_window: expected \(height, width\) of odd positive integers"),
    ({"hidden_window": ("a", "b")}, r"^hidden_window: expected \(height, width\) of odd positive integers"),
    ({"hidden_window": 17}, r"^hidden_window: expected \(height, width\) of odd positive integers"),
])
def test_bad_arguments_are_named(options, message):
    arguments = {"target": _wall(), "calib": KITTI, **options}
    with pytest.raises(InputError, match=message):
        simulate_scan(**arguments)


@pytest.mark.kitti
def test_a_simulated_scan_of_frame_5_looks_like_its_real_scan(kitti_root):
    """Frame 5 has both KITTI's annotation and its own scan: the simulation from the annotation has about the
    real scan's density and, like it, returns behind the annotation (see-through), which the clean inputs lack."""
    drive = kitti_root / "depth_completion"
    real = KittiAnnotated(drive, input_from="scan", camera="image_02")[0]
    simulated = KittiAnnotated(drive, input_from="lidar", camera="image_02", seed=0)[0]
    assert torch.equal(real.target, simulated.target)  # the whole annotation is the target, as with the scan
    density = (simulated.sparse > 0).float().mean().item()
    assert density == pytest.approx((real.sparse > 0).float().mean().item(), rel=0.3)

    def behind(sample):
        both = (sample.sparse > 0) & (sample.target > 0)
        gap = sample.sparse[both] - sample.target[both]
        return (gap > torch.clamp(0.1 * sample.target[both], min=0.5)).float().mean().item()

    assert 0.0005 < behind(simulated) < 0.02
    assert 0.0005 < behind(real) < 0.02
    assert torch.equal(KittiAnnotated(drive, input_from="lidar", camera="image_02", seed=0)[0].sparse,
                       simulated.sparse)
