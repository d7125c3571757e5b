"""The synthetic scene's pinhole camera: intrinsics and the ray-cast RGB and depth render.

Lambertian shading from a sun direction with cast shadows, the textures of
:mod:`~crfdepth.data.synthetic.texture`, a sky gradient with clouds, a mild optical blur
(one ray per pixel would alias) and a little sensor noise. Depth is camera z-depth in
metres, 0 where the pixel sees sky (docs/design.md section 1).
"""

from __future__ import annotations

import math

import numpy as np

from crfdepth.data.synthetic._checks import check_int
from crfdepth.data.synthetic.raycast import (
    boxes_in_frame,
    camera_windows,
    cast_rays,
    intersect,
    rotate_rays,
    surface_normals,
)
from crfdepth.data.synthetic.texture import textured_albedo, value_noise
from crfdepth.data.synthetic.world import PLANE, TINY, World

__all__ = ["KITTI_CROP_WIDTH", "KITTI_FOCAL_PX", "camera_intrinsics", "render_camera"]

KITTI_FOCAL_PX = 721.5377
"""KITTI's rectified focal length in pixels, for the 1216-pixel-wide benchmark crop."""
KITTI_CROP_WIDTH = 1216


def camera_intrinsics(height: int, width: int) -> np.ndarray:
    """KITTI-like pinhole intrinsics for an image of the given size.

    The focal length is KITTI's (721.5 px at 1216 px wide) scaled with the width, square
    pixels; the principal point sits at KITTI's relative position in the 1216x352 crop
    (horizontally near the centre, vertically at 43 % of the height, so the horizon is
    above the middle of the image and more road is visible).

    Returns:
        (3, 3) float64 K in pixels.

    Raises:
        InputError: ``height`` or ``width`` is not a positive integer.
    """
    check_int("height", height, 1, 16384)
    check_int("width", width, 1, 16384)
    f = KITTI_FOCAL_PX * width / KITTI_CROP_WIDTH
    return np.array([[f, 0.0, 0.4906 * width], [0.0, f, 0.4257 * height], [0.0, 0.0, 1.0]])


# Light and sky colours, (3, 1) float32.
_SUN_COLOUR = np.array([1.0, 0.95, 0.85], dtype=np.float32)[:, None] * 0.75
_SKY_LIGHT = np.array([0.80, 0.86, 1.0], dtype=np.float32)[:, None] * 0.42
_HORIZON = np.array([0.78, 0.84, 0.90], dtype=np.float32)[:, None]
_ZENITH = np.array([0.38, 0.56, 0.86], dtype=np.float32)[:, None]
_CLOUD = np.array([0.95, 0.95, 0.96], dtype=np.float32)[:, None]


def _pose_parts(pose):
    """(R, o, level) of a (4, 4) world<-frame pose; None: identity (R None)."""
    if pose is None:
        return None, np.zeros(3), True
    pose = np.asarray(pose, dtype=np.float64)
    R, o = pose[:3, :3], pose[:3, 3]
    level = bool(abs(R[1, 1] - 1.0) < 1e-12)  # a turn about the vertical (y) axis only
    return R, o, level


def render_camera(world: World, K, height, width, rng, noise_std, pose=None,
                  return_index: bool = False):
    """Ray-cast the camera: (H, W, 3) float32 image in [0, 1], (H, W) float32 z-depth.

    ``pose``: (4, 4) world<-camera transform (default: the camera at the world's origin,
    looking along z). The world's boxes stay axis-aligned: the camera's rays are moved and
    turned instead. ``return_index``: also return the (H, W) int64 index of the primitive
    each pixel sees (-1: sky).
    """
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    dx = ((np.arange(width) - cx) / fx)[None, :]
    dy = ((np.arange(height) - cy) / fy)[:, None]
    dx = np.where(np.abs(dx) < TINY, TINY, dx)
    dy = np.where(np.abs(dy) < TINY, TINY, dy)
    dz = np.ones((1, 1))
    R, o, level = _pose_parts(pose)
    if R is None:
        d = (dx, dy, dz)
        inv = (1.0 / dx, 1.0 / dy, dz)
        windows = camera_windows(world, K, height, width)
    else:
        d = rotate_rays(R, (dx, dy, dz))
        inv = tuple(1.0 / c for c in d)
        lo, hi = boxes_in_frame(world.lo, world.hi, R, o)
        windows = camera_windows(world, K, height, width, lo, hi, level)
    t, idx = cast_rays(world, (height, width), tuple(o), d, inv, windows)

    hit = idx >= 0
    depth = np.where(hit, t, 0.0).astype(np.float32)  # camera rays have d_z = 1: t = z

    flat = np.flatnonzero(hit)
    ih = idx.ravel()[flat]
    # Hits sorted by material, so that texturing works on contiguous slices.
    order = np.argsort(world.mat[ih], kind="stable")
    flat, ih = flat[order], ih[order]
    th = t.ravel()[flat]
    rows, cols = np.divmod(flat, width)
    p = np.empty((3, len(flat)), dtype=np.float32)  # hit points, world frame
    if R is None:
        p[0] = dx[0, cols] * th
        p[1] = dy[rows, 0] * th
        p[2] = th
    else:
        for k in range(3):
            p[k] = o[k] + np.broadcast_to(d[k], (height, width)).ravel()[flat] * th
    n = surface_normals(world, ih, p)
    col, n = textured_albedo(world, ih, p, n)
    lit = _sunlit(world, K, height, width, flat, p, n, pose)

    sun = world.sun.astype(np.float32)
    ndotl = np.maximum(sun[0] * n[0] + sun[1] * n[1] + sun[2] * n[2], 0.0) * lit
    col *= _SKY_LIGHT * (0.8 - 0.2 * n[1]) + _SUN_COLOUR * ndotl
    fog = 1.0 - np.exp(th.astype(np.float32) / -450.0)
    col += (_HORIZON - col) * fog

    image = np.empty((3, height * width), dtype=np.float32)
    image[:, flat] = col
    sky = np.flatnonzero(~hit)
    sr, sc = np.divmod(sky, width)
    image[:, sky] = _sky(world, dx[0, sc].astype(np.float32), dy[sr, 0].astype(np.float32))
    image = _soften(image.reshape(3, height, width))
    if noise_std > 0:
        image += rng.standard_normal(image.shape, dtype=np.float32) * np.float32(noise_std)
    np.clip(image, 0.0, 1.0, out=image)
    image = np.ascontiguousarray(image.transpose(1, 2, 0))
    if return_index:
        return image, depth, idx
    return image, depth


