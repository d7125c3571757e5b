"""Tests for crfdepth.potentials.occlusion: see-through mask, soft gate, fallback (docs/design.md section 3b)."""

from __future__ import annotations

import warnings

import numpy as np
import pytest
import torch

from crfdepth.errors import InputError
from crfdepth.potentials.occlusion import (
    DEFAULT_SOFTNESS,
    DEFAULT_THRESHOLD,
    DEFAULT_WINDOW,
    OcclusionFallbackWarning,
    gate_or_fallback,
    occlusion_gate,
    see_through_mask,
    see_through_residual,
)

F_PX, CAMERA_HEIGHT_M = 720.0, 1.65


def _gate(sparse):
    return occlusion_gate(sparse, DEFAULT_THRESHOLD, DEFAULT_SOFTNESS)


def _occluder_scene():
    """A box at 8 m in front of a wall at 25 m, scanned on rows 5 px apart, every 2 px.

    Leaked background returns sit inside the box's silhouette (rows 40-79, columns
    80-129) between the box's own returns, as parallax puts them: 1-3 px inside its left
    and right edges on the scan rows (odd columns), and a background scan line shifted 1 px
    inside its top edge (odd columns).
    """
    h, w = 120, 200
    sparse = torch.zeros(1, 1, h, w)
    box = torch.zeros(h, w, dtype=torch.bool)
    box[40:80, 80:130] = True
    rows, cols = torch.arange(2, h, 5), torch.arange(0, w, 2)
    grid = torch.zeros(h, w, dtype=torch.bool)
    grid[rows[:, None], cols[None, :]] = True
    sparse[0, 0][grid] = 25.0
    sparse[0, 0][grid & box] = 8.0
    leaked = torch.zeros(h, w, dtype=torch.bool)
    for r in rows[(rows >= 40) & (rows < 80)]:
        leaked[r, [81, 83, 125, 127]] = True  # in-ring samples inside the side edges
    leaked[41, 81:130:2] = True                # background ring shifted under the top edge
    sparse[0, 0][leaked] = 25.0
    return sparse, box, leaked


def test_leaked_background_is_removed_and_the_rest_kept():
    sparse, box, leaked = _occluder_scene()
    before = sparse.clone()
    g, mask = _gate(sparse)[0, 0], see_through_mask(sparse)[0, 0]
    assert torch.equal(sparse, before)  # input untouched
    valid = sparse[0, 0] > 0
    assert int(leaked.sum()) == 8 * 4 + 25
    assert bool(mask[leaked].all()) and float(g[leaked].max()) < 0.1
    # r = 1/8 - 1/25 = 0.085 1/m for every leaked point: a 18-px parallax band.
    r = see_through_residual(sparse)[0, 0]
    assert torch.allclose(r[leaked], torch.tensor(1 / 8 - 1 / 25))
    foreground = valid & box & ~leaked
    assert int(foreground.sum()) == 8 * 25  # 8 scan rows x 25 columns
    assert not bool(mask[foreground].any()) and float(g[foreground].min()) > 0.9
    assert torch.equal(g[foreground], torch.ones_like(g[foreground]))  # nothing nearer: exactly 1
    # Wall returns further from the box than the window's radius are untouched.
    k = DEFAULT_WINDOW // 2
    near_box = torch.zeros_like(box)
    near_box[40 - k:80 + k, 80 - k:130 + k] = True
    wall_far = valid & ~near_box
    assert int(wall_far.sum()) > 1000
    assert not bool(mask[wall_far].any()) and torch.equal(g[wall_far], torch.ones_like(g[wall_far]))
    # Empty pixels: gate 1, mask False.
    assert torch.equal(g[~valid], torch.ones_like(g[~valid])) and not bool(mask[~valid].any())


