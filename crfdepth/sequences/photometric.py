"""Photometric self-supervision: warp neighbouring frames into the target with a depth map.

A pure, differentiable loss of a depth map (docs/design.md section 13; Godard et
al. 2019, "Digging into self-supervised monocular depth estimation"; Ma et al. 2019 for
depth completion). It does not know the model: depth in, loss out, so
:class:`crfdepth.model.CRFDepth`, :class:`crfdepth.layer.CRFRefine` or any other network
can use it.

For a target image ``I_t``, its depth ``D_t`` and neighbouring images ``I_s`` with the
relative poses ``T_s<-t``, each target pixel ``p`` is lifted to ``D_t(p) K^-1 p``, moved
into the source camera and projected; ``I_s`` sampled there (bilinear) is ``I_s->t``.
The per-pixel error is::

    e_s(p) = alpha (1 - SSIM(I_t, I_s->t)(p)) / 2 + (1 - alpha) |I_t(p) - I_s->t(p)|

(SSIM over a 3x3 window, averaged over the colour channels), and the loss is the mean,
over the valid pixels, of ``min_s e_s(p)``. A pixel is valid where

1. it lands inside at least one source image and in front of that camera (only those
   sources enter the minimum);
2. (``automask``) the warp explains it better than doing nothing: ``min_s e_s(p)`` is
   below ``min_s e(I_t, I_s)(p)``, the error of the *unwarped* sources, by more than
   :data:`AUTOMASK_MARGIN`. This drops a static camera, objects that move with the
   camera, a standing car and textureless regions, whose error no depth can lower;
3. the optional ``mask`` holds (e.g. leave out the sky or the car's bonnet).

How it plugs into the trainer (``train/module.py``): the ``sequence`` layout
(:class:`crfdepth.data.sequences.SequenceFrames`) yields, per frame, the image, the sparse
LiDAR, K, and the neighbours' images ``(B, S, 3, H, W)`` with the poses
``T_s<-t`` ``(B, S, 4, 4)``; ``CRFDepthModule(photometric_weight=w)`` adds
``w * photometric_loss(image, neighbours, out.depth, K, poses, allow_empty=True, reduction="frame")``
to each image's depth loss (``w`` = 0, the default, leaves training as it is).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Literal

import kornia
import torch
import torch.nn.functional as F
from kornia.geometry.camera import project_points, unproject_points
from kornia.geometry.conversions import normalize_pixel_coordinates
from kornia.geometry.linalg import transform_points

from crfdepth.checks import check_map, check_number, check_rigid, describe
from crfdepth.errors import InputError
from crfdepth.intrinsics import check_intrinsics

__all__ = ["AUTOMASK_MARGIN", "MIN_SOURCE_DEPTH_M", "SSIM_WINDOW", "PhotometricMaps", "photometric_error",
           "photometric_loss", "warp_to_target"]

SSIM_WINDOW = 3
"""SSIM window (pixels), as in Monodepth2; kornia's window is a Gaussian of sigma 1.5 over it."""
MIN_SOURCE_DEPTH_M = 1e-3
"""A warped point must lie at least this far in front of the source camera (metres) to count."""
AUTOMASK_MARGIN = 1e-4
"""The warp must beat the unwarped source by more than this (error units, in [0, 1]) for a
pixel to count; it absorbs the rounding of an identity warp (about 1e-7), so a static camera
is masked deterministically rather than by coin flips of the last bit."""
_EDGE_SLACK_PX = 1e-3  # pixels: float32 rounding of the projection, far below any real shift


@dataclass
class PhotometricMaps:
    """The per-pixel pieces of :func:`photometric_loss`, for inspection (all (B, ...) tensors).

    Attributes:
        error: (B, 1, H, W) ``min_s e_s``, the per-pixel error of the best in-view source
            (1 where no source is in view; look at ``valid``).
        valid: (B, 1, H, W) bool, the pixels the loss averages over (all masks combined).
        in_view: (B, 1, H, W) bool, inside at least one source image and in front of it.
        automask: (B, 1, H, W) bool, where the warp beats every unwarped source (all True
            with ``automask=False``).
        source_errors: (B, S, H, W) ``e_s`` per source (masked sources hold 1).
        identity_errors: (B, S, H, W) the error of each unwarped source.
        warped: (B, S, C, H, W) the sources warped into the target.
        best_source: (B, 1, H, W) int64 index of the source that gave ``error``.
    """

    error: torch.Tensor
    valid: torch.Tensor
    in_view: torch.Tensor
    automask: torch.Tensor
    source_errors: torch.Tensor
    identity_errors: torch.Tensor
    warped: torch.Tensor
    best_source: torch.Tensor


