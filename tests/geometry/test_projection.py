"""Tests of crfdepth.geometry.projection: synthetic z-buffer cases and the shared KITTI scans."""

from __future__ import annotations

import numpy as np
import pytest

from crfdepth.errors import InputError
from crfdepth.geometry.projection import (
    count_in_image,
    fraction_mask,
    keep_every_ring,
    keep_fraction,
    project_points,
    project_to_depth,
    project_velodyne,
    recover_rings,
    ring_mask,
)
from crfdepth.io.calibration import Calibration, RigCalibration, load_calibration
from crfdepth.io.kitti import read_depth_png, read_velodyne

DRIVE = "2011_09_26_drive_0001_sync"
FRAME = "0000000005"
K = np.array([[100.0, 0.0, 20.0], [0.0, 100.0, 10.0], [0.0, 0.0, 1.0]])

# Velodyne (x forward, y left, z up) -> camera (x right, y down, z forward).
VELO_TO_CAM = np.array([[0.0, -1.0, 0.0, 0.0], [0.0, 0.0, -1.0, 0.0], [1.0, 0.0, 0.0, 0.0], [0.0, 0.0, 0.0, 1.0]])


def _toy_calibration(image_size=(21, 41)) -> Calibration:
    P = np.concatenate([K, [[0.0], [0.0], [0.0]]], axis=1)
    return Calibration(P_rect=P, R_rect=np.eye(4), T_velo_to_cam=VELO_TO_CAM, image_size=image_size)


# --------------------------------------------------------------------------- synthetic


def test_project_to_depth_nearest_point_wins():
    # Three points on the ray through pixel (u=25, v=12) at z = 4, 2, 3, one elsewhere.
    ray = np.array([(25 - 20) / 100, (12 - 10) / 100, 1.0])
    points = np.stack([4 * ray, 2 * ray, 3 * ray, [0.0, 0.0, 5.0]])
    depth = project_to_depth(points, K, (21, 41))
    assert depth.shape == (21, 41) and depth.dtype == np.float32
    assert depth[12, 25] == pytest.approx(2.0)
    assert depth[10, 20] == pytest.approx(5.0)
    assert np.count_nonzero(depth) == 2


def test_project_to_depth_drops_points_behind_and_outside():
    points = np.array([
        [0.0, 0.0, -5.0],    # behind, would project onto the principal point
        [0.0, 0.0, 0.0],     # on the camera centre
        [10.0, 0.0, 1.0],    # u = 1020: right of the image
        [0.0, -10.0, 1.0],   # v = -990: above the image
        [0.1, 0.05, 1.0],    # u = 30, v = 15: kept
    ])
    depth = project_to_depth(points, K, (21, 41))
    assert np.count_nonzero(depth) == 1
    assert depth[15, 30] == pytest.approx(1.0)
    assert depth[10, 20] == 0


def test_project_to_depth_stores_z_not_range():
    # A point off-axis at z = 2: its Euclidean range is larger, the map stores 2.
    point = np.array([[0.18, 0.08, 2.0]])
    depth = project_to_depth(point, K, (21, 41))
    assert depth[14, 29] == pytest.approx(2.0)
    assert np.linalg.norm(point) > 2.009


def test_project_velodyne_applies_calibration():
    calib = _toy_calibration()
    # Velodyne: 5 m ahead, 0.25 m to the right (y = -0.25), 0.1 m up; and one behind.
    points = np.array([[5.0, -0.25, 0.1, 0.7], [2.5, -0.125, 0.05, 0.1], [-5.0, 0.0, 0.0, 0.3]], dtype=np.float32)
    depth = project_velodyne(points, calib)  # image size from the calibration
    assert depth.shape == (21, 41)
    # Camera: x = 0.25, y = -0.1, z = 5 -> u = 25, v = 8; the point at 2.5 m hides it.
    assert np.count_nonzero(depth) == 1
    assert depth[8, 25] == pytest.approx(2.5)
    np.testing.assert_array_equal(project_velodyne(points[:, :3], calib, (21, 41)), depth)


