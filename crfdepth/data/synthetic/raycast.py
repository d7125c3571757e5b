"""Vectorised ray casting against the primitives of a :class:`~.world.World`.

A ray bundle is a 2-D grid (rows, cols) whose origin and direction components are arrays
that broadcast to the grid shape: a pinhole camera's x direction depends only on the
column and its y direction only on the row, so most of the work of an intersection is done
on 1-D arrays. Each primitive is only tested on a window of the grid that can see it
(:func:`camera_windows` for the camera; the LiDAR simulator has its own).
"""

from __future__ import annotations

import math

import numpy as np

from crfdepth.data.synthetic.world import BOX, CYLINDER, PLANE, SPHERE, TINY, World

__all__ = ["boxes_in_frame", "camera_windows", "cast_rays", "intersect", "rotate_rays",
           "surface_normals"]

_NEAR = 0.05  # camera near plane, metres
_EPS = 1e-6


def _win(a, rs: slice, cs: slice):
    """Slice a broadcastable (R, C), (R, 1), (1, C) or (1, 1) array to a window."""
    if np.ndim(a) == 0:
        return a
    return a[rs if a.shape[0] > 1 else slice(None), cs if a.shape[1] > 1 else slice(None)]


def intersect(world: World, i: int, o, d, inv, any_hit: bool = False):
    """Ray parameter t of the first hit with primitive ``i`` (inf for no hit).

    ``o``, ``d``, ``inv`` are 3-tuples of broadcastable arrays (origin, direction,
    1/direction). With ``any_hit`` (shadow rays) any crossing at t > eps counts, even one
    starting inside the primitive.
    """
    kind = world.kind[i]
    lo, hi = world.lo[i], world.hi[i]
    if kind == BOX:
        tn, tf = -np.inf, np.inf
        for k in range(3):
            a = (lo[k] - o[k]) * inv[k]
            c = (hi[k] - o[k]) * inv[k]
            tn = np.maximum(tn, np.minimum(a, c))
            tf = np.minimum(tf, np.maximum(a, c))
        if any_hit:
            return np.where((tf >= tn) & (tf > _EPS), 1.0, np.inf)
        return np.where((tf >= tn) & (tn > _EPS), tn, np.inf)
    if kind == CYLINDER:  # vertical, lateral surface only (caps are never seen)
        r = 0.5 * (hi[0] - lo[0])
        fx = o[0] - 0.5 * (lo[0] + hi[0])
        fz = o[2] - 0.5 * (lo[2] + hi[2])
        a = d[0] * d[0] + d[2] * d[2] + TINY
        bh = fx * d[0] + fz * d[2]
        disc = bh * bh - a * (fx * fx + fz * fz - r * r)
        sq = np.sqrt(np.maximum(disc, 0.0))
        t = (-bh - sq) / a
        if any_hit:
            t = np.where(t > _EPS, t, (-bh + sq) / a)
        y = o[1] + t * d[1]
        ok = (disc >= 0) & (t > _EPS) & (y >= lo[1]) & (y <= hi[1])
        return np.where(ok, t, np.inf)
    if kind == SPHERE:
        r = 0.5 * (hi[0] - lo[0])
        f = [o[k] - 0.5 * (lo[k] + hi[k]) for k in range(3)]
        a = d[0] * d[0] + d[1] * d[1] + d[2] * d[2]
        bh = f[0] * d[0] + f[1] * d[1] + f[2] * d[2]
        disc = bh * bh - a * (f[0] * f[0] + f[1] * f[1] + f[2] * f[2] - r * r)
        sq = np.sqrt(np.maximum(disc, 0.0))
        t = (-bh - sq) / a
        if any_hit:
            t = np.where(t > _EPS, t, (-bh + sq) / a)
        return np.where((disc >= 0) & (t > _EPS), t, np.inf)
    # Ground plane y = ground_y, seen from above only.
    t = (world.ground_y - o[1]) * inv[1]
    return np.where((t > _EPS) & (d[1] > 0), t, np.inf)


def cast_rays(world: World, shape, o, d, inv, windows):
    """Nearest hit over the primitives. ``windows``: list of (i, row_slice, col_slice).

    Returns (t, idx): (R, C) ray parameter (inf = no hit) and primitive index (-1 = none).
    """
    best_t = np.full(shape, np.inf)
    best_i = np.full(shape, -1, dtype=np.int64)
    for i, rs, cs in windows:
        ow, dw, iw = ([_win(a, rs, cs) for a in v] for v in (o, d, inv))
        t = intersect(world, i, ow, dw, iw)
        bt = best_t[rs, cs]
        t = np.broadcast_to(t, bt.shape)
        closer = t < bt
        if closer.any():
            np.copyto(bt, t, where=closer)
            np.copyto(best_i[rs, cs], i, where=closer)
    return best_t, best_i