# --------------------------------------------------------------------------- checks


def _per_frame(value: object, name: str, n: int, bsz: int, what: str, note: str) -> torch.Tensor:
    """An (n, n) tensor for every frame or a (B, n, n) one per frame, as (B, n, n); ``what`` and
    ``note`` complete the error messages."""
    if not isinstance(value, torch.Tensor):
        raise InputError(f"{name}: expected a ({n}, {n}) or ({bsz}, {n}, {n}) tensor{what}, got {describe(value)}")
    if tuple(value.shape) == (n, n):
        value = value[None].expand(bsz, n, n)
    if tuple(value.shape) != (bsz, n, n):
        raise InputError(f"{name}: expected shape ({n}, {n}) or ({bsz}, {n}, {n}) ({note}), got "
                         f"shape {tuple(value.shape)}")
    return value


def _check_intrinsics(K: object, bsz: int, height: int, width: int, ref: torch.Tensor) -> torch.Tensor:
    """K (3, 3) or (B, 3, 3) as a (B, 3, 3) tensor like ``ref`` (gradients kept)."""
    K = _per_frame(K, "K", 3, bsz, "", "one per frame of target_depth")
    for b in range(bsz):
        check_intrinsics(K[b], "K" if bsz == 1 else f"K[{b}]", image_size=(height, width))
    return K.to(device=ref.device, dtype=ref.dtype)


def _check_pose(T: object, name: str, bsz: int, ref: torch.Tensor) -> torch.Tensor:
    """A rigid T_source<-target, (4, 4) or (B, 4, 4), as a (B, 4, 4) tensor like ``ref``."""
    T = _per_frame(T, name, 4, bsz, " T_source<-target", "T_source<-target, one per frame")
    if not T.is_floating_point():
        raise InputError(f"{name}: expected a floating-point rigid transform, got dtype {T.dtype}")
    for b in range(bsz):
        check_rigid(T[b].detach().double(), name if bsz == 1 else f"{name}[{b}]")
    return T.to(device=ref.device, dtype=ref.dtype)


def _check_depth(target_depth: object, where: torch.Tensor | None) -> torch.Tensor:
    depth = check_map("target_depth", target_depth, channels=1)
    if depth.numel() == 0:
        raise InputError(f"target_depth: expected at least one frame of at least one pixel, got {describe(depth)}")
    used = depth.detach() if where is None else depth.detach()[where]
    bad = used <= 0
    if bool(bad.any()):
        raise InputError(f"target_depth: expected z-depth > 0 metres at every pixel the loss uses, got "
                         f"{int(bad.sum())} pixel(s) <= 0 (minimum {float(used.min()):.4g}); fill the depth first "
                         f"or leave those pixels out with mask")
    return depth


# --------------------------------------------------------------------------- warp


