"""Tests for the stereo check of LiDAR returns (crfdepth/sequences/stereo.py) and the synthetic right camera."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from crfdepth.data.synthetic import make_sequence
from crfdepth.errors import InputError
from crfdepth.sequences.stereo import baseline_from_projections, stereo_check, stereo_consistent

FX, BASELINE = 100.0, 0.5  # fx * baseline = 50 px m
D_BACK, D_FRONT = 4, 10  # disparities of the background plane (12.5 m) and of the square in front (5 m)
Z_BACK, Z_FRONT = FX * BASELINE / D_BACK, FX * BASELINE / D_FRONT
H, W = 40, 120
SQUARE = (slice(10, 30), slice(50, 70))  # rows, columns of the square in the left image
FLAT = slice(90, 110)  # a texture-less band of the background (columns of the left image)


def _pair():
    """A rectified pair: a textured plane at 12.5 m, a textured square at 5 m in front of it, a flat band.

    Returns (left, right, K) with images (3, H, W) in [0, 1] (grey repeated)."""
    rng = np.random.default_rng(0)
    back = rng.uniform(0.2, 0.8, (H, W + 20))  # texture on the plane, indexed by left column
    back[:, FLAT] = 0.5
    front = rng.uniform(0.2, 0.8, (H, 20))
    left = back[:, :W].copy()
    left[SQUARE] = front[SQUARE[0]]
    right = back[:, D_BACK:W + D_BACK].copy()  # the plane's column u is seen at u - D_BACK
    right[SQUARE[0], SQUARE[1].start - D_FRONT:SQUARE[1].stop - D_FRONT] = front[SQUARE[0]]
    K = np.array([[FX, 0, W / 2], [0, FX, H / 2], [0, 0, 1]])
    images = [torch.tensor(np.repeat(x[None], 3, axis=0), dtype=torch.float32) for x in (left, right)]
    return images[0], images[1], K


def _returns():
    """Good returns on the plane and the square, the plane's returns occluded in the right view (columns 44-49
    of the square's rows: the square covers them there), and four wrong returns (name -> pixel)."""
    depth = np.zeros((H, W), np.float32)
    depth[2:38:3, 20:44:3] = Z_BACK
    depth[2:38:3, 72:88:3] = Z_BACK
    depth[12:28:3, 53:68:3] = Z_FRONT
    depth[11:29:2, 44:50] = Z_BACK  # occluded in the right view
    wrong = {"see_through": (20, 60, Z_BACK), "too_near": (20, 30, Z_FRONT), "flat": (20, 100, Z_FRONT),
             "outside_right": (20, 3, Z_FRONT)}
    for v, u, z in wrong.values():
        depth[v, u] = z
    return torch.from_numpy(depth), wrong


def test_a_see_through_and_a_too_near_return_are_dropped_and_the_rest_kept():
    left, right, K = _pair()
    depth, wrong = _returns()
    before = depth.clone()
    check = stereo_check(depth, left, right, K, BASELINE)
    assert torch.equal(depth, before)  # input untouched
    assert check.keep.shape == (1, 1, H, W) and check.keep.dtype == torch.bool
    dropped = {tuple(p) for p in torch.nonzero(check.dropped[0, 0]).tolist()}
    assert dropped == {wrong["see_through"][:2], wrong["too_near"][:2]}
    assert torch.equal(check.keep | check.dropped, (depth > 0)[None, None])
    # Stereo sees the square and the plane where the wrong returns are.
    assert check.disparity[0, 0, 20, 60] == pytest.approx(D_FRONT, abs=0.3)
    assert check.disparity[0, 0, 20, 30] == pytest.approx(D_BACK, abs=0.3)
    # Texture-less, outside the right image, occluded in the right view: not informative, kept.
    for name in ("flat", "outside_right"):
        v, u, _ = wrong[name]
        assert check.keep[0, 0, v, u] and not check.informative[0, 0, v, u], name
    assert check.keep[0, 0, 11:29:2, 44:50].all()
    # The correct returns whose patch lies on one surface in both images are informative (and agree).
    assert check.informative[0, 0, 2:38:3, 20:36:3].all() and check.informative[0, 0, 2:38:3, 75:88:3].all()
    assert check.informative[0, 0, 15:25:3, 56:63:3].all()
    assert check.counts() == {"returns": int((depth > 0).sum()), "informative": int(check.informative.sum()),
                              "dropped": 2}


