"""Tests for the synthetic street's primitives (crfdepth/data/synthetic/world.py)."""

from __future__ import annotations

import numpy as np

from crfdepth.data.synthetic.world import (
    BOX,
    CAMERA_HEIGHT_M,
    N_MATERIALS,
    PLANE,
    ROAD,
    SPHERE,
    build_world,
    road_markings,
)


def test_build_world_is_deterministic_for_a_generator_seed():
    a = build_world(np.random.default_rng(4))
    b = build_world(np.random.default_rng(4))
    c = build_world(np.random.default_rng(5))
    for field in ("kind", "mat", "lo", "hi", "albedo", "style", "sun", "noise"):
        np.testing.assert_array_equal(getattr(a, field), getattr(b, field))
    assert a.lo.shape != c.lo.shape or not np.array_equal(a.lo, c.lo)


def test_world_structure():
    w = build_world(np.random.default_rng(0))
    n = len(w.kind)
    assert w.lo.shape == w.hi.shape == (n, 3) and w.albedo.shape == (n, 3) and w.style.shape == (n, 4)
    # The ground plane (road material) is the last primitive, and the only plane.
    assert w.kind[-1] == PLANE and w.mat[-1] == ROAD and (w.kind[:-1] != PLANE).all()
    assert (w.lo <= w.hi).all()
    assert ((0 <= w.mat) & (w.mat < N_MATERIALS)).all()
    assert ((w.albedo >= 0) & (w.albedo <= 1)).all()
    assert w.ground_y == CAMERA_HEIGHT_M
    # Objects stand on the ground (y down): nothing reaches below it.
    assert (w.hi[:-1, 1] <= CAMERA_HEIGHT_M + 1e-9).all()
    # Spheres (foliage) have equal extents on all axes.
    s = w.kind == SPHERE
    np.testing.assert_allclose((w.hi - w.lo)[s, 0], (w.hi - w.lo)[s, 1])
    assert (w.kind == BOX).sum() > 20  # façades, cars, sidewalks
    # The sun is above the horizon (y down) and a unit vector.
    assert w.sun[1] < 0 and abs(np.linalg.norm(w.sun) - 1.0) < 1e-12
    assert w.noise.shape == (256, 256) and w.noise.dtype == np.float32
    assert 0.0 <= w.noise.min() and w.noise.max() < 1.0
    # Channel-first copies used by the renderer.
    np.testing.assert_allclose(w.centre_t.T, 0.5 * (w.lo + w.hi), rtol=1e-6)


def test_road_markings_solid_and_dashed_lines(make_world):
    w = make_world([(PLANE, ROAD, (-1e6, CAMERA_HEIGHT_M, -1e6), (1e6, CAMERA_HEIGHT_M, 1e6))])
    z = np.linspace(0.0, 30.0, 301)
    # Solid edge lines: marked everywhere along z, 7.5 cm either side.
    assert road_markings(w, np.full_like(z, 1.75), z).all()
    assert road_markings(w, np.full_like(z, -5.25 + 0.07), z).all()
    assert not road_markings(w, np.full_like(z, 1.75 + 0.08), z).any()
    # Between the lines: no marking.
    assert not road_markings(w, np.full_like(z, 0.0), z).any()
    # The divider is dashed: 3 m painted out of every 9 m.
    dashed = road_markings(w, np.full_like(z, -1.75), z)
    assert dashed.any() and not dashed.all()
    np.testing.assert_array_equal(dashed, np.mod(z, 9.0) < 3.0)