def surface_normals(world: World, idx: np.ndarray, p: np.ndarray) -> np.ndarray:
    """Unit outward normals (3, M) float32 at hit points p (3, M) of primitives idx (M,)."""
    kind = world.kind[idx]
    rel = (p.astype(np.float32) - world.centre_t[:, idx]) / world.half_t[:, idx]
    n = np.zeros_like(rel)
    m = kind == BOX
    if m.any():  # the face is on the axis where the point is farthest out (|rel| = 1)
        r = rel[:, m]
        a = np.abs(r)
        on_x = (a[0] >= a[1]) & (a[0] >= a[2])
        on_y = ~on_x & (a[1] >= a[2])
        on_z = ~on_x & ~on_y
        n[:, m] = np.sign(r) * np.stack([on_x, on_y, on_z])
    m = (kind == CYLINDER) | (kind == SPHERE)
    if m.any():
        v = rel[:, m]
        v[1] *= kind[m] == SPHERE  # cylinders: horizontal normals
        n[:, m] = v / np.maximum(np.sqrt((v * v).sum(axis=0)), TINY)
    n[1, kind == PLANE] = -1.0
    return n


def boxes_in_frame(lo: np.ndarray, hi: np.ndarray, R: np.ndarray, o: np.ndarray):
    """Axis-aligned bounds, in a frame at ``o`` with axes ``R`` (columns, world coordinates),
    of the world boxes (lo, hi) (n, 3): ``R^T (corner - o)`` over the 8 corners.

    A conservative box for the windows of a moved (and turned) camera or LiDAR.
    """
    corners = np.stack([np.where(np.array(b, dtype=bool), hi, lo)
                        for b in np.ndindex(2, 2, 2)], axis=1)  # (n, 8, 3)
    local = (corners - np.asarray(o, dtype=np.float64)) @ np.asarray(R, dtype=np.float64)
    return local.min(axis=1), local.max(axis=1)


def rotate_rays(R: np.ndarray, d):
    """World directions ``R @ d`` of a ray bundle ``d`` (3-tuple of broadcastable arrays).

    Terms with a zero coefficient are skipped, so a turn about the vertical keeps a pinhole
    camera's separable (1, W) / (H, 1) components. Components of magnitude below TINY are
    replaced by TINY (their inverse is taken).
    """
    out = []
    for k in range(3):
        c = np.zeros((1, 1))
        for j in range(3):
            if R[k, j] != 0.0:
                c = c + R[k, j] * d[j]
        out.append(np.where(np.abs(c) < TINY, TINY, c))
    return tuple(out)


def camera_windows(world: World, K: np.ndarray, height: int, width: int, lo=None, hi=None,
                   level: bool = True):
    """Pixel windows that can see each primitive's box (lo, hi) from a camera at 0.

    ``lo``, ``hi`` are in the camera frame (default: the world's boxes, camera at the world's
    origin). ``level``: the camera's x axis is horizontal and its y axis vertical (a turn
    about the vertical only), so the ground is seen below the horizon row ``cy`` only;
    otherwise the ground plane's window is the whole image.
    """
    lo = world.lo if lo is None else lo
    hi = world.hi if hi is None else hi
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    out = []
    for i in range(len(world.kind)):
        if world.kind[i] == PLANE:
            r0 = max(0, min(height, int(math.floor(cy)))) if level else 0
            out.append((i, slice(r0, height), slice(0, width)))
            continue
        z0 = max(lo[i, 2], _NEAR)
        if hi[i, 2] <= z0:
            continue
        xs = np.array([lo[i, 0], hi[i, 0]])[:, None]
        ys = np.array([lo[i, 1], hi[i, 1]])[:, None]
        zs = np.array([z0, hi[i, 2]])[None, :]
        u, v = fx * xs / zs + cx, fy * ys / zs + cy
        c0, c1 = max(0, math.floor(u.min()) - 1), min(width, math.ceil(u.max()) + 2)
        r0, r1 = max(0, math.floor(v.min()) - 1), min(height, math.ceil(v.max()) + 2)
        if c0 < c1 and r0 < r1:
            out.append((i, slice(r0, r1), slice(c0, c1)))
    return out

