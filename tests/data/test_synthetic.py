"""Tests for the built-in synthetic street scene (crfdepth/data/synthetic.py)."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from scipy import ndimage

from crfdepth.data.synthetic import (
    CAMERA_HEIGHT_M,
    KITTI_FOCAL_PX,
    SyntheticScene,
    camera_intrinsics,
    lidar_elevations,
    make_scene,
)
from crfdepth.errors import InputError
from crfdepth.projection import project_to_depth


@pytest.fixture(scope="module")
def scene() -> SyntheticScene:
    return make_scene(0)


@pytest.fixture(scope="module")
def scene16() -> SyntheticScene:
    return make_scene(0, beams=16)


def _density(s: SyntheticScene) -> float:
    return float((s.sparse > 0).mean())


def _leaks(s: SyntheticScene) -> np.ndarray:
    """LiDAR pixels whose depth lies well behind the surface the camera sees."""
    d = s.depth
    return (s.sparse > 0) & (d > 0) & (s.sparse > d + np.maximum(1.0, 0.1 * d))


def test_shapes_dtypes_and_ranges(scene):
    h, w = 352, 1216
    assert scene.image.shape == (h, w, 3) and scene.image.dtype == np.float32
    assert scene.depth.shape == (h, w) and scene.depth.dtype == np.float32
    assert scene.sparse.shape == (h, w) and scene.sparse.dtype == np.float32
    assert scene.K.shape == (3, 3) and scene.K.dtype == np.float64
    assert scene.T_cam_lidar.shape == (4, 4) and scene.T_cam_lidar.dtype == np.float64
    assert scene.points.ndim == 2 and scene.points.shape[1] == 4
    assert scene.points.dtype == np.float32
    assert scene.rings.shape == (len(scene.points),)
    assert np.issubdtype(scene.rings.dtype, np.integer)
    assert scene.name == "synthetic-seed0"
    assert 0.0 <= scene.image.min() and scene.image.max() <= 1.0
    assert scene.image.std() > 0.05  # textured, not flat
    assert (scene.depth >= 0).all() and (scene.sparse >= 0).all()
    assert np.isfinite(scene.depth).all() and np.isfinite(scene.sparse).all()


def test_intrinsics_kitti_like():
    K = camera_intrinsics(352, 1216)
    assert K[0, 0] == pytest.approx(KITTI_FOCAL_PX) and K[1, 1] == K[0, 0]
    assert abs(K[0, 2] - 608) < 20 and 0.3 * 352 < K[1, 2] < 0.6 * 352
    K2 = camera_intrinsics(480, 640)
    assert K2[0, 0] == pytest.approx(KITTI_FOCAL_PX * 640 / 1216)


def test_deterministic_for_a_seed(scene):
    again = make_scene(0)
    for field in ("image", "depth", "sparse", "K", "points", "rings", "T_cam_lidar"):
        np.testing.assert_array_equal(getattr(again, field), getattr(scene, field))


def test_different_seeds_differ(scene):
    other = make_scene(1)
    assert other.name != scene.name
    assert np.abs(other.image - scene.image).mean() > 0.02
    assert (np.abs(other.depth - scene.depth) > 0.5).mean() > 0.1
    assert not np.array_equal(other.sparse, scene.sparse)


def test_global_random_state_untouched():
    state = np.random.get_state()[1].copy()
    torch_state = torch.random.get_rng_state().clone()
    make_scene(5, 48, 160)
    assert np.array_equal(np.random.get_state()[1], state)
    assert torch.equal(torch.random.get_rng_state(), torch_state)


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


def test_points_project_to_sparse(scene):
    T = scene.T_cam_lidar
    R = T[:3, :3]
    np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-12)
    assert np.linalg.det(R) == pytest.approx(1.0)
    np.testing.assert_array_equal(T[3], [0, 0, 0, 1])
    # KITTI-like mount: the LiDAR origin is behind and above the camera.
    assert T[2, 3] < -0.1 and T[1, 3] < 0
    pts_cam = scene.points[:, :3].astype(np.float64) @ R.T + T[:3, 3]
    np.testing.assert_array_equal(project_to_depth(pts_cam, scene.K, (352, 1216)), scene.sparse)


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


def test_depth_ground_objects_and_sky(scene):
    d, K = scene.depth, scene.K
    h, w = d.shape
    cy = K[1, 2]
    # Every pixel below the horizon sees a surface; sky (0) only above it.
    rows = np.arange(h)
    assert (d[rows > cy + 1] > 0).all()
    sky_rows = np.nonzero((d == 0).any(axis=1))[0]
    assert len(sky_rows) > 0 and sky_rows.max() < cy
    assert (d[0] == 0).mean() > 0.02  # some sky in the top row
    assert (d > 0).mean() > 0.8
    # Known answer: the road is the plane y = camera height, z = f * h / (v - cy).
    v = h - 1
    plane = K[1, 1] * CAMERA_HEIGHT_M / (v - cy)
    on_road = np.abs(d[v] - plane) < 1e-4 * plane
    assert on_road.mean() > 0.4
    # Objects stand out of the ground: many pixels nearer than the ground would be.
    below = np.maximum(rows[:, None] - cy, 1e-9)
    ground_z = np.where(rows[:, None] > cy, K[1, 1] * CAMERA_HEIGHT_M / below, np.inf)
    assert ((d > 0) & (d < 0.9 * ground_z)).mean() > 0.2


def test_to_tensors(scene):
    t = scene.to_tensors()
    assert set(t) == {"image", "sparse", "depth", "K", "target"}
    assert t["image"].shape == (3, 352, 1216) and t["image"].dtype == torch.float32
    assert t["sparse"].shape == (1, 352, 1216) and t["depth"].shape == (1, 352, 1216)
    assert t["K"].shape == (3, 3) and t["K"].dtype == torch.float32
    np.testing.assert_array_equal(t["image"].numpy(), scene.image.transpose(2, 0, 1))
    np.testing.assert_array_equal(t["sparse"][0].numpy(), scene.sparse)
    t["sparse"].fill_(-1.0)  # tensors do not share memory with the scene
    assert (scene.sparse >= 0).all()


def test_target_is_the_depth_below_the_first_scan_line_up_to_80_m(scene):
    target = scene.target()
    first = int(np.flatnonzero((scene.sparse > 0).any(axis=1))[0])
    assert not target[:first].any() and target.max() <= 80.0
    kept = target > 0
    np.testing.assert_array_equal(target[kept], scene.depth[kept])
    assert kept.mean() > 0.5  # most of the image below the scan lines is evaluated


def test_non_kitti_size():
    s = make_scene(3, height=480, width=640, beams=32)
    assert s.image.shape == (480, 640, 3) and s.depth.shape == (480, 640)
    assert s.sparse.shape == (480, 640)
    assert s.K[0, 0] == pytest.approx(KITTI_FOCAL_PX * 640 / 1216)
    valid = s.sparse > 0
    assert 0.005 < valid.mean() < 0.06
    assert np.median(np.abs(s.sparse[valid] - s.depth[valid])) < 0.05
    assert (s.depth[0] == 0).any() and (s.depth[-1] > 0).all()


@pytest.mark.parametrize(
    "kwargs, name",
    [
        ({"height": 0}, "height"),
        ({"width": -5}, "width"),
        ({"height": 352.0}, "height"),
        ({"beams": 0}, "beams"),
        ({"beams": 1000}, "beams"),
        ({"seed": -1}, "seed"),
        ({"seed": 1.5}, "seed"),
        ({"azimuth_step_deg": 0.0}, "azimuth_step_deg"),
        ({"max_range": -1.0}, "max_range"),
        ({"range_noise_std": -0.1}, "range_noise_std"),
        ({"dropout": 1.0}, "dropout"),
        ({"image_noise_std": float("nan")}, "image_noise_std"),
    ],
)
def test_bad_arguments_raise_input_error(kwargs, name):
    with pytest.raises(InputError, match=name) as info:
        make_scene(**kwargs)
    value = next(iter(kwargs.values()))
    assert repr(value) in str(info.value) or str(value) in str(info.value)


def test_public_helpers_check_input():
    with pytest.raises(InputError, match="width"):
        camera_intrinsics(352, 0)
    with pytest.raises(InputError, match="beams"):
        lidar_elevations(0)
    assert lidar_elevations(16).shape == (16,)
    assert np.all(np.diff(lidar_elevations(32)) > 0)
