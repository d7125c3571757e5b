"""The photometric loss on an analytic two-plane scene (docs/design.md section 13).

The scene is ray-cast here, independently of the warp under test: a textured wall at
z = 10 m and a textured rectangle at z = 5 m in front of it, seen by a target camera at
the origin and by source cameras moved and yawed around it. Images are point samples of
smooth procedural textures, so a correct warp reproduces the target up to bilinear
interpolation and the regions that one source cannot see. About 3 s in all.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from crfdepth.errors import InputError
from crfdepth.model import CRFDepth
from crfdepth.sequences.photometric import photometric_error, photometric_loss, warp_to_target

H, W, F = 96, 128, 110.0
WALL_Z, FG_Z = 10.0, 5.0
FG_X, FG_Y = (-1.2, 0.6), (-1.5, 2.5)  # the near rectangle's extent, metres (x right, y down)
# Two neighbours, as frames t-1 and t+1: centres (metres) and yaw (degrees) of the source cameras.
MOVES = (((0.4, 0.05, 0.3), 2.0), ((-0.4, -0.05, -0.3), -2.0))


def intrinsics(h: int, w: int, f: float) -> np.ndarray:
    return np.array([[f, 0.0, (w - 1) / 2], [0.0, f, (h - 1) / 2], [0.0, 0.0, 1.0]])


def pose(centre, yaw_deg: float = 0.0) -> np.ndarray:
    """T_cam<-world of a camera at ``centre`` (world = target camera), yawed about y."""
    a = math.radians(yaw_deg)
    R_wc = np.array([[math.cos(a), 0.0, math.sin(a)], [0.0, 1.0, 0.0], [-math.sin(a), 0.0, math.cos(a)]])
    T = np.eye(4)
    T[:3, :3] = R_wc.T
    T[:3, 3] = -R_wc.T @ np.asarray(centre, float)
    return T


def texture(x, y, phase):
    """Smooth RGB in [0.2, 0.8] (periods 0.8-1.7 m) of a point (x, y) on a plane."""
    return np.stack([0.5 + 0.17 * np.sin(2 * np.pi * (x / 0.95 + y / 1.7) + phase + 2.1 * k)
                     + 0.13 * np.sin(2 * np.pi * (x / 1.6 - y / 0.8) + 1.3 * phase + 0.7 * k) for k in range(3)], -1)


def render(T_cam_world, K, h=H, w=W, wall_z=WALL_Z, fg_z=FG_Z):
    """Ray-cast the two planes: (h, w, 3) image and (h, w) z-depth in this camera."""
    R, t = T_cam_world[:3, :3], T_cam_world[:3, 3]
    c = -R.T @ t
    u, v = np.meshgrid(np.arange(w), np.arange(h))
    d_cam = np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones((h, w))], -1)  # z = 1
    d = d_cam @ R  # world directions R^T d_cam
    s_wall, s_fg = (wall_z - c[2]) / d[..., 2], (fg_z - c[2]) / d[..., 2]
    p_fg = c + s_fg[..., None] * d
    hit = (s_fg > 0) & (p_fg[..., 0] >= FG_X[0]) & (p_fg[..., 0] <= FG_X[1]) & \
          (p_fg[..., 1] >= FG_Y[0]) & (p_fg[..., 1] <= FG_Y[1])
    s = np.where(hit, s_fg, s_wall)  # ray length in units of d_cam, whose z is 1: s is the z-depth
    p = c + s[..., None] * d
    image = np.where(hit[..., None], texture(0.5 * p[..., 0], 0.5 * p[..., 1], 1.0), texture(p[..., 0], p[..., 1], 0.0))
    return image, s


def lidar(K, h, w, centre, wall_z, fg_z, rows=4, cols=2):
    """Sparse z-depth in the target camera of a LiDAR at ``centre`` (every ``rows``-th row and
    ``cols``-th column of its range image), returns the camera cannot see included."""
    _, depth = render(pose(centre), K, h, w, wall_z, fg_z)
    v, u = np.mgrid[0:h:rows, 0:w:cols]
    z = depth[v, u]
    p = np.stack([(u - K[0, 2]) / K[0, 0] * z, (v - K[1, 2]) / K[1, 1] * z, z], -1) + np.asarray(centre)
    uu = np.round(K[0, 0] * p[..., 0] / p[..., 2] + K[0, 2]).astype(int)
    vv = np.round(K[1, 1] * p[..., 1] / p[..., 2] + K[1, 2]).astype(int)
    ok = (uu >= 0) & (uu < w) & (vv >= 0) & (vv < h)
    order = np.argsort(-p[..., 2][ok])  # far first: the nearest return of a pixel wins
    sparse = np.zeros((h, w))
    sparse[vv[ok][order], uu[ok][order]] = p[..., 2][ok][order]
    return sparse


def as_image(a, dtype=torch.float32):
    return torch.from_numpy(a).permute(2, 0, 1)[None].to(dtype)


def as_map(a, dtype=torch.float32):
    return torch.from_numpy(a)[None, None].to(dtype)


def make_pair(h=H, w=W, f=F, moves=MOVES, dtype=torch.float32, wall_z=WALL_Z, fg_z=FG_Z):
    K = intrinsics(h, w, f)
    image, depth = render(np.eye(4), K, h, w, wall_z, fg_z)
    poses = [pose(c, yaw) for c, yaw in moves]
    sources = [as_image(render(T, K, h, w, wall_z, fg_z)[0], dtype) for T in poses]
    return {"target_image": as_image(image, dtype), "source_images": sources, "target_depth": as_map(depth, dtype),
                "K": torch.from_numpy(K).to(dtype), "poses": [torch.from_numpy(T).to(dtype) for T in poses]}


@pytest.fixture(scope="module")
def pair():
    return make_pair()


def loss_of(pair, **changes):
    return float(photometric_loss(**{**pair, **changes}))


# --------------------------------------------------------------------------- the true depth and pose


def test_true_depth_and_pose_give_near_zero_loss(pair):
    both = loss_of(pair)
    assert both < 0.005  # measured 0.0014 (bilinear resampling of the textures)
    # One neighbour alone misses what it cannot see (3-4 px bands beside the near plane):
    # the per-pixel minimum over both neighbours removes that error.
    single = [loss_of(pair, source_images=[s], poses=[T]) for s, T in zip(pair["source_images"], pair["poses"])]
    assert all(0.005 < v < 0.03 for v in single), single  # measured 0.016, 0.011
    assert both < 0.3 * min(single)


def test_warp_reproduces_the_target_where_visible(pair):
    warped, valid = warp_to_target(pair["source_images"][0], pair["target_depth"], pair["K"], pair["poses"][0])
    assert warped.shape == pair["target_image"].shape and valid.dtype == torch.bool
    assert float(valid.float().mean()) > 0.8  # measured 0.87: moving 0.3 m ahead loses the borders
    diff = (warped - pair["target_image"]).abs().mean(1, keepdim=True)[valid]
    assert float(diff.median()) < 0.005  # half of the pixels within 0.5% of the target
    assert float((diff < 0.02).float().mean()) > 0.9  # the rest: what the source cannot see


@pytest.mark.parametrize("wrong, factor", [("depth x 1.2", 10), ("depth x 0.8", 10), ("flat depth", 5),
                                           ("yaw off by 1 degree", 50), ("inverted poses", 50)])
def test_wrong_depth_or_pose_gives_a_larger_loss(pair, wrong, factor):
    depth, poses = pair["target_depth"], pair["poses"]
    if wrong == "depth x 1.2":
        depth = depth * 1.2
    elif wrong == "depth x 0.8":
        depth = depth * 0.8
    elif wrong == "flat depth":
        depth = torch.full_like(depth, float(depth.median()))
    elif wrong == "yaw off by 1 degree":
        poses = [torch.from_numpy(pose(c, yaw + 1.0)).float() for c, yaw in MOVES]
    else:
        poses = [torch.linalg.inv(T) for T in poses]
    true = loss_of(pair)
    # measured: 0.044, 0.075, 0.022, 0.19, 0.29 against 0.0014 for the truth
    assert loss_of(pair, target_depth=depth, poses=poses) > factor * true


# --------------------------------------------------------------------------- masks


@pytest.mark.parametrize("tx", [1.0, -0.6])
def test_sideways_move_masks_a_band_of_the_analytic_width(pair, tx):
    """Source camera moved by -tx (points move by +tx in it): the wall (z = 10 m) beside the
    near plane shifts by F tx / z pixels and leaves the view on one side."""
    T = torch.eye(4)
    T[0, 3] = tx
    source = as_image(render(T.double().numpy(), intrinsics(H, W, F))[0])
    _, maps = photometric_loss(pair["target_image"], [source], pair["target_depth"], pair["K"], [T], automask=False,
                               return_maps=True)
    out = ~maps.in_view[0, 0]
    band = F * abs(tx) / WALL_Z  # 11 and 6.6 px
    cols = out.all(dim=0)  # columns entirely out of view
    width = int(cols.sum())
    assert abs(width - band) <= 1.0, (width, band)
    side = cols[-width:] if tx > 0 else cols[:width]
    assert bool(side.all())  # on the side the scene leaves by
    assert float(out.float().mean()) == pytest.approx(width / W, abs=1.5 / W)  # nothing else
    assert not bool((maps.valid & ~maps.in_view).any())
    # The rest still fits, but for what the source cannot see: the wall the near plane
    # uncovers as it shifts 11 px further than the wall (about 10% of the pixels).
    assert float(maps.error[maps.valid].median()) < 0.005
    assert float((maps.error[maps.valid] > 0.02).float().mean()) < 0.12


def test_points_behind_the_source_camera_are_out_of_view(pair):
    T = torch.eye(4)
    T[2, 3] = -12.0  # the source camera 12 m ahead: the whole scene (<= 10 m) behind it
    warped, valid = warp_to_target(pair["target_image"], pair["target_depth"], pair["K"], T)
    assert not bool(valid.any()) and bool(torch.isfinite(warped).all())
    with pytest.raises(InputError, match=r"^poses: expected target pixels that land inside a source image and in "
                                         r"front of its camera, got none: every pixel leaves the view"):
        photometric_loss(pair["target_image"], [pair["target_image"]], pair["target_depth"], pair["K"], [T])


def test_static_camera_is_auto_masked(pair):
    depth = pair["target_depth"].clone().requires_grad_(True)
    args = (pair["target_image"], [pair["target_image"]], depth, pair["K"], [torch.eye(4)])
    with pytest.raises(InputError, match=r"^source_images: expected a neighbour whose warp explains some pixel "
                                         r"better than the unwarped image, got none: the auto-mask excluded every"):
        photometric_loss(*args)
    loss, maps = photometric_loss(*args, allow_empty=True, return_maps=True)
    assert float(loss.detach()) == 0.0 and loss.requires_grad  # zero, still on the graph for training
    assert bool(maps.in_view.all()) and not bool(maps.automask.any())
    assert float(maps.error.detach().max()) < 1e-4  # the identity warp reproduces the image (float32 SSIM: 3e-5)
    # Without the auto-mask the same pair is a (useless) perfect fit.
    assert float(photometric_loss(*args, automask=False).detach()) < 1e-4


def test_object_moving_with_the_camera_is_auto_masked(pair):
    """A patch at the same pixels of target and source (a car ahead driving at our speed):
    no depth warps it onto itself, the unwarped source fits it, so it is masked."""
    rows, cols = slice(8, 32), slice(92, 120)
    rng = np.random.default_rng(0)
    patch = torch.from_numpy(rng.uniform(0.1, 0.9, (3, 24, 28))).float()
    target, sources = pair["target_image"].clone(), [s.clone() for s in pair["source_images"]]
    for im in (target, *sources):
        im[0, :, rows, cols] = patch
    depth = pair["target_depth"].clone()
    depth[..., rows, cols] = 8.0  # its true depth: the warp moves it by 2-5 px in each source
    kw = dict(pair, target_image=target, source_images=sources, target_depth=depth)
    loss, maps = photometric_loss(**kw, return_maps=True)
    inner = torch.zeros(H, W, dtype=torch.bool)
    inner[9:31, 93:119] = True  # the patch less its border pixels (SSIM's window reaches across)
    assert float((~maps.automask[0, 0][inner]).float().mean()) > 0.95  # measured: all of them
    rest = torch.ones(H, W, dtype=torch.bool)
    rest[5:35, 89:123] = False
    assert float(maps.valid[0, 0][rest].float().mean()) > 0.95
    assert float(loss) < 0.01  # nearly as without the object (0.0054 against 0.0014)
    assert float(photometric_loss(**kw, automask=False)) > 0.02  # the patch's error counts without the mask


def test_given_mask_and_reductions(pair):
    mask = torch.zeros(1, 1, H, W, dtype=torch.bool)
    mask[..., :, :64] = True
    _, maps = photometric_loss(**pair, mask=mask, return_maps=True)
    assert not bool(maps.valid[..., 64:].any()) and float(maps.valid[..., :64].float().mean()) > 0.95
    # A batch of two frames: the truth and a wrong depth; "frame" gives each frame's own loss.
    batch = {"target_image": pair["target_image"].repeat(2, 1, 1, 1),
                 "source_images": torch.stack([s.repeat(2, 1, 1, 1) for s in pair["source_images"]], dim=1),
                 "target_depth": torch.cat([pair["target_depth"], pair["target_depth"] * 1.2]), "K": pair["K"],
                 "poses": torch.stack([T.expand(2, 4, 4) for T in pair["poses"]], dim=1)}
    frames = photometric_loss(**batch, reduction="frame")
    assert frames.shape == (2,)
    assert float(frames[0]) == pytest.approx(loss_of(pair), rel=1e-5)
    assert float(frames[1]) == pytest.approx(loss_of(pair, target_depth=pair["target_depth"] * 1.2), rel=1e-5)
    none, maps = photometric_loss(**batch, reduction="none", return_maps=True)
    mean = photometric_loss(**batch)
    assert none.shape == (2, 1, H, W) and float((none[~maps.valid]).abs().max()) == 0.0
    assert float(mean) == pytest.approx(float(none.sum() / maps.valid.sum()), rel=1e-6)


def test_error_formula():
    """alpha (1 - SSIM) / 2 + (1 - alpha) |a - b|: alpha = 0 is the L1 error, alpha = 1 half the dissimilarity."""
    g = torch.Generator().manual_seed(0)
    a, b = torch.rand(1, 3, 8, 9, generator=g), torch.rand(1, 3, 8, 9, generator=g)
    assert torch.allclose(photometric_error(a, b, 0.0), (a - b).abs().mean(1, keepdim=True), atol=1e-7)
    assert float(photometric_error(a, a, 0.85).abs().max()) < 1e-6
    assert 0.2 < float(photometric_error(a, b, 1.0).mean()) < 0.6  # unrelated noise: SSIM near 0


# --------------------------------------------------------------------------- gradients


def test_finite_differences_in_depth():
    """float64 gradcheck of the loss in every depth pixel of a tiny 10x14 pair."""
    pair = make_pair(h=10, w=14, f=12.0, moves=(((0.6, 0.1, 0.4), 3.0),), dtype=torch.float64)
    depth = pair["target_depth"].clone().requires_grad_(True)

    def loss(d):
        return photometric_loss(**dict(pair, target_depth=d), automask=False)

    assert float(loss(depth).detach()) > 0.01  # a coarse image: bilinear error, far from a kink-free zero
    assert torch.autograd.gradcheck(loss, (depth,), eps=1e-6, atol=1e-7, rtol=1e-4)


@pytest.mark.parametrize("structure", ["shipped", "paper"])
def test_gradients_reach_every_learned_weight(structure):
    """The photometric loss of the model's depth on a 64x96 frame, with a LiDAR 0.5 m
    beside the camera (returns at the near plane's edges that the occlusion gate weighs).

    The planes are 9 and 10 m away so that the shipped gate (threshold 0.0091 1/m) is in
    its transition for the edge returns (1/9 - 1/10 = 0.011 1/m) rather than saturated.
    Weights the depth does not depend on cannot get a photometric gradient: the std's
    (``std_head.weights``; ``log_std_scale``, used only by ``uncertainty="posterior"``)
    and ``log_refine_prior`` in pixel mode (no refinement); the trainer freezes them
    likewise (train/module.py). The std's weights get theirs from the NLL term here.
    """
    h, w, f, wall_z, fg_z = 64, 96, 80.0, 10.0, 9.0
    pair = make_pair(h, w, f, wall_z=wall_z, fg_z=fg_z)
    K = intrinsics(h, w, f)
    sparse = as_map(lidar(K, h, w, (0.5, -0.4, 0.0), wall_z, fg_z))
    model = CRFDepth.from_pretrained() if structure == "shipped" else CRFDepth()
    out = model(pair["target_image"], sparse, pair["K"], return_std=True)
    photometric = photometric_loss(**dict(pair, target_depth=out.depth))
    assert 0 < float(photometric.detach()) < 0.05
    photometric.backward(retain_graph=True)
    std_only = {"std_head.weights", "log_std_scale"}
    unused = {"log_refine_prior"} if model.settings.structure.mode == "pixel" else set()
    unused.add("log_std_scale")  # posterior std only
    grads = {}
    for name, p in model.named_parameters():
        if name in std_only | unused:
            assert p.grad is None, name
            continue
        assert p.grad is not None, name
        grads[name] = p.grad.clone()
    expected = 10 if structure == "shipped" else 9  # + gate threshold and softness; + refine prior
    assert len(grads) == expected, sorted(grads)
    bad = {n: g.tolist() for n, g in grads.items() if not bool(torch.isfinite(g).all()) or not bool((g != 0).all())}
    assert not bad, f"zero or non-finite photometric gradients: {bad}"
    # The std's weights, through a Gaussian NLL of the true depth (depth detached, as in training).
    target = pair["target_depth"]
    nll = (out.std.log() + (out.depth.detach() - target) ** 2 / (2 * out.std ** 2)).mean()
    nll.backward()
    g = model.std_head.weights.grad
    assert g is not None and bool(torch.isfinite(g).all()) and bool((g != 0).all()), g


# --------------------------------------------------------------------------- bad input


def _bad(pair, name):
    d, s, T = pair["target_depth"], pair["source_images"], pair["poses"]
    cases = {
        "depth shape": {"target_depth": d[0]},
        "depth nan": {"target_depth": d.clone().index_fill_(3, torch.tensor([5]), float("nan"))},
        "depth zero": {"target_depth": d.clone().index_fill_(3, torch.tensor([5]), 0.0)},
        "source size": {"source_images": [s[0], s[1][..., :-2]]},
        "image range": {"target_image": pair["target_image"] * 255},
        "pose scaled": {"poses": [T[0], T[1] * 2]},
        "pose count": {"poses": [T[0]]},
        "K shape": {"K": pair["K"][:2]},
        "K fov": {"K": pair["K"] * torch.tensor([[0.02, 1, 1], [1, 0.02, 1], [1, 1, 1]])},  # f = 2.2 px
        "alpha": {"alpha": 1.5},
    }
    return {**pair, **cases[name]}


@pytest.mark.parametrize("case, message", [
    ("depth shape", r"^target_depth: expected a \(B, 1, H, W\) tensor of z-depth in metres, got shape \(1, 96, 128\)"),
    ("depth nan", r"^target_depth: expected finite values, got 96 NaN/inf entries$"),
    ("depth zero", r"^target_depth: expected z-depth > 0 metres at every pixel the loss uses, got 96 pixel\(s\) <= 0"),
    ("source size", r"^source_images\[1\]: expected batch 1 and size 96x128 \(HxW\) like target_image"),
    ("image range", r"^target_image: expected values in \[0.0, 1.0\], got range"),
    ("pose scaled", r"^poses\[1\]: expected the last row of a rigid 4x4 transform to be 0 0 0 1, got 0 0 0 2"),
    ("pose count", r"^poses: expected one T_source<-target per source image \(2\), got 1$"),
    ("K shape", r"^K: expected shape \(3, 3\) or \(1, 3, 3\) \(one per frame of target_depth\), got shape \(2, 3\)"),
    ("K fov", r"^K: expected a field of view below 170 degrees"),
    ("alpha", r"^alpha: expected a number in \[0, 1\], got 1.5$"),
])
def test_bad_input_names_the_argument(pair, case, message):
    with pytest.raises(InputError, match=message):
        photometric_loss(**_bad(pair, case))


def test_non_rigid_rotation_and_wrong_mask_are_refused(pair):
    T = pair["poses"][0].clone()
    T[:3, :3] *= 1.01
    with pytest.raises(InputError, match=r"^poses\[0\]: expected a rigid transform .* orthonormal within 0.001"):
        photometric_loss(**dict(pair, poses=[T, pair["poses"][1]]))
    with pytest.raises(InputError, match=r"^mask: expected a \(B, 1, H, W\) tensor like target_depth"):
        photometric_loss(**pair, mask=torch.ones(H, W, dtype=torch.bool))
    mask = torch.zeros(1, 1, H, W, dtype=torch.bool)
    with pytest.raises(InputError, match=r"^mask: expected some in-view pixels to use, got none"):
        photometric_loss(**pair, mask=mask)
    # depth <= 0 is fine where the mask leaves the pixel out
    depth = pair["target_depth"].clone()
    depth[..., :, :10] = 0.0
    mask = torch.ones(1, 1, H, W, dtype=torch.bool)
    mask[..., :, :10] = False
    assert float(photometric_loss(**dict(pair, target_depth=depth), mask=mask)) < 0.005
