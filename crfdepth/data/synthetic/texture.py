"""Surface appearance of the synthetic street: value noise and per-material textures.

Asphalt noise and lane markings, paving tiles and curb stones, façades with floors of
windows and shop windows, cars with glass, pillars, lights and number plates, signs,
poles, bark and foliage. Per-hit arrays are channel-first, (3, M), so that numpy's inner
loops run over the hits.
"""

from __future__ import annotations

import numpy as np

from crfdepth.data.synthetic.world import (
    CAR_BODY,
    CAR_CABIN,
    FACADE,
    FOLIAGE,
    N_MATERIALS,
    POLE,
    ROAD,
    SIDEWALK,
    SIGN,
    TRUNK,
    World,
    road_markings,
)

__all__ = ["textured_albedo", "value_noise"]


def value_noise(table: np.ndarray, u, v) -> np.ndarray:
    """Smooth value noise in [0, 1] at coordinates (u, v) (same shapes), float32."""
    u = np.asarray(u, dtype=np.float32)
    v = np.asarray(v, dtype=np.float32)
    iu, iv = np.floor(u), np.floor(v)
    fu, fv = u - iu, v - iv
    fu, fv = fu * fu * (3 - 2 * fu), fv * fv * (3 - 2 * fv)
    iu = iu.astype(np.int32) & 255  # the table is 256 x 256
    iv = (iv.astype(np.int32) & 255) << 8
    iu1, iv1 = (iu + 1) & 255, (iv + 256) & 0xFF00
    flat = table.ravel()
    a = flat[iv + iu]
    a += (flat[iv + iu1] - a) * fu
    b = flat[iv1 + iu]
    b += (flat[iv1 + iu1] - b) * fu
    return a + (b - a) * fv


def _rgb(*c) -> np.ndarray:
    return np.array(c, dtype=np.float32)[:, None]


def textured_albedo(world: World, idx, p, n):
    """Textured base colour (3, M) at each hit; foliage also perturbs the normals n.

    The hits must be sorted by material (``world.mat[idx]`` non-decreasing).
    """
    tab = world.noise
    mat = world.mat[idx]
    col = world.albedo_t[:, idx]
    bounds = np.searchsorted(mat, np.arange(N_MATERIALS + 1))

    def seg(first: int, last: int | None = None) -> slice:
        return slice(bounds[first], bounds[(first if last is None else last) + 1])

    m = seg(ROAD)
    if m.start < m.stop:
        xm, zm = p[0, m], p[2, m]
        v = 0.82 + 0.22 * value_noise(tab, xm * 0.4, zm * 0.15) + 0.12 * value_noise(tab, xm * 5 + 50, zm * 5)
        c = col[:, m]
        c *= v
        mark = road_markings(world, xm, zm)
        c[:, mark] = _rgb(0.86, 0.86, 0.84) * (0.85 + 0.15 * value_noise(tab, xm[mark] * 3, zm[mark]))
    m = seg(SIDEWALK)
    if m.start < m.stop:
        xm, zm = p[0, m], p[2, m]
        top = n[1, m] < -0.5
        joint = (np.mod(xm, 0.6) < 0.035) | (np.mod(zm, 0.6) < 0.035)
        v = 0.9 + 0.15 * value_noise(tab, xm * 2 + 90, zm * 2)
        v = np.where(top, np.where(joint, v * 0.8, v), 1.15)  # paving tiles; curb stone
        col[:, m] *= v
    m = seg(FACADE)
    if m.start < m.stop:
        col[:, m] = _facade(world, idx[m], p[:, m], n[:, m], col[:, m])
    m = seg(CAR_BODY, CAR_CABIN)
    if m.start < m.stop:
        col[:, m] = _car(world, idx[m], mat[m], p[:, m], n[:, m], col[:, m])
    m = seg(SIGN)
    if m.start < m.stop:
        lo, hi = world.lo[idx[m]].T, world.hi[idx[m]].T
        pm = p[:, m]
        border = ((pm[0] - lo[0] < 0.05) | (hi[0] - pm[0] < 0.05)
                  | (pm[1] - lo[1] < 0.05) | (hi[1] - pm[1] < 0.05))
        front = np.abs(n[2, m]) > 0.5
        c = col[:, m]
        c[:, border & front] = 0.9
        c[:, ~front] = 0.5
    m = seg(POLE, TRUNK)
    if m.start < m.stop:
        ang = np.arctan2(n[0, m], n[2, m])
        v = 0.8 + 0.35 * value_noise(tab, ang * 3 + 7, p[1, m] * (6.0 * (mat[m] == TRUNK) + 0.5))
        col[:, m] *= v
    m = seg(FOLIAGE)
    if m.start < m.stop:
        nm = n[:, m]
        r = world.half_t[0, idx[m]]
        u = np.arctan2(nm[0], nm[2]) * r * 2.5 + idx[m] * 13.0
        w = np.arccos(np.clip(nm[1], -1, 1)) * r * 2.5
        c1 = value_noise(tab, u, w)
        c2 = value_noise(tab, 2.7 * u + 31, 2.7 * w)
        col[:, m] *= (0.45 + 0.9 * (0.6 * c1 + 0.4 * c2)) * (0.75 - 0.25 * nm[1])
        # Bumpy normals: clumps of leaves catch the sun unevenly.
        nn = nm + 0.8 * np.stack([c1 - 0.5, c2 - 0.5, 0.5 - c1])
        n[:, m] = nn / np.sqrt((nn * nn).sum(axis=0))
    np.clip(col, 0.0, 1.0, out=col)
    return col, n