def _soften(img: np.ndarray) -> np.ndarray:
    """Mild optical blur of a (3, H, W) image: [1, 2, 1] / 4 along both axes (anti-alias)."""
    out = img.copy()
    out[:, :, 1:-1] = 0.5 * img[:, :, 1:-1] + 0.25 * (img[:, :, :-2] + img[:, :, 2:])
    tmp = out.copy()
    out[:, 1:-1] = 0.5 * tmp[:, 1:-1] + 0.25 * (tmp[:, :-2] + tmp[:, 2:])
    return out


def _sky(world, dx, dy):
    """(3, M) sky colour for camera rays (dx, dy, 1): gradient and soft clouds."""
    el = np.arctan2(-dy, np.sqrt(dx * dx + 1.0))  # elevation of the ray, radians
    s = np.clip(el / math.radians(40.0), 0.0, 1.0) ** 0.7
    img = _HORIZON + (_ZENITH - _HORIZON) * s
    # Clouds on a plane high up, seen in perspective.
    up = np.maximum(-dy, 0.02)
    u, w = dx / up * 0.35, 0.35 / up
    c = value_noise(world.noise, u, w) * 0.6 + value_noise(world.noise, 2.3 * u + 17, 2.3 * w) * 0.4
    c = np.clip((c - 0.55) * 3.0, 0.0, 1.0) * np.clip(el / 0.08, 0.0, 1.0) * 0.8
    return img + (_CLOUD - img) * c


def _sunlit(world: World, K, height, width, flat, p, n, pose=None) -> np.ndarray:
    """(M,) 1 where hit point p (3, M) at pixel ``flat`` sees the sun, 0 where shadowed.

    ``p`` and ``n`` are in the world frame; ``pose`` is the camera's (see :func:`render_camera`).
    """
    L = world.sun
    lit = np.ones(height * width, dtype=np.float32)
    facing = np.zeros(height * width, dtype=bool)
    facing[flat] = L[0] * n[0] + L[1] * n[1] + L[2] * n[2] > 0
    facing = facing.reshape(height, width)
    grid = []
    for k in range(3):  # shadow-ray origins, nudged off the surface; sky: far away
        g = np.full(height * width, 1e6)
        g[flat] = p[k] + n[k] * 1e-3
        grid.append(g.reshape(height, width))
    # The points a box can shadow lie in the box swept along -L down to the ground.
    sweep = (world.ground_y - world.lo[:, 1]) / max(-L[1], 1e-3)
    moved_lo = world.lo - sweep[:, None] * L
    moved_hi = world.hi - sweep[:, None] * L
    lo = np.minimum(world.lo, np.minimum(moved_lo, moved_hi))
    hi = np.maximum(world.hi, np.maximum(moved_lo, moved_hi))
    inv = tuple(1.0 / (c if abs(c) > TINY else TINY) for c in L)
    lit2 = lit.reshape(height, width)
    R, o, level = _pose_parts(pose)
    if R is not None:
        lo, hi = boxes_in_frame(lo, hi, R, o)
    for i, rs, cs in camera_windows(world, K, height, width, lo, hi, level):
        if world.kind[i] == PLANE:
            continue
        f = facing[rs, cs]
        if not f.any():
            continue
        o = tuple(g[rs, cs] for g in grid)
        occluded = np.isfinite(intersect(world, i, o, L, inv, any_hit=True)) & f
        lit2[rs, cs][occluded] = 0.0
    return lit[flat]