def test_project_velodyne_needs_an_image_size():
    calib = _toy_calibration(image_size=None)
    with pytest.raises(InputError, match="image_size: required when calib.image_size is None"):
        project_velodyne(np.zeros((3, 4)), calib)


@pytest.mark.parametrize("points, image_size, match", [
    (np.zeros((3, 2)), (21, 41), r"points_cam: expected an \(N, 3\+\) array.*\(3, 2\)"),
    (np.zeros(3), (21, 41), r"points_cam: expected.*\(3,\)"),
    (np.zeros((3, 3)), (0, 41), r"image_size: expected \(height, width\) of positive integers"),
    (np.zeros((3, 3)), (21,), r"image_size"),
])
def test_project_to_depth_rejects_bad_input(points, image_size, match):
    with pytest.raises(InputError, match=match):
        project_to_depth(points, K, image_size)
    with pytest.raises(InputError, match=r"P: expected a \(3, 4\).*\(2, 2\)"):
        project_to_depth(np.zeros((3, 3)), np.eye(2), (21, 41))


def _synthetic_scan(rings: int = 8, per_ring: int = 360, jitter: float = 0.01, seed: int = 0) -> np.ndarray:
    """Rings in scan order, each sweeping azimuth from just right of ahead round to just left."""
    rng = np.random.default_rng(seed)
    scans = []
    for ring in range(rings):
        azimuth = np.linspace(-np.pi + 0.05, np.pi - 0.05, per_ring) + rng.normal(0, jitter, per_ring)
        # atan2(-y, -x) = azimuth  <=>  (x, y) = -(cos, sin)
        radius = 10.0 + ring
        scans.append(np.stack([-radius * np.cos(azimuth), -radius * np.sin(azimuth),
                               np.full(per_ring, -0.1 * ring), np.zeros(per_ring)], axis=1))
    return np.concatenate(scans).astype(np.float32)


def test_recover_rings_synthetic_with_jitter():
    scan = _synthetic_scan(rings=8, jitter=0.01)
    assert np.count_nonzero(np.diff(np.arctan2(-scan[:, 1], -scan[:, 0])) < 0) > 8  # jitter goes backwards
    rings = recover_rings(scan)
    assert rings.dtype == np.int64 and rings.shape == (8 * 360,)
    np.testing.assert_array_equal(rings, np.repeat(np.arange(8), 360))


def test_ring_and_fraction_masks_partition_the_points():
    scan = _synthetic_scan(rings=8)
    mask = ring_mask(scan, 4, offset=1)
    np.testing.assert_array_equal(np.unique(recover_rings(scan)[mask]), [1, 5])
    np.testing.assert_array_equal(keep_every_ring(scan, 4, offset=1), scan[mask])
    assert np.count_nonzero(~mask) == 6 * 360  # the held-out points
    np.testing.assert_array_equal(ring_mask(scan, 1), np.ones(len(scan), dtype=bool))
    explicit = ring_mask(scan, 2, rings=np.arange(len(scan)))
    np.testing.assert_array_equal(explicit, np.arange(len(scan)) % 2 == 0)

    half = fraction_mask(scan, 0.5, seed=3)
    assert half.dtype == bool and np.count_nonzero(half) == len(scan) // 2
    np.testing.assert_array_equal(half, fraction_mask(scan, 0.5, seed=3))  # reproducible
    assert not np.array_equal(half, fraction_mask(scan, 0.5, seed=4))
    np.testing.assert_array_equal(keep_fraction(scan, 0.5, seed=3), scan[half])  # order kept
    generator = np.random.default_rng(3)
    np.testing.assert_array_equal(fraction_mask(scan, 0.5, seed=generator), half)
    assert fraction_mask(scan, 1.0).all()


