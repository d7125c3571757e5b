"""make_sequence: the synthetic street along a camera path, true poses, moving cars."""

from __future__ import annotations

import math

import numpy as np
import pytest

from crfdepth.data.synthetic import SyntheticScene, ego_pose, make_sequence
from crfdepth.data.synthetic.camera import camera_intrinsics, render_camera
from crfdepth.errors import InputError

H, W = 176, 608  # half the default size: a 10-frame sequence builds in about 1.5 s


@pytest.fixture(scope="module")
def straight():
    return make_sequence(10, 3, speed=10.0, movers=2, height=H, width=W)


@pytest.fixture(scope="module")
def curve():
    return make_sequence(6, 1, speed=8.0, rate=10.0, yaw_rate=12.0, height=H, width=W)


def _rigid(T):
    return np.allclose(T[:3, :3] @ T[:3, :3].T, np.eye(3), atol=1e-12) and np.allclose(T[3], [0, 0, 0, 1])


def test_frames_carry_what_make_scene_gives(straight):
    f = straight[4]
    assert isinstance(f, SyntheticScene) and len(straight) == 10
    assert f.image.shape == (H, W, 3) and f.depth.shape == (H, W) and f.sparse.shape == (H, W)
    assert f.points.shape[1] == 4 and f.rings.shape == (len(f.points),)
    assert f.mover_points.shape == (len(f.points),) and f.mover_pixels.shape == (H, W)
    np.testing.assert_allclose(f.K, camera_intrinsics(H, W))
    np.testing.assert_allclose(f.T_w_lidar, f.T_w_cam @ f.T_cam_lidar, atol=1e-12)
    assert f.index == 4 and f.time == pytest.approx(0.4, abs=1e-12)
    # about 4-5 % of the pixels of a full-size frame hold a return; at half size more are shared
    assert 0.05 < (f.sparse > 0).mean() < 0.25


def test_poses_follow_the_speed_straight(straight):
    P = straight.camera_poses()
    np.testing.assert_allclose(P[0], np.eye(4), atol=0)
    steps = np.linalg.norm(np.diff(P[:, :3, 3], axis=0), axis=1)
    np.testing.assert_allclose(steps, 10.0 / 10.0, atol=1e-9)
    np.testing.assert_allclose(P[:, :3, :3], np.broadcast_to(np.eye(3), (10, 3, 3)), atol=1e-12)
    assert P[-1, 2, 3] == pytest.approx(9.0, abs=1e-9)  # forward is +z of the camera
    # LiDAR odometry's view: relative LiDAR poses, forward is +x of the LiDAR
    L = straight.lidar_poses()
    np.testing.assert_allclose(L[0], np.eye(4), atol=1e-12)
    np.testing.assert_allclose(L[-1, :3, 3], [9.0, 0.0, 0.0], atol=1e-9)


def test_poses_follow_the_speed_on_a_curve(curve):
    P = curve.camera_poses()
    assert all(_rigid(T) for T in P)
    w, dt, v = math.radians(12.0), 0.1, 8.0
    chord = 2 * v / w * math.sin(w * dt / 2)  # the arc's chord between two frames
    steps = np.linalg.norm(np.diff(P[:, :3, 3], axis=0), axis=1)
    np.testing.assert_allclose(steps, chord, atol=1e-9)
    assert chord == pytest.approx(0.8, abs=2e-4)
    # the heading turns by yaw_rate / rate per frame, to the left (towards -x)
    yaw = np.degrees(np.arctan2(-P[:, 0, 2], P[:, 2, 2]))
    np.testing.assert_allclose(np.diff(yaw), 1.2, atol=1e-9)
    assert P[-1, 0, 3] < -0.05  # drifted left
    # in the LiDAR frame (z up) the turn is a positive yaw
    L = curve.lidar_poses()
    lyaw = np.degrees(np.arctan2(L[:, 1, 0], L[:, 0, 0]))
    np.testing.assert_allclose(lyaw, 1.2 * np.arange(6), atol=1e-9)


def _backproject(depth, K, rows, cols):
    z = depth[rows, cols].astype(np.float64)
    x = (cols - K[0, 2]) / K[0, 0] * z
    y = (rows - K[1, 2]) / K[1, 1] * z
    return np.stack([x, y, z, np.ones_like(z)])


