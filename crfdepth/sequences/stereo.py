"""LiDAR depth checked against a rectified stereo pair: drop the returns stereo contradicts
(docs/design.md section 16).

KITTI's annotation kept only the accumulated returns that agreed with a stereo reconstruction,
which removed the see-through points, movers' smears and registration errors that section 15
found carrying a squared-error loss. :func:`stereo_check` is that test for a depth map (a scan,
held-out returns, camera-view targets) with a second camera rectified beside the first.

**The rule.** A return at left pixel ``(u, v)`` with z-depth ``z`` has the disparity
``d0 = fx * baseline / z``: the right camera sees it at ``(u - d0, v)``. Grey patches of
``window`` x ``window`` pixels are compared by zero-mean normalised cross-correlation (ZNCC),
each patch pixel weighted by its colour similarity to, and distance from, the centre (adaptive
support weights, Yoon and Kweon 2006: the patch stays on the centre's own surface at depth edges):

- ``best``, ``d_s``: the best ZNCC over the disparities ``0 .. fx * baseline / min_depth_m`` and
  its disparity (parabola-refined): what stereo sees at the pixel;
- ``own``: the best ZNCC within ``tol = DISPARITY_TOL_PX + DISPARITY_TOL_REL * d0`` of ``d0``,
  including ``d0`` itself (the right image warped by kornia's ``remap``, bilinear).

A return is *informative* when its right patch lies inside the right image (and ``d0`` inside
the search), its left patch is textured (weighted grey std >= ``MIN_TEXTURE``) and stereo
matches it well somewhere (``best >= MIN_SCORE``). It is **dropped** when it is informative,
stereo disagrees (``|d_s - d0| > tol``), the match there is clearly better than at the return's
own disparity (``best - own > MARGIN``), and that match passes the left/right consistency check
(the right pixel ``u - d_s`` searched back against the left image leads to ``u`` within
``LR_TOL_PX``; a pixel occluded in the right view has a spurious best match, which fails it).
Everything else is kept: texture-less patches, occluded pixels, returns outside the right image
or nearer than ``min_depth_m``. The check never adds or moves a return.

Torch only (CPU or CUDA), batched, evaluated at the returns: ``O(N D window^2)`` time for ``N``
returns and ``D`` disparities, in chunks of 1024 returns (KITTI: about 2 s for a whole scan on
one CPU thread).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch

from crfdepth.checks import check_has_data, check_number, describe
from crfdepth.errors import InputError
from crfdepth.intrinsics import check_intrinsics

__all__ = ["DISPARITY_TOL_PX", "DISPARITY_TOL_REL", "LR_TOL_PX", "MARGIN", "MIN_SCORE", "MIN_TEXTURE",
           "STEREO_MIN_DEPTH_M", "StereoCheck", "baseline_from_projections", "remove_stereo_contradicted",
           "stereo_check", "stereo_consistent"]

# --- Thresholds (docs/design.md section 16; measured by benchmarks/stereo_check.py) -----------------
# Disparity tolerance: KITTI's LiDAR-camera calibration is good to about a pixel, a return is stored at
# its rounded pixel (+-0.5 px) and the stereo disparity is refined to a fraction of a pixel, so agreement
# within 1.5 px is agreement; the relative part (5% of d0) covers range noise and the depth change across
# the patch on slanted surfaces (the ground), which grows with the disparity.
DISPARITY_TOL_PX = 1.5
DISPARITY_TOL_REL = 0.05
# Stereo must match at least this well (ZNCC, in [-1, 1]) before it may overrule a return: below it the
# patch is noise-dominated or seen differently by the two cameras (specular, transparent, occluded).
MIN_SCORE = 0.7
# ... and better than at the return's own disparity by this much: the own match of a correct return
# near a depth edge loses some correlation to the other side of the edge, and image noise moves ZNCC by
# a few hundredths; a see-through return's own match is typically below 0.3 (another surface).
MARGIN = 0.1
# Grey-level standard deviation over the patch (images in [0, 1]) below which a patch carries no
# information: 8-bit quantisation and sensor noise are about 0.004-0.008; smooth road and sky are below
# 0.01.
MIN_TEXTURE = 0.01
# The left/right consistency check: the right pixel's best match must lead back within this (pixels).
LR_TOL_PX = 2.0
# The nearest depth searched (metres): sets the largest disparity, fx * baseline / 3 m (130 px on KITTI).
# Returns nearer than that are kept unjudged; a car bonnet aside, a road scene has none.
STEREO_MIN_DEPTH_M = 3.0
# Adaptive support weights (Yoon and Kweon 2006): a patch pixel counts by exp(-|colour - centre colour| /
# SUPPORT_COLOUR - distance / SUPPORT_DISTANCE_PX), colours in [0, 1] (mean absolute RGB difference). A
# plain window straddling a depth edge matches the nearer side ("foreground fattening") and would overrule
# the correct returns beside every edge; weighting by colour keeps the patch on the centre's own surface.
SUPPORT_COLOUR = 0.05
SUPPORT_DISTANCE_PX = 4.0

_EPS = 1e-6
_INVALID = -2.0  # a score no ZNCC reaches


@dataclass(frozen=True)
class StereoCheck:
    """The result of :func:`stereo_check`; every map is (B, 1, H, W), like the depth given.

    Attributes:
        keep: bool, a return (depth > 0) that stereo does not contradict.
        dropped: bool, a return stereo contradicts (``depth > 0`` and not ``keep``).
        informative: bool, a return stereo could judge: in the right image's view, textured, and
            matched by stereo with ``best >= MIN_SCORE`` (module docstring).
        disparity: float32 stereo disparity ``d_s`` at the returns' pixels, pixels (0 elsewhere).
        own_score, best_score: float32 ZNCC at the return's own disparity and at ``d_s`` (0 where no
            return).
    """

    keep: torch.Tensor
    dropped: torch.Tensor
    informative: torch.Tensor
    disparity: torch.Tensor
    own_score: torch.Tensor
    best_score: torch.Tensor

    def counts(self) -> dict[str, int]:
        """Returns, informative ones and dropped ones, summed over the batch."""
        returns = int(self.keep.sum()) + int(self.dropped.sum())
        return {"returns": returns, "informative": int(self.informative.sum()), "dropped": int(self.dropped.sum())}


def baseline_from_projections(P_reference, P_other) -> float:
    """Stereo baseline in metres of two rectified cameras from their (3, 4) projection matrices.

    ``(P_reference[0, 3] - P_other[0, 3]) / fx`` (KITTI's ``P_rect_02``, ``P_rect_03``: 0.54 m). Positive:
    the other camera is to the right of the reference (x right), as camera 3 is of camera 2.
    """
    a, b = np.asarray(P_reference, dtype=np.float64), np.asarray(P_other, dtype=np.float64)
    if a.shape != (3, 4) or b.shape != (3, 4):
        raise InputError(f"P_reference, P_other: expected two (3, 4) projection matrices, got shapes {a.shape} "
                         f"and {b.shape}")
    return float((a[0, 3] - b[0, 3]) / a[0, 0])


# --------------------------------------------------------------------------- checks


def _as_frames(name: str, t: object, channels: tuple[int, ...]) -> torch.Tensor:
    if not isinstance(t, torch.Tensor):
        raise InputError(f"{name}: expected a torch.Tensor, got {type(t).__name__}")
    check_has_data(name, t)
    if t.dim() == 3:
        t = t[None]
    if t.dim() != 4 or t.shape[1] not in channels:
        want = " or ".join(f"(B, {c}, H, W)" for c in channels)
        raise InputError(f"{name}: expected a {want} tensor, got {describe(t)}")
    t = t.to(torch.float32)
    if not bool(torch.isfinite(t).all()):
        raise InputError(f"{name}: expected finite values, got NaN or inf")
    low, high = float(t.min()), float(t.max())
    if low < -1e-3 or high > 1 + 1e-3:
        raise InputError(f"{name}: expected an image with values in [0, 1] (8-bit images divided by 255), got "
                         f"values from {low:.4g} to {high:.4g}")
    return t


def _check(depth, left, right, K, baseline_m, window, min_depth_m):
    if not isinstance(depth, torch.Tensor):
        raise InputError(f"depth: expected a torch.Tensor, got {type(depth).__name__}")
    check_has_data("depth", depth)
    if depth.dim() == 2:
        depth = depth[None, None]
    elif depth.dim() == 3 and depth.shape[0] == 1:
        depth = depth[None]
    if depth.dim() != 4 or depth.shape[1] != 1:
        raise InputError(f"depth: expected a (B, 1, H, W), (1, H, W) or (H, W) tensor, got {describe(depth)}")
    if not depth.is_floating_point() or not bool(torch.isfinite(depth).all()) or bool((depth < 0).any()):
        raise InputError(f"depth: expected finite floating-point depth >= 0 metres (0 = no return), got "
                         f"{describe(depth)}" + ("" if not depth.is_floating_point() else " with NaN, inf or < 0"))
    bsz, _, h, w = depth.shape
    images = []
    for name, image in (("left", left), ("right", right)):
        image = _as_frames(name, image, (1, 3))
        if image.shape[0] != bsz or tuple(image.shape[2:]) != (h, w):
            raise InputError(f"{name}: expected batch and size {(bsz, h, w)} like depth, got "
                             f"{(image.shape[0], *image.shape[2:])}")
        if image.device != depth.device:
            raise InputError(f"{name}: expected the device of depth ({depth.device}), got {image.device}")
        images.append(image)
    if isinstance(K, torch.Tensor) and K.dim() == 3:
        if K.shape[0] != bsz:
            raise InputError(f"K: expected (3, 3) or ({bsz}, 3, 3) like depth's batch, got {describe(K)}")
        mats = [check_intrinsics(k, f"K[{i}]", (h, w)) for i, k in enumerate(K)]
    else:
        mats = [check_intrinsics(K, "K", (h, w))] * bsz
    if isinstance(baseline_m, torch.Tensor) and baseline_m.numel() == 1:
        baseline_m = float(baseline_m)
    baseline_m = check_number("baseline_m", baseline_m)
    if baseline_m == 0 or abs(baseline_m) > 10:
        raise InputError(f"baseline_m: expected a stereo baseline in metres, 0 < |baseline_m| <= 10 (> 0: the "
                         f"right image's camera is to the right), got {baseline_m!r}")
    window = check_number("window", window, low=3, high=31, low_open=False, high_open=False, integer=True)
    if window % 2 == 0:
        raise InputError(f"window: expected an odd number of pixels in [3, 31], got {window}")
    min_depth_m = check_number("min_depth_m", min_depth_m, low=0)
    return depth, images[0], images[1], [m[0, 0] for m in mats], float(baseline_m), int(window), float(min_depth_m)


# --------------------------------------------------------------------------- matching


def _gray(image: torch.Tensor) -> torch.Tensor:
    if image.shape[1] == 1:
        return image
    weights = torch.tensor([0.299, 0.587, 0.114], dtype=image.dtype, device=image.device).view(1, 3, 1, 1)
    return (image * weights).sum(dim=1, keepdim=True)


def _weights(colour: torch.Tensor, r: int) -> torch.Tensor:
    """Adaptive support weights of (n, 3, w, w) colour patches (Yoon and Kweon 2006): similarity to the
    centre pixel's colour times closeness to it, normalised to sum 1 per patch: (n, w, w)."""
    centre = colour[:, :, r:r + 1, r:r + 1]
    o = torch.arange(-r, r + 1, device=colour.device, dtype=colour.dtype)
    dist = (o[:, None] ** 2 + o[None, :] ** 2).sqrt()
    w = torch.exp(-(colour - centre).abs().mean(dim=1) / SUPPORT_COLOUR - dist / SUPPORT_DISTANCE_PX)
    return w / w.sum(dim=(1, 2), keepdim=True)


@dataclass
class _Patches:
    """The reference patches of n query pixels: rows (n, w), centred grey (n, w, w), weights (n, w, w),
    weighted variance (n,)."""

    rows: torch.Tensor
    centred: torch.Tensor
    weight: torch.Tensor
    var: torch.Tensor


def _patches(grey, colour, b, v, u, r) -> _Patches:
    h, w = grey.shape[-2:]
    o = torch.arange(-r, r + 1, device=u.device)
    rows = (v[:, None] + o[None]).clamp(0, h - 1)
    cols = (u[:, None] + o[None]).clamp(0, w - 1)
    ref = grey[b[:, None, None], 0, rows[:, :, None], cols[:, None, :]]
    rgb = colour[b[:, None, None, None], torch.arange(colour.shape[1], device=u.device)[None, :, None, None],
                 rows[:, None, :, None], cols[:, None, None, :]]
    weight = _weights(rgb, r)
    centred = ref - (weight * ref).sum(dim=(1, 2), keepdim=True)
    return _Patches(rows, centred, weight, (weight * centred * centred).sum(dim=(1, 2)))


def _zncc(p: _Patches, other: torch.Tensor) -> torch.Tensor:
    """Weighted ZNCC of the patches with ``other`` (n, w rows, D candidates, w columns): (n, D)."""
    n, w, d = other.shape[:3]
    flat = other.permute(0, 2, 1, 3).reshape(n, d, w * w)
    weights = torch.stack([p.weight, p.weight * p.centred], dim=1).reshape(n, 2, w * w)
    mean, cov = torch.bmm(flat, weights.transpose(1, 2)).unbind(dim=-1)
    var = (torch.bmm(flat * flat, p.weight.reshape(n, w * w, 1))[..., 0] - mean * mean).clamp_min(0)
    return (cov / ((p.var[:, None] * var).sqrt() + _EPS)).clamp(-1.0, 1.0)


def _search(p: _Patches, other_grey, b, u, r, max_d, direction) -> torch.Tensor:
    """Weighted ZNCC of the patches at (v, u) with the other image's patches at (v, u + direction * d),
    d = 0..max_d: (n, max_d + 1), ``_INVALID`` where the other patch leaves the image."""
    w = other_grey.shape[-1]
    span = torch.arange(-r, max_d + r + 1, device=u.device)
    cols = u[:, None] + direction * span[None]  # (n, max_d + 2r + 1)
    strip = other_grey[b[:, None, None], 0, p.rows[:, :, None], cols.clamp(0, w - 1)[:, None, :]]
    patches = strip.unfold(-1, 2 * r + 1, 1)  # (n, rows, max_d + 1, cols)
    if direction < 0:
        patches = patches.flip(-1)  # the unfolded columns ran from dx = +r down to -r
    score = _zncc(p, patches)
    valid = ((cols >= 0) & (cols < w)).unfold(-1, 2 * r + 1, 1).all(dim=-1)
    return torch.where(valid, score, torch.full_like(score, _INVALID))


def _at(p: _Patches, other_grey, b, u, r, disparity) -> torch.Tensor:
    """Weighted ZNCC of the patches with the other image warped to them at a sub-pixel disparity
    (n,): the right patch sampled at (v + dy, u + dx - disparity) by kornia's remap (bilinear)."""
    w = other_grey.shape[-1]
    o = torch.arange(-r, r + 1, device=u.device, dtype=other_grey.dtype)
    x = (u[:, None].to(o.dtype) - disparity[:, None] + o[None]).clamp(0, w - 1)  # (n, w)
    out = torch.empty(len(u), dtype=other_grey.dtype, device=u.device)
    from kornia.geometry.transform import remap  # at first use: kornia's import is 0.2 s
    for frame in torch.unique(b).tolist():
        sel = torch.nonzero(b == frame).flatten()
        n = len(sel)
        map_x = x[sel][:, None, :].expand(n, 2 * r + 1, 2 * r + 1).reshape(1, n * (2 * r + 1), 2 * r + 1)
        map_y = p.rows[sel].to(o.dtype)[:, :, None].expand(n, 2 * r + 1, 2 * r + 1).reshape(map_x.shape)
        warped = remap(other_grey[frame:frame + 1], map_x, map_y, mode="bilinear", align_corners=True)
        sub = _Patches(p.rows[sel], p.centred[sel], p.weight[sel], p.var[sel])
        out[sel] = _zncc(sub, warped.reshape(n, 2 * r + 1, 1, 2 * r + 1))[:, 0]
    return out


def _refine(score: torch.Tensor, arg: torch.Tensor) -> torch.Tensor:
    """Sub-pixel disparity: a parabola through the (n, D) scores at arg - 1, arg, arg + 1."""
    n = torch.arange(score.shape[0], device=score.device)
    lo, hi = (arg - 1).clamp_min(0), (arg + 1).clamp_max(score.shape[1] - 1)
    c0, c1, c2 = score[n, lo], score[n, arg], score[n, hi]
    ok = (arg > 0) & (arg < score.shape[1] - 1) & (c0 > _INVALID) & (c2 > _INVALID)
    den = c0 - 2 * c1 + c2
    step = torch.where(ok & (den < -_EPS), 0.5 * (c0 - c2) / den.clamp_max(-_EPS), torch.zeros_like(c1))
    return arg.to(score.dtype) + step.clamp(-0.5, 0.5)


# --------------------------------------------------------------------------- the check


def stereo_check(depth, left, right, K, baseline_m: float, *, window: int = 9,
                 min_depth_m: float = STEREO_MIN_DEPTH_M) -> StereoCheck:
    """Which LiDAR returns a rectified stereo pair contradicts (module docstring: the rule).

    Args:
        depth: (B, 1, H, W), (1, H, W) or (H, W) float z-depth of the returns in the left image,
            metres, 0 = no return (a projected scan, held-out returns, accumulated targets).
        left: (B, 3, H, W) or (3, H, W) RGB (or 1-channel grey) image in [0, 1] of the camera ``depth``
            belongs to.
        right: the other camera's image, same shape, rectified with ``left`` (same rows, same ``K``).
        K: (3, 3) or (B, 3, 3) intrinsics of both images, pixels (``fx`` is used).
        baseline_m: distance between the two cameras' centres, metres; > 0 when ``right`` is to the
            right of ``left`` (KITTI camera 3 beside camera 2: :func:`baseline_from_projections`),
            < 0 when it is to the left (the pair is then mirrored).
        window: odd patch size in pixels, 3 to 31 (default 9; docs/design.md section 16).
        min_depth_m: the nearest depth searched, metres (sets the largest disparity); nearer returns
            are kept unjudged.

    Returns:
        :class:`StereoCheck`, every map (B, 1, H, W) on ``depth``'s device. ``depth * keep`` is the
        cleaned depth. The inputs are not modified.

    Raises:
        InputError: a tensor of the wrong shape, dtype or device, non-finite values, negative
            depth; a bad ``K``, ``baseline_m``, ``window`` or ``min_depth_m``.
    """
    depth, left, right, fxs, baseline, window, min_depth = _check(depth, left, right, K, baseline_m, window,
                                                                  min_depth_m)
    depth, left, right = depth.detach(), left.detach(), right.detach()
    if baseline < 0:  # the other camera to the left: mirror the pair, the rule is the same
        depth, left, right = depth.flip(-1), left.flip(-1), right.flip(-1)
    result = _run(depth, left, right, fxs, abs(baseline), window // 2, min_depth)
    if baseline < 0:
        result = StereoCheck(*(t.flip(-1) for t in (result.keep, result.dropped, result.informative,
                                                     result.disparity, result.own_score, result.best_score)))
    return result


def _run(depth, left, right, fxs, baseline, r, min_depth, chunk: int = 1024) -> StereoCheck:
    w = depth.shape[-1]
    colours = [image if image.shape[1] == 3 else image.expand(-1, 3, -1, -1) for image in (left, right)]
    greys = [_gray(image) for image in colours]
    has = depth > 0
    bi, _, vi, ui = torch.nonzero(has, as_tuple=True)
    d0 = torch.tensor(fxs, dtype=torch.float32, device=depth.device)[bi] * baseline / depth[has]
    max_d = max(0, min(w - 1 - 2 * r, math.ceil(max(fxs) * baseline / min_depth)))
    tol = DISPARITY_TOL_PX + DISPARITY_TOL_REL * d0
    n = len(ui)
    best, ds, own = (torch.zeros(n, device=depth.device) for _ in range(3))
    informative = torch.zeros(n, dtype=torch.bool, device=depth.device)
    disagree = torch.zeros_like(informative)
    # 1. Search the returns in the right image's view, textured, at every disparity.
    in_view = torch.nonzero((ui.float() - d0 - r >= 0) & (d0 <= max_d)).flatten()
    for s in range(0, len(in_view), chunk):
        idx = in_view[s:s + chunk]
        b, v, u = bi[idx], vi[idx], ui[idx]
        p = _patches(greys[0], colours[0], b, v, u, r)
        textured = p.var.sqrt() >= MIN_TEXTURE
        idx, b, u, d = idx[textured], b[textured], u[textured], d0[idx][textured]
        p = _Patches(*(t[textured] for t in (p.rows, p.centred, p.weight, p.var)))
        score = _search(p, greys[1], b, u, r, max_d, -1)  # left pixel u against right pixels u - d
        top, arg = score.max(dim=1)
        # The return's own match: exactly at d0 and at the integer disparities within the tolerance.
        near = (torch.arange(max_d + 1, device=u.device)[None] - d[:, None]).abs() <= tol[idx, None]
        own_grid = torch.where(near, score, torch.full_like(score, _INVALID)).max(dim=1).values
        best[idx], ds[idx], own[idx] = top, _refine(score, arg), torch.maximum(_at(p, greys[1], b, u, r, d), own_grid)
        informative[idx] = top >= MIN_SCORE
    disagree = informative & ((ds - d0).abs() > tol) & (best - own > MARGIN)
    # 2. Left/right consistency of the contradicting matches: the right pixel u - d_s, searched against
    # the left image, leads back to u (an occluded pixel's best match does not).
    drop = disagree.clone()
    candidates = torch.nonzero(disagree).flatten()
    for s in range(0, len(candidates), chunk):
        idx = candidates[s:s + chunk]
        b, v, arg = bi[idx], vi[idx], torch.round(ds[idx]).long()
        back_u = (ui[idx] - arg).clamp(0, w - 1)
        back = _search(_patches(greys[1], colours[1], b, v, back_u, r), greys[0], b, back_u, r, max_d, +1)
        drop[idx] = (back.argmax(dim=1) - arg).abs() <= LR_TOL_PX

    def paint(values, dtype):
        out = torch.zeros(depth.shape, dtype=dtype, device=depth.device)
        out[bi, 0, vi, ui] = values.to(dtype)
        return out

    dropped = paint(drop, torch.bool)
    return StereoCheck(keep=has & ~dropped, dropped=dropped, informative=paint(informative, torch.bool),
                       disparity=paint(ds, torch.float32), own_score=paint(own, torch.float32),
                       best_score=paint(best, torch.float32))


def stereo_consistent(depth, left, right, K, baseline_m: float, **options) -> torch.Tensor:
    """The keep mask of :func:`stereo_check`: (B, 1, H, W) bool (or the shape of ``depth``), True at
    the returns stereo does not contradict, False at the dropped ones and where ``depth`` is 0.
    ``options``: ``window``, ``min_depth_m``."""
    keep = stereo_check(depth, left, right, K, baseline_m, **options).keep
    return keep.reshape(depth.shape) if isinstance(depth, torch.Tensor) else keep


def remove_stereo_contradicted(target: np.ndarray, left: np.ndarray, right: np.ndarray, K: np.ndarray,
                                baseline_m: float) -> np.ndarray:
    """A new (H, W) float32 ``target`` (z-depth, metres, 0 = no target; not modified) with the pixels
    :func:`stereo_consistent` drops set to 0. ``left``, ``right``: (H, W, 3) uint8 RGB images of the target's
    camera and of the other camera of the rectified pair; ``K``: (3, 3) of both (pixels); ``baseline_m``: metres,
    > 0 when ``right``'s camera is right of ``left``'s (:func:`baseline_from_projections`)."""
    images = [torch.from_numpy(np.ascontiguousarray(image)).permute(2, 0, 1).float() / 255.0 for image in (left, right)]
    keep = stereo_consistent(torch.from_numpy(np.ascontiguousarray(target, dtype=np.float32)), images[0], images[1],
                             K, baseline_m)
    out = np.array(target, dtype=np.float32, copy=True)
    out[~keep.numpy()] = 0.0
    return out