def _facade(world, idx, p, n, col):
    """Façade texture (3, M): floors of windows, shop windows on the ground floor."""
    fh, wp, wf, phase = (world.style[idx, k].astype(np.float32) for k in range(4))
    h = np.float32(world.ground_y) - p[1]  # height above ground
    side = np.abs(n[0]) > 0.5  # faces along the street; others show x
    s = np.where(side, p[2], p[0]) + phase
    top_h = (world.ground_y - world.lo[idx, 1]).astype(np.float32)
    floor = np.floor(h / fh)
    fy = h - floor * fh
    cell = np.floor(s / wp)
    fxw = s - cell * wp
    ww = wf * wp
    upper = (floor >= 1) & (fy > 0.9) & (fy < 2.3) & (fxw < ww) & (h < top_h - 0.9)
    shop = (floor == 0) & (fy > 0.5) & (fy < 2.6) & (fxw < 0.8 * wp) & (fxw > 0.1 * wp)
    vertical = np.abs(n[1]) < 0.5
    window = (upper | shop) & vertical
    tab = world.noise
    wall = col * (0.88 + 0.2 * value_noise(tab, s * 1.5, h * 1.5) + 0.04 * value_noise(tab, s * 9, h * 9))
    band = vertical & (((fy < 0.18) & (floor >= 1)) | (h > top_h - 0.5))  # cornices
    wall[:, band] *= 0.82
    # One random value per window: some reflect more sky, some are lit.
    rnd = tab[(floor.astype(np.int64) * 7 + idx * 13) & 255,
              (cell.astype(np.int64) + idx * 31) & 255]
    glass = _rgb(0.10, 0.13, 0.17) + rnd * rnd * _rgb(0.25, 0.25, 0.22)
    out = np.where(window, glass, wall)
    frame = upper & vertical & ((fy < 0.97) | (fy > 2.23) | (fxw < 0.07) | (fxw > ww - 0.07))
    out[:, frame] = _rgb(0.85, 0.85, 0.82)
    return out


def _car(world, idx, mat, p, n, col):
    """Car texture (3, M): glass cabin with pillars, lights and a number plate."""
    lo, hi = world.lo[idx].T.astype(np.float32), world.hi[idx].T.astype(np.float32)
    x, y, z = p
    out = col.copy()
    cabin = mat == CAR_CABIN
    roof = n[1] < -0.5
    side = np.abs(n[0]) > 0.5
    along = np.where(side, z, x)
    a_lo = np.where(side, lo[2], lo[0])
    a_hi = np.where(side, hi[2], hi[0])
    pillar = (along - a_lo < 0.1) | (a_hi - along < 0.1) | (hi[1] - y < 0.05) | (y - lo[1] < 0.06)
    glass = cabin & ~roof & ~pillar
    out[:, glass] = _rgb(0.08, 0.10, 0.13) + 0.12 * np.clip(0.3 - n[1, glass], 0.0, 1.0)
    end_face = ~cabin & (np.abs(n[2]) > 0.5)
    xr = (x - lo[0]) / (hi[0] - lo[0])
    yr = y - lo[1]  # metres below the top of the body
    light = end_face & (yr > 0.08) & (yr < 0.25) & ((xr < 0.2) | (xr > 0.8))
    rear = n[2] < 0
    out[:, light & rear] = _rgb(0.8, 0.08, 0.05)
    out[:, light & ~rear] = _rgb(0.95, 0.93, 0.8)
    out[:, end_face & (np.abs(xr - 0.5) < 0.14) & (yr > 0.33) & (yr < 0.45)] = 0.92  # plate
    return out

