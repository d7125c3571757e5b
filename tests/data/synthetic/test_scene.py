"""Tests for make_scene and SyntheticScene (crfdepth/data/synthetic/scene.py)."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from crfdepth.data.synthetic import KITTI_FOCAL_PX, make_scene
from crfdepth.errors import InputError
from crfdepth.geometry.projection import project_to_depth


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