@pytest.mark.parametrize("call, match", [
    (lambda s: ring_mask(s, 0), r"k: expected an integer >= 1.*got 0"),
    (lambda s: keep_every_ring(s, 2.5), r"k: expected an integer >= 1"),
    (lambda s: ring_mask(s, 4, offset=4), r"offset: expected an integer in \[0, 4\)"),
    (lambda s: ring_mask(s, 4, rings=np.zeros(3, dtype=int)), r"rings: expected an integer array of shape"),
    (lambda s: fraction_mask(s, 0.0), r"fraction: expected a number in \(0, 1\], got 0\.0"),
    (lambda s: keep_fraction(s, 1.5), r"fraction: expected a number in \(0, 1\], got 1\.5"),
    (lambda s: keep_fraction(s, float("nan")), r"fraction: expected a number in \(0, 1\]"),
    (lambda s: recover_rings(s[:, :1]), r"points: expected an \(N, 2\+\) array"),
])
def test_subsampling_validates_arguments(call, match):
    with pytest.raises(InputError, match=match):
        call(_synthetic_scan(rings=2, per_ring=20))


def test_subsampling_does_not_modify_input():
    scan = _synthetic_scan(rings=4)
    before = scan.copy()
    keep_every_ring(scan, 2)[:] = 0
    keep_fraction(scan, 0.3, seed=0)[:] = 0
    np.testing.assert_array_equal(scan, before)


def test_project_points_takes_either_calibration_type():
    """A toy KITTI Calibration, its RigCalibration view and a plain rig with the same
    K [I | 0] T give the same map as project_velodyne (hand-checked: 10 m ahead lands on
    the principal point)."""
    calib = _toy_calibration()
    points = np.array([[10.0, 0.0, 0.0, 0.3], [5.0, -0.5, 0.2, 0.1], [-3.0, 0.0, 0.0, 0.0]])
    expected = project_velodyne(points, calib)
    assert expected[10, 20] == pytest.approx(10.0) and np.count_nonzero(expected) == 2
    plain = RigCalibration(K=K, T_cam_lidar=VELO_TO_CAM)
    for calibration in (calib, RigCalibration.from_kitti(calib), plain):
        np.testing.assert_array_equal(project_points(points, calibration, (21, 41)), expected)
    with pytest.raises(InputError, match="calibration: expected a RigCalibration or a KITTI Calibration"):
        project_points(points, K, (21, 41))


def test_count_in_image_counts_before_the_z_buffer():
    # Two points on one pixel, one behind the camera, one outside: 2 land (1 pixel).
    points = np.array([[10.0, 0.0, 0.0], [20.0, 0.0, 0.0], [-10.0, 0.0, 0.0], [1.0, -5.0, 0.0]])
    assert count_in_image(points, VELO_TO_CAM, K, (21, 41)) == 2
    assert count_in_image(points, np.linalg.inv(VELO_TO_CAM), K, (21, 41)) == 0
    assert np.count_nonzero(project_to_depth(points @ VELO_TO_CAM[:3, :3].T, K, (21, 41))) == 1


# --------------------------------------------------------------------------- shared KITTI


def _all_scans(root):
    return (sorted((root / "raw" / "2011_09_26").glob("*/velodyne_points/data/*.bin"))
            + sorted((root / "object" / "training" / "velodyne").glob("*.bin")))


@pytest.fixture(scope="module")
def raw_frame(kitti_root):
    day = kitti_root / "raw" / "2011_09_26"
    points = read_velodyne(day / DRIVE / "velodyne_points" / "data" / f"{FRAME}.bin")
    calib = load_calibration(day, camera=2)
    official = read_depth_png(kitti_root / "depth_completion" / "data_depth_velodyne" / "train" / DRIVE
                              / "proj_depth" / "velodyne_raw" / "image_02" / f"{FRAME}.png")
    return points, calib, official