def _static_reprojection_errors(seq, a, b, shift=(0.0, 0.0, 0.0)):
    """Relative depth errors of frame a's static pixels seen in frame b: back-project with a's
    true depth, move with the true poses, compare with b's depth interpolated where b's
    surface is planar (inverse depth affine in the pixel over the 2x2 neighbourhood).
    Signed: negative where frame b sees something in front (the point is occluded there).
    ``shift``: metres added to the relative translation (a wrong pose)."""
    fa, fb = seq[a], seq[b]
    K = fa.K
    rows, cols = np.nonzero((fa.depth > 0) & (fa.depth < 40) & ~fa.moving_pixels)
    X = _backproject(fa.depth, K, rows, cols)
    Xb = np.linalg.inv(fb.T_w_cam) @ fa.T_w_cam @ X
    Xb[:3] += np.asarray(shift)[:, None]
    z = Xb[2]
    u, v = K[0, 0] * Xb[0] / z + K[0, 2], K[1, 1] * Xb[1] / z + K[1, 2]
    ok = (z > 1) & (u >= 0) & (v >= 0) & (u < W - 1) & (v < H - 1)
    u, v, z = u[ok], v[ok], z[ok]
    c0, r0 = np.floor(u).astype(int), np.floor(v).astype(int)
    q = [fb.depth[r0 + i, c0 + j] for i in (0, 1) for j in (0, 1)]
    inv = [1.0 / np.maximum(d, 1e-6) for d in q]
    valid = np.all([d > 0 for d in q], axis=0) & np.all([fb.mover_pixels[r0 + i, c0 + j] < 0
                                                        for i in (0, 1) for j in (0, 1)], axis=0)
    twist = np.abs(inv[0] - inv[1] - inv[2] + inv[3])  # 0 for an affine inverse depth
    planar = valid & (twist < 1e-4 * inv[0])
    fu, fv = u - c0, v - r0
    interp = ((1 - fv) * ((1 - fu) * inv[0] + fu * inv[1]) + fv * ((1 - fu) * inv[2] + fu * inv[3]))
    rel = (1.0 / interp[planar] - z[planar]) / z[planar]
    return rel, planar.mean()


@pytest.mark.parametrize("which,a,b", [("straight", 0, 6), ("curve", 0, 5), ("curve", 4, 1)])
def test_static_points_have_consistent_depth_across_frames(which, a, b, request):
    seq = request.getfixturevalue(which)
    rel, share = _static_reprojection_errors(seq, a, b)
    assert share > 0.3 and rel.size > 5000  # most pixels land on a planar patch of frame b
    # surfaces the camera sees in both frames: their depths agree to float32 precision
    # (measured: median 3e-8, 92-97 % within 1e-4); the rest are occluded in frame b (b sees
    # something in front: measured 2-6 %), or a thin pole or sign edge of frame a falls
    # between frame b's pixel centres (b sees the surface behind: measured 0.7-1.7 %)
    assert np.median(np.abs(rel)) < 1e-5
    assert np.mean(np.abs(rel) < 1e-4) > 0.9
    assert np.mean(rel > 1e-3) < 0.025
    # a pose off by 5 cm (3 cm along each axis) is seen
    wrong, _ = _static_reprojection_errors(seq, a, b, shift=(0.03, 0.03, 0.03))
    assert np.median(np.abs(wrong)) > 1e-3


def test_lidar_points_lie_on_the_rendered_surfaces(curve):
    """Static returns of scan 5 moved into camera 0 with the true poses hit frame 0's depth."""
    f0, f5 = curve[0], curve[5]
    p = f5.points[:, :3].astype(np.float64)
    ph = np.c_[p, np.ones(len(p))].T
    X = np.linalg.inv(f0.T_w_cam) @ f5.T_w_lidar @ ph
    K = f0.K
    z = X[2]
    u = np.round(K[0, 0] * X[0] / z + K[0, 2]).astype(int)
    v = np.round(K[1, 1] * X[1] / z + K[1, 2]).astype(int)
    ok = (z > 2) & (z < 30) & (u >= 0) & (v >= 0) & (u < W) & (v < H)
    d = f0.depth[v[ok], u[ok]]
    rel = np.abs(d - z[ok]) / z[ok]
    # range noise 2 cm and half a pixel of rounding; occluded and edge returns differ
    assert np.median(rel) < 0.01
    assert np.mean(rel < 0.05) > 0.85


