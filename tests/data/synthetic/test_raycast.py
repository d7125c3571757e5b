"""Tests for ray casting against primitives (crfdepth/data/synthetic/raycast.py), known answers."""

from __future__ import annotations

import math

import numpy as np
import pytest

from crfdepth.data.synthetic.camera import camera_intrinsics
from crfdepth.data.synthetic.raycast import camera_windows, cast_rays, intersect, surface_normals
from crfdepth.data.synthetic.world import (
    BOX,
    CAMERA_HEIGHT_M,
    CYLINDER,
    FACADE,
    FOLIAGE,
    PLANE,
    POLE,
    ROAD,
    SPHERE,
    TINY,
    build_world,
)

G = CAMERA_HEIGHT_M
ROWS = [
    (BOX, FACADE, (-1.0, -1.0, 5.0), (1.0, 1.0, 6.0)),        # 0: box 5 m ahead
    (SPHERE, FOLIAGE, (-2.0, -2.0, 8.0), (2.0, 2.0, 12.0)),   # 1: sphere, centre z = 10, r = 2
    (CYLINDER, POLE, (4.0, -3.0, 9.0), (6.0, G, 11.0)),       # 2: vertical cylinder at x = 5, z = 10, r = 1
    (PLANE, ROAD, (-1e6, G, -1e6), (1e6, G, 1e6)),            # 3: the ground
]


def rays(*directions):
    """A (1, N) bundle of directions and their inverses (zeros replaced as the renderer does)."""
    d = np.array(directions, dtype=np.float64).T[:, None, :]
    d = np.where(np.abs(d) < TINY, TINY, d)
    return tuple(d), tuple(1.0 / d)


def test_intersect_known_answers(make_world):
    w = make_world(ROWS)
    o = (0.0, 0.0, 0.0)
    d, inv = rays((0, 0, 1))
    assert intersect(w, 0, o, d, inv)[0, 0] == pytest.approx(5.0)
    assert intersect(w, 1, o, d, inv)[0, 0] == pytest.approx(8.0)
    # (0.5 t - 5)^2 + (t - 10)^2 = 1  ->  t = (25 - sqrt(5)) / 2.5
    d, inv = rays((0.5, 0, 1))
    assert intersect(w, 2, o, d, inv)[0, 0] == pytest.approx((25 - math.sqrt(5)) / 2.5)
    d, inv = rays((0, 1, 1), (0, -1, 1))
    t = intersect(w, 3, o, d, inv)[0]
    assert t[0] == pytest.approx(G) and np.isinf(t[1])  # the ground is seen from above only
    d, inv = rays((1, 0, 0.01))
    assert np.isinf(intersect(w, 0, o, d, inv)[0, 0])


def test_shadow_rays_from_inside_a_box(make_world):
    w = make_world(ROWS)
    d, inv = rays((0, 0, 1))
    inside = (0.0, 0.0, 5.5)
    assert np.isinf(intersect(w, 0, inside, d, inv)[0, 0])
    assert np.isfinite(intersect(w, 0, inside, d, inv, any_hit=True)[0, 0])


def test_cast_rays_keeps_the_nearest_hit(make_world):
    w = make_world(ROWS)
    d, inv = rays((0, 0, 1), (0.5, 0, 1), (0, 1, 1), (0, -1, 1))
    full = [(i, slice(None), slice(None)) for i in range(len(ROWS))]
    t, idx = cast_rays(w, (1, 4), (0.0, 0.0, 0.0), d, inv, full)
    assert idx[0].tolist() == [0, 2, 3, -1]  # box before sphere; cylinder; ground; sky
    np.testing.assert_allclose(t[0, :3], [5.0, (25 - math.sqrt(5)) / 2.5, G])
    assert np.isinf(t[0, 3])


def test_surface_normals_known_answers(make_world):
    w = make_world(ROWS)
    idx = np.array([0, 0, 1, 2, 3])
    p = np.array([[0.0, 0.0, 5.0], [1.0, 0.2, 5.5], [0.0, 0.0, 8.0], [4.0, 0.5, 10.0], [3.0, G, 20.0]]).T
    n = surface_normals(w, idx, p)
    assert n.shape == (3, 5) and n.dtype == np.float32
    expected = [[0, 0, -1], [1, 0, 0], [0, 0, -1], [-1, 0, 0], [0, -1, 0]]
    np.testing.assert_allclose(n.T, expected, atol=1e-6)


def test_camera_windows_lose_no_hit():
    """Oracle: casting every primitive over the whole image gives the same nearest hits."""
    w = build_world(np.random.default_rng(2))
    h, wd = 60, 200
    K = camera_intrinsics(h, wd)
    dx = ((np.arange(wd) - K[0, 2]) / K[0, 0])[None, :]
    dy = ((np.arange(h) - K[1, 2]) / K[1, 1])[:, None]
    dx = np.where(np.abs(dx) < TINY, TINY, dx)
    dy = np.where(np.abs(dy) < TINY, TINY, dy)
    dz = np.ones((1, 1))
    d, inv = (dx, dy, dz), (1.0 / dx, 1.0 / dy, dz)
    windows = camera_windows(w, K, h, wd)
    assert len(windows) < len(w.kind)  # primitives behind the camera are skipped
    full = [(i, slice(None), slice(None)) for i in range(len(w.kind))]
    t_win, i_win = cast_rays(w, (h, wd), (0.0, 0.0, 0.0), d, inv, windows)
    t_all, i_all = cast_rays(w, (h, wd), (0.0, 0.0, 0.0), d, inv, full)
    np.testing.assert_array_equal(i_win, i_all)
    np.testing.assert_array_equal(t_win, t_all)