def _warp(source: torch.Tensor, depth: torch.Tensor, K: torch.Tensor, T: torch.Tensor
          ) -> tuple[torch.Tensor, torch.Tensor]:
    """The warp of :func:`warp_to_target` on checked (B, C, H, W), (B, 1, H, W), (B, 3, 3), (B, 4, 4)."""
    height, width = depth.shape[-2:]
    # kornia's depth_to_3d_v2 does the same but mishandles a batch of K before kornia 0.8.1.
    rows, cols = (torch.arange(n, device=depth.device, dtype=depth.dtype) for n in (height, width))
    pixels = torch.stack(torch.meshgrid(cols, rows, indexing="xy"), dim=-1)  # (H, W, 2) as (u, v)
    points = unproject_points(pixels, depth.permute(0, 2, 3, 1), K[:, None, None])  # (B, H, W, 3) z = depth
    points = transform_points(T[:, None], points)  # (B, H, W, 3) source camera
    z = points[..., 2:]
    in_front = z > MIN_SOURCE_DEPTH_M
    # Points behind the camera get z = 1: finite pixels, masked below, no inf in the backward.
    safe = torch.cat([points[..., :2], torch.where(in_front, z, torch.ones_like(z))], dim=-1)
    pixels = project_points(safe, K[:, None, None])  # (B, H, W, 2) source pixels (u, v)
    u, v = pixels[..., 0], pixels[..., 1]
    # Bilinear sampling with pixel centres at integers (align_corners=True) needs all four
    # neighbours inside: 0 <= u <= W - 1, 0 <= v <= H - 1, give or take the rounding of an
    # identity warp (the border padding covers that sliver).
    slack = _EDGE_SLACK_PX
    inside = (u >= -slack) & (u <= width - 1 + slack) & (v >= -slack) & (v <= height - 1 + slack)
    valid = (in_front[..., 0] & inside)[:, None]
    grid = normalize_pixel_coordinates(pixels, height, width)
    warped = F.grid_sample(source, grid, mode="bilinear", padding_mode="border", align_corners=True)
    return warped, valid