def test_the_keep_mask_has_the_depth_shape_and_batches_agree_with_single_frames():
    left, right, K = _pair()
    depth, _ = _returns()
    keep = stereo_consistent(depth, left, right, K, BASELINE)
    assert keep.shape == (H, W) and keep.dtype == torch.bool
    assert not keep[20, 60] and keep[20, 100] and not keep[0, 0]  # dropped, kept, no return
    shifted = torch.roll(depth, 1, dims=0)  # a second frame with other returns
    batch = stereo_consistent(torch.stack([depth, shifted])[:, None], torch.stack([left, left]),
                              torch.stack([right, right]), torch.tensor(K), BASELINE)
    assert torch.equal(batch[0, 0], keep)
    assert torch.equal(batch[1, 0], stereo_consistent(shifted, left, right, K, BASELINE))


def test_the_right_camera_as_reference_with_a_negative_baseline():
    # The same scene seen from the right camera: the plane's return at right column u - D_BACK, the
    # square's at u - D_FRONT; the left image is the other camera, to the left.
    left, right, K = _pair()
    depth = torch.zeros(H, W)
    depth[2:38:3, 20:40:3] = Z_BACK
    depth[12:28:3, 43:58:3] = Z_FRONT
    depth[20, 50] = Z_BACK  # on the square (right columns 40-59): see-through
    depth[5, 100] = Z_FRONT  # on the flat band (right columns 86-105): kept
    check = stereo_check(depth, right, left, K, -BASELINE)
    assert {tuple(p) for p in torch.nonzero(check.dropped[0, 0]).tolist()} == {(20, 50)}
    assert check.disparity[0, 0, 20, 50] == pytest.approx(D_FRONT, abs=0.3)


def test_bad_inputs_are_refused_by_name():
    left, right, K = _pair()
    depth, _ = _returns()
    cases = [
        (dict(depth=depth[None, None, None]), "depth: expected a (B, 1, H, W), (1, H, W) or (H, W) tensor"),
        (dict(depth=-depth), "depth: expected finite floating-point depth >= 0 metres"),
        (dict(left=left * 255), "left: expected an image with values in [0, 1]"),
        (dict(right=right[:, :, :-1]), "right: expected batch and size (1, 40, 120) like depth, got (1, 40, 119)"),
        (dict(baseline_m=0.0), "baseline_m: expected a stereo baseline in metres"),
        (dict(K=np.eye(4)), "K: expected a 3x3 matrix"),
        (dict(window=8), "window: expected an odd number of pixels"),
    ]
    for change, message in cases:
        args = dict(depth=depth, left=left, right=right, K=K, baseline_m=BASELINE) | change
        window = args.pop("window", 9)
        with pytest.raises(InputError, match=None) as info:
            stereo_check(**args, window=window)
        assert str(info.value).startswith(message), (str(info.value), message)


def test_kitti_baseline_from_the_projection_matrices():
    P2 = [[721.5377, 0, 609.5593, 44.85728], [0, 721.5377, 172.854, 0.2163791], [0, 0, 1, 0.002745884]]
    P3 = [[721.5377, 0, 609.5593, -339.5242], [0, 721.5377, 172.854, 2.199936], [0, 0, 1, 0.002729905]]
    assert baseline_from_projections(P2, P3) == pytest.approx(0.5327, abs=1e-4)
    assert baseline_from_projections(P3, P2) == pytest.approx(-0.5327, abs=1e-4)


def test_the_synthetic_right_camera_sees_each_surface_at_its_disparity_and_changes_nothing_else():
    plain = make_sequence(2, 3, height=64, width=208, movers=1)
    stereo = make_sequence(2, 3, height=64, width=208, movers=1, stereo_baseline=0.54)
    for a, b in zip(plain, stereo):
        for name in ("image", "depth", "sparse", "points", "rings", "mover_pixels", "mover_points", "T_w_cam"):
            assert np.array_equal(getattr(a, name), getattr(b, name)), name
        assert a.right_image is None and b.baseline_m == 0.54 and b.right_image.shape == b.image.shape
    f = stereo[1]
    v, u = np.nonzero(f.depth > 0)
    d = f.K[0, 0] * 0.54 / f.depth[v, u]
    ur = np.rint(u - d).astype(int)
    ok = (ur >= 0) & (np.abs(u - d - ur) < 0.1)
    seen = np.abs(f.right_depth[v[ok], ur[ok]] - f.depth[v[ok], u[ok]]) < 0.02 * f.depth[v[ok], u[ok]]
    assert seen.mean() > 0.95  # the same surface, where the right camera is not occluded
    diff = np.abs(f.image[v[ok], u[ok]] - f.right_image[v[ok], ur[ok]]).mean(axis=1)[seen]
    assert np.median(diff) < 0.02  # the same colour up to the two cameras' noise
    with pytest.raises(InputError, match=r"stereo_baseline: expected a value in \(0, 10\]"):
        make_sequence(1, 0, height=16, width=32, stereo_baseline=0.0)