def _road_scan(seed=0, width=400, cy=172.0):
    """A flat road 1.65 m below the camera (f = 720 px) on scan lines 4-6 px apart, depths 5-80 m.

    Each ring is tilted by up to +-1 px over the width (rings are curves in the image) and
    sampled every ~2 px with sub-pixel jitter, 2 cm range noise; z-buffer to pixels.
    """
    g = np.random.default_rng(seed)
    height = int(cy + F_PX * CAMERA_HEIGHT_M / 5.0) + 3
    sparse = np.zeros((height, width), np.float32)
    v = cy + F_PX * CAMERA_HEIGHT_M / 80.0  # the 80 m row
    while True:
        u = np.arange(0.0, width - 1, 2.0) + g.uniform(-0.3, 0.3, width // 2)
        vv = v + g.uniform(-1, 1) * (u - width / 2) / (width / 2)
        z = F_PX * CAMERA_HEIGHT_M / (vv - cy) + g.normal(0.0, 0.02, u.shape)
        keep = (z >= 5.0) & (z <= 80.0)
        rr, cc = np.round(vv[keep]).astype(int), np.round(u[keep]).astype(int)
        for r_, c_, z_ in zip(rr, cc, z[keep]):
            if sparse[r_, c_] == 0 or z_ < sparse[r_, c_]:
                sparse[r_, c_] = z_
        v += g.uniform(4.0, 6.0)
        if F_PX * CAMERA_HEIGHT_M / (v - 1 - cy) < 5.0:
            break
    return torch.from_numpy(sparse)[None, None]


def _grazing_wall(lateral=1.0, width=600, cx=300.0):
    """A vertical wall 1 m to the right of the camera, seen at a grazing angle: 1/z affine in u."""
    sparse = torch.zeros(1, 1, 60, width)
    for row in range(2, 60, 5):
        u = torch.arange(int(cx) + 8, width, 2, dtype=torch.float32)  # z = f d / (u - cx) <= 90 m
        sparse[0, 0, row, u.long()] = F_PX * lateral / (u - cx)
    return sparse


@pytest.mark.parametrize("scene", ["road", "wall"])
def test_slanted_planes_are_kept(scene):
    sparse = _road_scan() if scene == "road" else _grazing_wall()
    valid = sparse > 0
    z = sparse[valid]
    if scene == "road":
        assert float(z.min()) < 5.5 and float(z.max()) > 75.0 and int(valid.sum()) > 5000
        # A metric rule would cut it: depth changes by metres between far rings, so "more
        # than 1.5 m behind the nearest return of a 9x9 window" flags 3.7% of this road.
        r9 = see_through_residual(sparse, window=9)[valid]
        metric_gap = z - 1.0 / (1.0 / z + r9)
        assert float((metric_gap > 1.5).float().mean()) > 0.03
    assert not bool(see_through_mask(sparse).any())
    g = _gate(sparse)
    assert float(g[valid].min()) > 0.9
    # how far from the threshold: r stays below half of it
    assert float(see_through_residual(sparse).max()) < DEFAULT_THRESHOLD / 2


def test_gate_shape_values_and_monotonicity():
    # One near return and neighbours increasingly deeper: the gate falls with r.
    sparse = torch.zeros(1, 1, 1, 5, dtype=torch.float64)
    sparse[0, 0, 0] = torch.tensor([10.0, 10.05, 10.5, 11.0, 12.0], dtype=torch.float64)
    g = occlusion_gate(sparse, 0.01, 0.002, window=9)[0, 0, 0]
    r = see_through_residual(sparse, window=9)[0, 0, 0]
    assert g[0] == 1.0 and r[0] == 0.0
    assert bool((g[1:] < g[:-1]).all()) and bool((g > 0).all())
    expected = torch.sigmoid((0.01 - r) / 0.002) / torch.sigmoid(torch.tensor(0.01 / 0.002, dtype=torch.float64))
    torch.testing.assert_close(g, expected)
    # Near the threshold g is about 1/2 (for threshold >> softness).
    assert float(occlusion_gate(sparse, float(r[3]), 1e-5, window=9)[0, 0, 0, 3]) == pytest.approx(0.5)


def test_gradcheck_threshold_and_softness():
    gen = torch.Generator().manual_seed(0)
    sparse = 10.0 + torch.rand(2, 1, 6, 7, generator=gen, dtype=torch.float64)
    sparse[torch.rand(2, 1, 6, 7, generator=gen) > 0.6] = 0.0
    r = see_through_residual(sparse, window=3)
    assert float(r.max()) > 0.005  # r spans the transition of the gate below
    t = torch.tensor(0.004, dtype=torch.float64, requires_grad=True)
    s = torch.tensor(0.002, dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(lambda t_, s_: occlusion_gate(sparse, t_, s_, window=3), (t, s))
    # Through the logarithms, as the model learns them.
    log_t, log_s = t.detach().log().requires_grad_(), s.detach().log().requires_grad_()
    assert torch.autograd.gradcheck(lambda a, b: occlusion_gate(sparse, a.exp(), b.exp(), window=3), (log_t, log_s))


def test_no_gradient_to_sparse_and_stable_for_sharp_gates():
    sparse, _, leaked = _occluder_scene()
    sparse.requires_grad_(True)
    t = torch.tensor(DEFAULT_THRESHOLD, requires_grad=True)
    s = torch.tensor(DEFAULT_THRESHOLD / 500, requires_grad=True)  # t/s = 500, float32
    g = occlusion_gate(sparse, t, s)
    assert bool(torch.isfinite(g).all()) and float(g.detach()[0, 0][leaked].max()) < 1e-30
    g.sum().backward()
    assert sparse.grad is None
    assert t.grad is not None and s.grad is not None and bool(torch.isfinite(t.grad)) and bool(torch.isfinite(s.grad))


def test_fallback_warns_names_the_frame_and_returns_ones():
    # Frame 0: four returns at 2 m, every other one of its 100 at 50 m within 2 px of one
    # of them: the gate would keep 4 of 100 (4% < 10%). Frame 1: one 8 m return among
    # 25 m ones, an ordinary occluder (keeps 76%).
    sparse = torch.zeros(2, 1, 10, 10)
    sparse[0] = 50.0
    sparse[0, 0, 2:8:5, 2:8:5] = 2.0
    sparse[1] = 25.0
    sparse[1, 0, 5, 5] = 8.0
    with pytest.warns(OcclusionFallbackWarning,
                      match=r"frame 0 would keep 4 of 100 data weight \(4\.0% < min_kept_share 0\.1, 100 returns\)"):
        gate, fell = gate_or_fallback(sparse, DEFAULT_THRESHOLD, DEFAULT_SOFTNESS)
    assert fell.tolist() == [True, False]
    assert torch.equal(gate[0], torch.ones_like(gate[0]))
    torch.testing.assert_close(gate[1], _gate(sparse[1:])[0])
    # A frame without any return, or a harmless gate, passes silently.
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        gate, fell = gate_or_fallback(torch.zeros(1, 1, 4, 4), 0.01, 0.002)
        assert not bool(fell.any()) and torch.equal(gate, torch.ones_like(gate))
        # data weights: the near returns carry 40 of frame 0's 136, so it keeps > 10%
        weight = torch.ones_like(sparse)
        weight[0, 0, 2:8:5, 2:8:5] = 10.0
        _, fell = gate_or_fallback(sparse, DEFAULT_THRESHOLD, DEFAULT_SOFTNESS, weight=weight)
        assert fell.tolist() == [False, False]


_Z = torch.zeros(1, 1, 4, 4)
_ODD = "window: expected an odd integer >= 3 .pixels., got "


@pytest.mark.parametrize(
    "call, message",
    [
        (lambda: _gate(torch.zeros(1, 2, 4, 4)), r"sparse: expected 1 channel\(s\), \(B, 1, H, W\), got shape"),
        (lambda: _gate(torch.zeros(4, 4)), r"sparse: expected a \(B, 1, H, W\) tensor, got shape \(4, 4\)"),
        (lambda: _gate(-torch.ones(1, 1, 4, 4)), r"sparse: expected values >= 0, got minimum -1"),
        (lambda: _gate(torch.full((1, 1, 4, 4), float("nan"))), "sparse: expected finite values, got 16 NaN/inf"),
        (lambda: _gate(_Z.long()), "sparse: expected a floating-point tensor"),
        (lambda: see_through_mask(_Z, window=4), _ODD + "4"),
        (lambda: see_through_mask(_Z, window=1), _ODD + "1"),
        (lambda: see_through_mask(_Z, window=5.0), _ODD + "float 5.0"),
        (lambda: see_through_mask(_Z, window=True), _ODD + "bool True"),
        (lambda: see_through_mask(_Z, threshold=0.0), "threshold: expected a finite value > 0, got 0"),
        (lambda: occlusion_gate(_Z, -0.01, 0.002), "threshold: expected a finite value > 0, got -0.01"),
        (lambda: occlusion_gate(_Z, torch.ones(2), 0.002), r"threshold: expected a scalar \(one element\), got shape"),
        (lambda: occlusion_gate(_Z, 0.01, 0.0), "softness: expected a finite value > 0, got 0"),
        (lambda: occlusion_gate(_Z, 0.01, "soft"), "softness: expected a number or a one-element tensor, got str"),
        (lambda: gate_or_fallback(_Z, 0.01, 0.002, weight=torch.zeros(1, 1, 3, 4)),
         r"weight: expected batch 1 and size 4x4 \(HxW\) like sparse"),
        (lambda: gate_or_fallback(_Z, 0.01, 0.002, min_kept_share=1.0),
         r"min_kept_share: expected a number in \(0, 1\), got 1.0"),
    ],
)
def test_bad_input_names_the_argument(call, message):
    with pytest.raises(InputError, match=message):
        call()


def _scans(kitti_root):
    """(name, full-scan projection, projection from a virtual camera at the LiDAR) of the
    drive 0060 and object frames (not drive 0001, the official validation frame)."""
    from PIL import Image

    from crfdepth.data.kitti import KittiRawScans
    from crfdepth.geometry.projection import project_to_depth, project_velodyne
    from crfdepth.io.kitti import read_velodyne

    for layout, root in (("raw", kitti_root / "raw"), ("object", kitti_root / "object" / "training")):
        ds = KittiRawScans(root, layout=layout, transform=None)
        for f in ds._frames:
            if "drive_0001" in f.name:
                continue
            calib = ds._calibration(f)
            with Image.open(f.image) as im:  # the header only
                size = im.size[::-1]
            points = read_velodyne(f.velodyne)
            velo_to_cam = calib.velo_to_rect_cam()
            cam = np.c_[points[:, :3], np.ones(len(points))] @ velo_to_cam[:3].T
            no_parallax = project_to_depth(cam - velo_to_cam[:3, 3], calib.P_rect[:, :3], size)
            yield f.name, project_velodyne(points, calib, size), no_parallax


@pytest.mark.kitti
def test_share_flagged_on_real_scans_and_parallax(kitti_root):
    shares = {"drive": [], "object": []}
    flagged = {"camera": 0, "no_parallax": 0}
    returns = {"camera": 0, "no_parallax": 0}
    for name, full, no_parallax in _scans(kitti_root):
        for key, sp in (("camera", full), ("no_parallax", no_parallax)):
            m = see_through_mask(torch.from_numpy(sp)[None, None])
            flagged[key] += int(m.sum())
            returns[key] += int((sp > 0).sum())
            if key == "camera":
                shares["drive" if "drive" in name else "object"].append(int(m.sum()) / int((sp > 0).sum()))
    drive, obj = np.array(shares["drive"]), np.array(shares["object"])
    assert len(drive) == 13 and len(obj) == 11
    # Measured: drive 0060 3.6% of the returns on average (2.4-5.0% per frame), object
    # frames 2.5% (0.8-6.1%).
    assert 0.025 < drive.mean() < 0.045 and 0.015 < drive.min() and drive.max() < 0.065
    assert 0.015 < obj.mean() < 0.035 and 0.004 < obj.min() and obj.max() < 0.08
    # Parallax is the cause: seen from the LiDAR itself, the same scans lose less
    # (3.1% against 2.5%, pooled; the rest are returns just outside silhouettes).
    camera, no_par = flagged["camera"] / returns["camera"], flagged["no_parallax"] / returns["no_parallax"]
    assert camera - no_par > 0.004, (camera, no_par)
