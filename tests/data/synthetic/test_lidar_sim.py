"""Tests for the simulated LiDAR (crfdepth/data/synthetic/lidar_sim.py)."""

from __future__ import annotations

import numpy as np
import pytest
from scipy import ndimage

from crfdepth.data.synthetic import SyntheticScene, lidar_elevations, make_scene
from crfdepth.errors import InputError


def _density(s: SyntheticScene) -> float:
    return float((s.sparse > 0).mean())


def _leaks(s: SyntheticScene) -> np.ndarray:
    """LiDAR pixels whose depth lies well behind the surface the camera sees."""
    d = s.depth
    return (s.sparse > 0) & (d > 0) & (s.sparse > d + np.maximum(1.0, 0.1 * d))


def test_sparse_density_like_kitti(scene, scene16):
    d64 = _density(scene)
    assert 0.03 < d64 < 0.06
    # The 16-beam scanner keeps every fourth beam: about a quarter of the density.
    assert 0.2 < _density(scene16) / d64 < 0.3
    assert 0.4 < _density(make_scene(0, beams=32)) / d64 < 0.6


def test_sparse_agrees_with_depth_except_edge_leaks(scene, scene16):
    for s in (scene, scene16):
        valid = s.sparse > 0
        assert (s.depth[valid] > 0).all()  # every return hit a surface the camera sees too
        err = np.abs(s.sparse[valid] - s.depth[valid])
        assert np.median(err) < 0.05  # 2 cm range noise plus sub-pixel rounding
        # Points from the background seen past the edges of foreground objects (the
        # LiDAR sits behind and above the camera): present, but a small minority.
        leak = _leaks(s)[valid].mean()
        assert 0.0 < leak < 0.05


def test_leaks_lie_at_depth_edges(scene):
    # Parallax between the two viewpoints (0.27 m apart) shifts a nearby object's edge by
    # up to ~20 px, so "near an edge" means within +-4 rows and +-15 columns of one.
    d, valid = scene.depth, scene.sparse > 0
    size = (9, 31)
    edge = ndimage.maximum_filter(d, size=size) > 1.1 * ndimage.minimum_filter(d, size=size) + 0.5
    near_edge = edge[valid].mean()  # share of all LiDAR pixels near an edge
    assert near_edge < 0.4
    assert edge[_leaks(scene)].mean() > 0.75  # leaks concentrate there


def test_points_rings_and_intensity(scene):
    p = scene.points
    rng = np.linalg.norm(p[:, :3], axis=1)
    assert rng.min() >= 0.9 and rng.max() <= 100.2
    assert 0.0 <= p[:, 3].min() and p[:, 3].max() <= 1.0
    assert scene.rings.min() == 0 and scene.rings.max() == 63
    # Range noise moves points along the beam: each ring keeps its elevation.
    elev = np.degrees(np.arctan2(p[:, 2], np.linalg.norm(p[:, :2], axis=1)))
    medians = np.array([np.median(elev[scene.rings == r]) for r in range(64)])
    np.testing.assert_allclose(medians, lidar_elevations(64), atol=0.1)
    assert medians[0] == pytest.approx(-24.8, abs=0.1)
    assert medians[-1] == pytest.approx(2.0, abs=0.1)
    # A full 360-degree scan: points behind the car too.
    assert (p[:, 0] < -5).sum() > 1000


def test_lidar_elevations_checks_input():
    with pytest.raises(InputError, match="beams"):
        lidar_elevations(0)
    assert lidar_elevations(16).shape == (16,)
    assert np.all(np.diff(lidar_elevations(32)) > 0)


def test_mount_is_a_rigid_kitti_like_transform():
    from crfdepth.data.synthetic.lidar_sim import LIDAR_IN_CAMERA_M, lidar_to_camera

    T = lidar_to_camera()
    R = T[:3, :3]
    np.testing.assert_array_equal(R @ R.T, np.eye(3))
    assert np.linalg.det(R) == pytest.approx(1.0)
    np.testing.assert_array_equal(T[:3, 3], LIDAR_IN_CAMERA_M)
    # LiDAR x (forward) is camera z, LiDAR y (left) is camera -x, LiDAR z (up) is camera -y.
    np.testing.assert_allclose(T @ [1.0, 0, 0, 1], [0.06, -0.08, 0.73, 1.0])
    np.testing.assert_allclose(T @ [0, 1.0, 0, 1], [-0.94, -0.08, -0.27, 1.0])
    np.testing.assert_allclose(T @ [0, 0, 1.0, 1], [0.06, -1.08, -0.27, 1.0])


def test_scan_of_the_bare_ground(make_world):
    """Known answer: every return lies on the ground, 1.73 m below the LiDAR; full rings only."""
    from crfdepth.data.synthetic.lidar_sim import scan_lidar
    from crfdepth.data.synthetic.world import CAMERA_HEIGHT_M, PLANE, ROAD

    g = CAMERA_HEIGHT_M
    w = make_world([(PLANE, ROAD, (-1e6, g, -1e6), (1e6, g, 1e6))])
    points, rings = scan_lidar(w, np.random.default_rng(0), 16, 1.0, 100.0, 0.0, 0.0)
    assert points.dtype == np.float32 and points.shape[1] == 4 and len(rings) == len(points)
    np.testing.assert_allclose(points[:, 2], -(g + 0.08), atol=1e-4)
    r = np.linalg.norm(points[:, :3], axis=1)
    assert r.min() >= 1.0 and r.max() <= 100.0
    # The ground is the same in every direction: each ring hits at all 360 azimuths or none.
    counts = np.bincount(rings)
    assert set(counts[counts > 0].tolist()) == {360}
    assert rings.max() < 15  # the top beam (+2 degrees) never reaches the ground
    assert np.all(np.diff(rings) >= 0)  # ordered by ring