def test_movers_move_by_their_velocity(straight):
    v = straight.mover_velocities
    assert v.shape == (2, 3) and np.all(v[:, 2] > 5) and np.all(v[:, :2] == 0)
    body = straight.mover_parts[:, 0]
    for k in (0, 5, 9):
        world = straight.world_at(straight[k].time)
        np.testing.assert_allclose(world.lo[body], straight.world.lo[body] + v * 0.1 * k, atol=1e-12)
    # measured in the rendered depth: the nearest world z of a mover ahead (its rear face)
    rear = []
    for k in range(0, 10, 3):
        f = straight[k]
        rows, cols = np.nonzero(f.mover_pixels == 0)
        X = f.T_w_cam @ _backproject(f.depth, f.K, rows, cols)
        rear.append(X[2].min())
    expect = straight.world.lo[body[0], 2] + v[0, 2] * 0.1 * np.arange(0, 10, 3)
    np.testing.assert_allclose(rear, expect, atol=2e-3)
    # LiDAR points of the movers: present, and only where the renderer says a mover is
    f = straight[9]
    assert f.moving_points.sum() > 500
    static = straight.world.lo[:, 2] == straight.world_at(0.9).lo[:, 2]
    assert static.sum() == len(static) - 8


def test_static_world_moves_nothing():
    seq = make_sequence(2, 0, speed=0.0, height=40, width=120, beams=8, image_noise_std=0.0,
                        range_noise_std=0.0, dropout=0.0)
    np.testing.assert_allclose(seq[1].T_w_cam, np.eye(4), atol=0)
    np.testing.assert_array_equal(seq[0].depth, seq[1].depth)
    assert not seq[0].moving_pixels.any() and not seq[1].moving_points.any()


def test_deterministic_for_a_seed():
    a = make_sequence(3, 7, movers=[4.0, (1.0, 0.0, 9.0)], yaw_rate=-5.0, height=40, width=120, beams=16)
    b = make_sequence(3, 7, movers=[4.0, (1.0, 0.0, 9.0)], yaw_rate=-5.0, height=40, width=120, beams=16)
    c = make_sequence(3, 8, movers=[4.0, (1.0, 0.0, 9.0)], yaw_rate=-5.0, height=40, width=120, beams=16)
    for fa, fb in zip(a, b):
        for name in ("image", "depth", "sparse", "points", "rings", "mover_pixels", "T_w_cam"):
            np.testing.assert_array_equal(getattr(fa, name), getattr(fb, name))
    np.testing.assert_allclose(a.mover_velocities, [[0, 0, 4.0], [1.0, 0, 9.0]])
    assert not np.array_equal(a[2].depth, c[2].depth)


def test_identity_pose_renders_like_make_scene_camera():
    """The pose argument of the renderer: the identity gives exactly the unposed render."""
    seq = make_sequence(1, 0, height=40, width=120, beams=8)
    K = camera_intrinsics(40, 120)
    a = render_camera(seq.world, K, 40, 120, np.random.default_rng(0), 0.01)
    b = render_camera(seq.world, K, 40, 120, np.random.default_rng(0), 0.01, pose=np.eye(4))
    np.testing.assert_array_equal(a[0], b[0])
    np.testing.assert_array_equal(a[1], b[1])


def test_ego_pose_formula():
    T = ego_pose(2.0, 5.0, 0.0)
    np.testing.assert_allclose(T[:3, 3], [0, 0, 10.0], atol=0)
    w = math.radians(30.0)
    T = ego_pose(1.0, 4.0, 30.0)  # radius 4 / w, 30 degrees of arc
    np.testing.assert_allclose(T[:3, 3], [4 / w * (math.cos(w) - 1), 0, 4 / w * math.sin(w)], atol=1e-12)


@pytest.mark.parametrize("kwargs,message", [
    ({"movers": 99}, "movers: expected an integer >= 0 and <= "),
    ({"movers": [(1.0, 2.0)]}, "movers[0]: expected a speed along the street (m/s) or a 3-vector"),
    ({"movers": "x"}, "movers[0]: expected a speed along the street"),
    ({"movers": True}, "movers: expected an integer or a list of velocities, got True"),
    ({"speed": -1.0}, "speed: expected a value in [0, 60], got -1.0"),
    ({"rate": 0.0}, "rate: expected a value in (0, 1000], got 0.0"),
    ({"n_frames": 0}, "n_frames: expected an integer >= 1 and <= 10000, got 0"),
])
def test_bad_arguments(kwargs, message):
    with pytest.raises(InputError) as e:
        make_sequence(**{"height": 20, "width": 40, "beams": 4, **kwargs})
    assert str(e.value).startswith(message)