def warp_to_target(source_image: torch.Tensor, target_depth: torch.Tensor, K: torch.Tensor,
                   T_source_target: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """The source image resampled into the target camera through the target's depth.

    Each target pixel ``p`` is lifted to ``X = D_t(p) K^-1 [p, 1]`` (kornia's
    ``unproject_points``), moved into the source camera (``T_source_target X``) and projected
    with K; the source image is sampled there bilinearly (pixel centres at integer
    coordinates, ``grid_sample(align_corners=True)``). Differentiable in the image, the
    depth, K and the pose.

    Args:
        source_image: (B, C, H, W) the source (neighbouring) frame, e.g. RGB in [0, 1].
        target_depth: (B, 1, H, W) z-depth of the target frame in metres, > 0 everywhere.
        K: (3, 3) or (B, 3, 3) pinhole intrinsics of both frames, pixels.
        T_source_target: (4, 4) or (B, 4, 4) rigid transform taking points of the target
            camera into the source camera (metres), ``T_source<-target``.

    Returns:
        ``(warped, valid)``: (B, C, H, W) the source seen from the target (border pixels
        repeated where ``valid`` is False) and (B, 1, H, W) bool, True where the point
        lands inside the source image (``0 <= u <= W-1``, ``0 <= v <= H-1``) and at least
        :data:`MIN_SOURCE_DEPTH_M` in front of its camera.

    Raises:
        InputError: a shape, dtype or device that does not fit, non-finite values, depth
            <= 0, implausible K, or a non-rigid pose; the message names the argument.
    """
    depth = _check_depth(target_depth, None)
    bsz, _, height, width = depth.shape
    source = check_map("source_image", source_image, depth, ref_name="target_depth", same_dtype=False)
    K = _check_intrinsics(K, bsz, height, width, depth)
    T = _check_pose(T_source_target, "T_source_target", bsz, depth)
    return _warp(source.to(depth.dtype), depth, K, T)


# --------------------------------------------------------------------------- error and loss


def photometric_error(image_a: torch.Tensor, image_b: torch.Tensor, alpha: float = 0.85) -> torch.Tensor:
    """(B, 1, H, W) ``alpha (1 - SSIM) / 2 + (1 - alpha) |a - b|``, averaged over channels.

    SSIM is kornia's (``kornia.metrics.ssim``) over a 3x3 window (:data:`SSIM_WINDOW`),
    reflect-padded, for images in [0, 1]; inputs are trusted (checked by the callers).
    """
    ssim = kornia.metrics.ssim(image_a, image_b, SSIM_WINDOW, max_val=1.0)
    dssim = ((1 - ssim) / 2).clamp(0, 1)
    l1 = (image_a - image_b).abs()
    return (alpha * dssim + (1 - alpha) * l1).mean(dim=1, keepdim=True)


def _as_stack(name: str, value: object, item_ndim: int) -> list:
    """A list/tuple of items or a tensor stacked along dim 1 as a list of items."""
    if isinstance(value, torch.Tensor):
        if value.dim() == item_ndim + 1:
            return list(value.unbind(1))
        if value.dim() == item_ndim:
            return [value]
        want = "(B, S, 3, H, W)" if item_ndim == 4 else "(B, S, 4, 4)"
        raise InputError(f"{name}: expected a list of tensors or a stacked {want} tensor, got {describe(value)}")
    if isinstance(value, (list, tuple)):
        if not value:
            raise InputError(f"{name}: expected at least one neighbour, got an empty {type(value).__name__}")
        return list(value)
    raise InputError(f"{name}: expected a list of tensors or a stacked tensor, got {type(value).__name__}")


def photometric_loss(target_image: torch.Tensor, source_images: Sequence[torch.Tensor] | torch.Tensor,
                     target_depth: torch.Tensor, K: torch.Tensor,
                     poses: Sequence[torch.Tensor] | torch.Tensor, *, alpha: float = 0.85, automask: bool = True,
                     mask: torch.Tensor | None = None, reduction: Literal["mean", "frame", "none"] = "mean",
                     allow_empty: bool = False, return_maps: bool = False
                     ) -> torch.Tensor | tuple[torch.Tensor, PhotometricMaps]:
    """Photometric reprojection loss of a depth map (docs/design.md section 13).

    ``mean over valid p of min_s [alpha (1 - SSIM(I_t, I_s->t)) / 2 + (1 - alpha) |I_t - I_s->t|](p)``,
    with the masks of the module docstring (out of view, auto-mask, ``mask``).

    Args:
        target_image: (B, 3, H, W) RGB in [0, 1] of the frame whose depth is judged.
        source_images: the S >= 1 neighbouring frames, a list of (B, 3, H, W) or a
            (B, S, 3, H, W) tensor, RGB in [0, 1], same size as the target.
        target_depth: (B, 1, H, W) predicted z-depth of the target in metres, > 0 where
            ``mask`` holds (everywhere without it).
        K: (3, 3) or (B, 3, 3) intrinsics shared by all frames, pixels.
        poses: ``T_source<-target`` per source, a list of (4, 4) / (B, 4, 4) or a
            (B, S, 4, 4) tensor, rigid, metres (the pose's scale fixes the depth's scale).
        alpha: weight of the SSIM term, in [0, 1] (0.85 as in Monodepth2).
        automask: drop pixels that an unwarped source explains at least as well.
        mask: optional (B, 1, H, W) bool (or 0/1) map of pixels to use.
        reduction: "mean" (over all valid pixels of the batch, a scalar), "frame" ((B,)
            mean per frame, 0 for a frame without valid pixel) or "none" ((B, 1, H, W),
            the error where valid, 0 elsewhere).
        allow_empty: with no valid pixel in the whole batch, return a zero loss (still
            attached to the graph) instead of raising; training on real sequences wants
            this (a car waiting at a light is fully auto-masked).
        return_maps: also return :class:`PhotometricMaps`.

    Returns:
        The loss (see ``reduction``), or ``(loss, maps)`` with ``return_maps``.

    Raises:
        InputError: bad shapes, sizes, dtypes or values (naming the argument), sources
            of different sizes, depth <= 0 where used, a non-rigid pose, implausible K,
            or (without ``allow_empty``) no valid pixel, saying which mask removed them.
    """
    check_number("alpha", alpha, low=0.0, high=1.0, low_open=False, high_open=False)
    if reduction not in ("mean", "frame", "none"):
        raise InputError(f"reduction: expected 'mean', 'frame' or 'none', got {reduction!r}")
    if not isinstance(target_depth, torch.Tensor) or target_depth.dim() != 4 or target_depth.shape[1] != 1:
        raise InputError(f"target_depth: expected a (B, 1, H, W) tensor of z-depth in metres, got "
                         f"{describe(target_depth)}")
    if mask is not None:
        if not isinstance(mask, torch.Tensor) or tuple(mask.shape) != tuple(target_depth.shape):
            raise InputError(f"mask: expected a (B, 1, H, W) tensor like target_depth {tuple(target_depth.shape)}, "
                             f"got {describe(mask)}")
        if mask.dtype != torch.bool:
            if not bool(((mask == 0) | (mask == 1)).all()):
                raise InputError("mask: expected a bool or 0/1 tensor, got other values")
            mask = mask != 0
        mask = mask.to(target_depth.device)
    depth = _check_depth(target_depth, mask)
    bsz, _, height, width = depth.shape
    target = check_map("target_image", target_image, depth, channels=3, ref_name="target_depth", low=0.0, high=1.0,
                       same_dtype=False).to(depth.dtype)
    sources = _as_stack("source_images", source_images, 4)
    if isinstance(poses, torch.Tensor) and poses.dim() == 4:
        transforms = list(poses.unbind(1))  # (B, S, 4, 4)
    elif isinstance(poses, torch.Tensor):
        transforms = [poses]  # one (4, 4) or (B, 4, 4) pose
    else:
        transforms = _as_stack("poses", poses, 2)
    if len(transforms) != len(sources):
        raise InputError(f"poses: expected one T_source<-target per source image ({len(sources)}), got "
                         f"{len(transforms)}")
    checked = []
    for i, s in enumerate(sources):
        name = f"source_images[{i}]" if len(sources) > 1 or not isinstance(source_images, torch.Tensor) \
            else "source_images"
        s = check_map(name, s, target, channels=3, ref_name="target_image", low=0.0, high=1.0, same_dtype=False)
        checked.append(s.to(depth.dtype))
    K = _check_intrinsics(K, bsz, height, width, depth)
    transforms = [_check_pose(T, f"poses[{i}]" if len(transforms) > 1 else "poses", bsz, depth)
                  for i, T in enumerate(transforms)]

    warped, errors, views, identity = [], [], [], []
    for s, T in zip(checked, transforms):
        w, v = _warp(s, depth, K, T)
        warped.append(w)
        views.append(v)
        errors.append(torch.where(v, photometric_error(target, w, alpha), torch.ones_like(depth)))
        identity.append(photometric_error(target, s, alpha))
    errors_s = torch.cat(errors, dim=1)  # (B, S, H, W)
    views_s = torch.cat(views, dim=1)
    identity_s = torch.cat(identity, dim=1)
    error, best = errors_s.min(dim=1, keepdim=True)
    in_view = views_s.any(dim=1, keepdim=True)
    if automask:
        beats = error.detach() < identity_s.detach().min(dim=1, keepdim=True).values - AUTOMASK_MARGIN
    else:
        beats = torch.ones_like(in_view)
    valid = in_view & beats
    if mask is not None:
        valid = valid & mask
    count = valid.sum()
    if int(count) == 0 and not allow_empty:
        raise InputError(_why_empty(in_view, beats, mask, automask))
    masked = torch.where(valid, error, torch.zeros_like(error))
    if reduction == "mean":
        loss = masked.sum() / count.clamp(min=1).to(error.dtype)
    elif reduction == "frame":
        loss = masked.flatten(1).sum(1) / valid.flatten(1).sum(1).clamp(min=1).to(error.dtype)
    else:
        loss = masked
    if not return_maps:
        return loss
    return loss, PhotometricMaps(error=error, valid=valid, in_view=in_view, automask=beats, source_errors=errors_s,
                                 identity_errors=identity_s, warped=torch.stack(warped, dim=1), best_source=best)


def _why_empty(in_view: torch.Tensor, beats: torch.Tensor, mask: torch.Tensor | None, automask: bool) -> str:
    """The message for a batch without a valid pixel: which mask removed them."""
    if not bool(in_view.any()):
        return ("poses: expected target pixels that land inside a source image and in front of its camera, got none: "
                "every pixel leaves the view; check that poses are T_source<-target (not inverted), in metres, and "
                "that target_depth and K are in metres and pixels of these images")
    if mask is not None and not bool((in_view & mask).any()):
        return "mask: expected some in-view pixels to use, got none: mask excludes every pixel that lands in a source"
    assert automask and not bool((in_view & beats).any())
    return ("source_images: expected a neighbour whose warp explains some pixel better than the unwarped image, got "
            "none: the auto-mask excluded every in-view pixel (a static camera or identical images?); pass "
            "allow_empty=True for a zero loss on such frames in training, or automask=False")
