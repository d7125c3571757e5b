"""Tests for the synthetic camera: intrinsics and render (crfdepth/data/synthetic/camera.py)."""

from __future__ import annotations

import numpy as np
import pytest

from crfdepth.data.synthetic import CAMERA_HEIGHT_M, KITTI_FOCAL_PX, camera_intrinsics
from crfdepth.errors import InputError


def test_intrinsics_kitti_like():
    K = camera_intrinsics(352, 1216)
    assert K[0, 0] == pytest.approx(KITTI_FOCAL_PX) and K[1, 1] == K[0, 0]
    assert abs(K[0, 2] - 608) < 20 and 0.3 * 352 < K[1, 2] < 0.6 * 352
    K2 = camera_intrinsics(480, 640)
    assert K2[0, 0] == pytest.approx(KITTI_FOCAL_PX * 640 / 1216)


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


def test_camera_intrinsics_checks_input():
    with pytest.raises(InputError, match="width"):
        camera_intrinsics(352, 0)


def test_render_of_the_bare_ground_is_the_ground_plane(make_world):
    """Known answer: a world of only the ground; z = f h / (v - cy) below the horizon, sky above."""
    from crfdepth.data.synthetic.camera import render_camera
    from crfdepth.data.synthetic.world import PLANE, ROAD

    g = CAMERA_HEIGHT_M
    w = make_world([(PLANE, ROAD, (-1e6, g, -1e6), (1e6, g, 1e6))])
    h, wd = 48, 64
    K = camera_intrinsics(h, wd)
    image, depth = render_camera(w, K, h, wd, np.random.default_rng(0), 0.0)
    assert image.shape == (h, wd, 3) and image.dtype == np.float32
    assert depth.shape == (h, wd) and depth.dtype == np.float32
    assert 0.0 <= image.min() and image.max() <= 1.0
    v = np.arange(h)
    below = v > K[1, 2]
    expected = (K[1, 1] * g / (v[below] - K[1, 2])).astype(np.float32)
    np.testing.assert_allclose(depth[below], np.broadcast_to(expected[:, None], (below.sum(), wd)), rtol=1e-6)
    assert (depth[~below] == 0).all()
    # The sky is bluer than the road.
    assert image[0, :, 2].mean() > image[-1, :, 2].mean()