@pytest.mark.kitti
def test_projection_matches_official_velodyne_raw(raw_frame):
    points, calib, official = raw_frame
    depth = project_velodyne(points, calib, official.shape)
    ours, theirs = np.count_nonzero(depth), np.count_nonzero(official)
    assert theirs == 19154
    assert abs(ours - theirs) / theirs < 0.01  # measured: 19137
    both = (depth > 0) & (official > 0)
    assert np.count_nonzero(both) > 5000
    assert np.median(np.abs(depth[both] - official[both])) < 0.05  # metres; measured 0.033
    assert 1.0 < depth[depth > 0].min() and depth.max() < 90.0


@pytest.mark.kitti
def test_stored_depth_is_third_row_of_velo_to_image(raw_frame):
    points, calib, _ = raw_frame
    homogeneous = np.concatenate([points[:, :3], np.ones((len(points), 1))], axis=1).astype(np.float64)
    y = homogeneous @ calib.velo_to_image().T
    z_rect = (homogeneous @ calib.velo_to_rect_cam().T)[:, 2]
    np.testing.assert_allclose(y[:, 2] - z_rect, calib.P_rect[2, 3], atol=1e-9)
    depth = project_velodyne(points, calib)
    front = y[:, 2] > 0
    u = np.round(y[front, 0] / y[front, 2]).astype(int)
    v = np.round(y[front, 1] / y[front, 2]).astype(int)
    inside = (u >= 0) & (u < 1242) & (v >= 0) & (v < 375)
    # Every stored value is the smallest third-row z among the points of its pixel.
    nearest = np.full((375, 1242), np.inf)
    np.minimum.at(nearest, (v[inside], u[inside]), y[front][inside, 2])
    np.testing.assert_allclose(depth[depth > 0], nearest[depth > 0], rtol=1e-6)
    assert np.count_nonzero(depth) == np.count_nonzero(np.isfinite(nearest))


@pytest.mark.kitti
def test_recover_rings_finds_64_on_every_shared_scan(kitti_root):
    scans = _all_scans(kitti_root)
    assert len(scans) == 1 + 13 + 11
    for path in scans:
        rings = recover_rings(read_velodyne(path))
        assert abs(rings.max() + 1 - 64) <= 1, path
        assert np.all(np.diff(rings) >= 0) and rings.min() == 0
        assert np.bincount(rings).min() > 500, path  # no ring split into a sliver


@pytest.mark.kitti
def test_rings_run_top_to_bottom(raw_frame):
    points = raw_frame[0]
    rings = recover_rings(points)
    elevation = np.arctan2(points[:, 2], np.hypot(points[:, 0], points[:, 1]))
    medians = np.array([np.median(elevation[rings == r]) for r in range(rings.max() + 1)])
    assert np.all(np.diff(medians) < 0)
    assert np.degrees(medians[0]) > 2.0 and np.degrees(medians[-1]) < -23.0


@pytest.mark.kitti
def test_keep_every_fourth_ring_keeps_a_quarter_of_projected_points(raw_frame):
    points, calib, _ = raw_frame
    full = np.count_nonzero(project_velodyne(points, calib))
    per_offset = []
    for offset in range(4):
        kept = keep_every_ring(points, 4, offset=offset)
        share = np.count_nonzero(project_velodyne(kept, calib)) / full
        assert abs(share - 0.25) < 0.03  # measured 0.244-0.257
        per_offset.append(share)
    # The four offsets partition the rings: their pixels nearly sum to the full map.
    assert sum(per_offset) == pytest.approx(1.0, abs=0.02)


@pytest.mark.kitti
def test_keep_fraction_half(raw_frame):
    points, calib, _ = raw_frame
    kept = keep_fraction(points, 0.5, seed=0)
    assert len(kept) == round(0.5 * len(points))
    share = np.count_nonzero(project_velodyne(kept, calib)) / np.count_nonzero(project_velodyne(points, calib))
    assert abs(share - 0.5) < 0.02  # measured 0.500
