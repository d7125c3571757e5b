"""Tests for value noise and material textures (crfdepth/data/synthetic/texture.py)."""

from __future__ import annotations

import numpy as np

from crfdepth.data.synthetic.texture import textured_albedo, value_noise
from crfdepth.data.synthetic.world import CAMERA_HEIGHT_M, FOLIAGE, PLANE, ROAD, SPHERE

G = CAMERA_HEIGHT_M


def test_value_noise_interpolates_the_table():
    table = np.random.default_rng(1).random((256, 256), dtype=np.float32)
    u = np.array([3.0, 250.0, 3.0 + 256.0])
    v = np.array([5.0, 17.0, 5.0 - 512.0])
    out = value_noise(table, u, v)
    assert out.dtype == np.float32
    # At lattice points the noise is the table entry (row v, column u), periodic in 256.
    np.testing.assert_array_equal(out, [table[5, 3], table[17, 250], table[5, 3]])
    grid_u, grid_v = np.meshgrid(np.linspace(-40, 40, 301), np.linspace(0, 20, 101))
    n = value_noise(table, grid_u, grid_v)
    assert n.shape == grid_u.shape and 0.0 <= n.min() and n.max() <= 1.0
    # Smooth: neighbouring samples 0.27 apart differ by less than the table's range.
    assert np.abs(np.diff(n, axis=1)).max() < 0.5
    assert np.abs(np.diff(n, axis=1)).mean() < 0.1


def test_road_marking_is_brighter_than_asphalt(make_world):
    w = make_world([(PLANE, ROAD, (-1e6, G, -1e6), (1e6, G, 1e6))])
    p = np.array([[1.75, G, 10.0], [0.0, G, 10.0]], dtype=np.float32).T  # on the edge line; in the lane
    n = np.tile(np.array([[0.0], [-1.0], [0.0]], dtype=np.float32), (1, 2))
    col, n_out = textured_albedo(w, np.array([0, 0]), p, n.copy())
    assert col.shape == (3, 2) and col.dtype == np.float32
    assert ((0.0 <= col) & (col <= 1.0)).all()
    assert (col[:, 0] > col[:, 1] + 0.3).all()
    np.testing.assert_array_equal(n_out, n)  # the road keeps its normals


def test_foliage_perturbs_normals_but_keeps_them_unit(make_world):
    w = make_world([(SPHERE, FOLIAGE, (-1.0, -1.0, 9.0), (1.0, 1.0, 11.0))])
    rng = np.random.default_rng(0)
    n = rng.normal(size=(3, 50)).astype(np.float32)
    n /= np.linalg.norm(n, axis=0)
    p = (np.array([[0.0], [0.0], [10.0]]) + n).astype(np.float32)
    col, n_out = textured_albedo(w, np.zeros(50, dtype=np.int64), p, n.copy())
    assert ((0.0 <= col) & (col <= 1.0)).all() and col.std() > 0.01
    np.testing.assert_allclose(np.linalg.norm(n_out, axis=0), 1.0, atol=1e-5)
    assert np.abs(n_out - n).max() > 0.05
