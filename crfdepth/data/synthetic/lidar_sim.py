"""The simulated LiDAR of the synthetic scene: an HDL-64E-like spinning scanner.

Mounted like KITTI's Velodyne (0.27 m behind, 0.08 m above and 0.06 m to the right of the
camera), 64 beams by default (fewer sample the same vertical field), a full 360-degree
scan ray-cast against the world, with range noise, random dropouts, a blind zone and a
maximum range. Points are returned in the LiDAR frame (KITTI Velodyne axes: x forward,
y left, z up, metres) with an intensity from the material's reflectance and the incidence
angle; :func:`lidar_to_camera` gives the mount (docs/design.md section 1).
"""

from __future__ import annotations

import math

import numpy as np

from crfdepth.data.synthetic._checks import check_int
from crfdepth.data.synthetic.raycast import boxes_in_frame, cast_rays, rotate_rays, surface_normals
from crfdepth.data.synthetic.world import PLANE, ROAD, TINY, World, road_markings

__all__ = ["LIDAR_IN_CAMERA_M", "MIN_RANGE_M", "lidar_elevations", "lidar_to_camera", "scan_lidar"]

LIDAR_IN_CAMERA_M = (0.06, -0.08, -0.27)
"""Position of the LiDAR origin in the camera frame (x right, y down, z forward), metres:
0.06 m to the right, 0.08 m above and 0.27 m behind the camera, like KITTI's Velodyne
seen from the left colour camera."""
MIN_RANGE_M = 1.0
"""Returns closer than this are discarded (the sensor's blind zone)."""

# LiDAR reflectance per material (lane markings get their own value).
_REFLECTANCE = np.array([0.22, 0.35, 0.3, 0.55, 0.08, 0.1, 0.95, 0.6, 0.3, 0.25])
_MARKING_REFLECTANCE = 0.8


def lidar_elevations(beams: int) -> np.ndarray:
    """Beam elevations of the simulated scanner, degrees, lowest first.

    With 64 beams this is the HDL-64E layout: an upper block of 32 beams from +2.0 to
    -8.33 degrees (about 1/3 degree apart) and a lower block of 32 from -8.83 to -24.8
    degrees (about 1/2 degree apart). Fewer (or more) beams sample the same vertical field
    with the same profile, so 16 beams sit close to every fourth beam of the 64 and give
    about a quarter of the returns. A single beam is the top one (+2 degrees).

    Returns:
        (beams,) float64, ascending (ring 0 first).

    Raises:
        InputError: ``beams`` is not an integer in [1, 128].
    """
    check_int("beams", beams, 1, 128)
    s = np.linspace(0.0, 1.0, beams) if beams > 1 else np.zeros(1)
    top_down = np.interp(s, [0.0, 31 / 63, 32 / 63, 1.0], [2.0, -8.33, -8.83, -24.8])
    return top_down[::-1].copy()


def lidar_to_camera() -> np.ndarray:
    """(4, 4) LiDAR (x fwd, y left, z up) to camera (x right, y down, z fwd)."""
    T = np.zeros((4, 4))
    T[0, 1] = -1.0  # x_cam = -y_lidar
    T[1, 2] = -1.0  # y_cam = -z_lidar
    T[2, 0] = 1.0  # z_cam = x_lidar
    T[:3, 3] = LIDAR_IN_CAMERA_M
    T[3, 3] = 1.0
    return T


def _lidar_windows(world: World, origin, az0: float, step: float, n_az: int, beams: int,
                   R=None):
    """Column windows (azimuth intervals) of the scan grid that can see each primitive.

    ``origin``: the LiDAR's position (world frame); ``R``: the camera-axes frame of the
    LiDAR in the world (None: the world's axes), a turn about the vertical only.
    """
    full = (slice(0, beams), slice(0, n_az))
    out = []
    if R is not None:
        lo_l, hi_l = boxes_in_frame(world.lo, world.hi, R, origin)
    for i in range(len(world.kind)):
        lo, hi = world.lo[i], world.hi[i]
        if world.kind[i] == PLANE or (lo[0] - 0.1 <= origin[0] <= hi[0] + 0.1
                                       and lo[2] - 0.1 <= origin[2] <= hi[2] + 0.1):
            out.append((i,) + full)
            continue
        if R is None:
            xs = np.array([lo[0], hi[0], lo[0], hi[0]]) - origin[0]
            zs = np.array([lo[2], lo[2], hi[2], hi[2]]) - origin[2]
        else:  # the corners of the box around the turned footprint, which contains it
            xs = np.array([lo_l[i, 0], hi_l[i, 0], lo_l[i, 0], hi_l[i, 0]])
            zs = np.array([lo_l[i, 2], lo_l[i, 2], hi_l[i, 2], hi_l[i, 2]])
        ang = np.arctan2(-xs, zs)  # LiDAR azimuth: atan2(y_lidar, x_lidar)
        ref = ang[0]
        rel = np.mod(ang - ref + np.pi, 2 * np.pi) - np.pi
        a0, a1 = ref + rel.min(), ref + rel.max()
        j0 = math.floor((a0 - az0) / step) - 1
        span = math.ceil((a1 - a0) / step) + 3
        if span >= n_az:
            out.append((i,) + full)
            continue
        j0 %= n_az
        j1 = j0 + span
        if j1 <= n_az:
            out.append((i, slice(0, beams), slice(j0, j1)))
        else:  # the interval wraps around azimuth +-180 degrees
            out.append((i, slice(0, beams), slice(j0, n_az)))
            out.append((i, slice(0, beams), slice(0, j1 - n_az)))
    return out


def scan_lidar(world: World, rng, beams, step_deg, max_range, noise_std, dropout, pose=None,
               beam_offsets_deg=None, return_index: bool = False):
    """Simulate one 360-degree scan: points (N, 4) float32 in the LiDAR frame, rings (N,).

    ``pose``: (4, 4) world<-camera transform of the camera the LiDAR is mounted on
    (default: the camera at the world's origin), a turn about the vertical only; the scan
    is instantaneous (no motion during the sweep). ``beam_offsets_deg``: (beams,) per-beam
    elevation errors (default: drawn from ``rng``, 0.02 degrees standard deviation).
    ``return_index``: also return the (N,) primitive index of each point.
    """
    elev = np.radians(lidar_elevations(beams))
    if beam_offsets_deg is None:
        beam_offsets_deg = rng.normal(0.0, 0.02, beams)
    elev = elev + np.radians(beam_offsets_deg)  # per-beam calibration error
    n_az = max(1, int(round(360.0 / step_deg)))
    step = 2 * math.pi / n_az
    az0 = rng.uniform(-math.pi, -math.pi + step)
    az = az0 + step * np.arange(n_az)
    ce, se = np.cos(elev)[:, None], np.sin(elev)[:, None]
    ca, sa = np.cos(az)[None, :], np.sin(az)[None, :]
    # Unit directions in the LiDAR frame (x fwd, y left, z up) and in the camera frame.
    lx, ly, lz = ce * ca, ce * sa, se
    if pose is None:
        R = None
        d = tuple(np.where(np.abs(c) < TINY, TINY, c) for c in (-ly, -lz, lx))
        origin = LIDAR_IN_CAMERA_M
    else:
        pose = np.asarray(pose, dtype=np.float64)
        R = pose[:3, :3]
        d = rotate_rays(R, (-ly, -lz, lx))
        origin = tuple(pose[:3, 3] + R @ np.asarray(LIDAR_IN_CAMERA_M))
    inv = tuple(1.0 / c for c in d)
    windows = _lidar_windows(world, origin, az0, step, n_az, beams, R)
    r, idx = cast_rays(world, (beams, n_az), origin, d, inv, windows)

    ok = (idx >= 0) & (r <= max_range) & (r >= MIN_RANGE_M)
    ok &= rng.random(ok.shape) >= dropout
    bb, jj = np.nonzero(ok)
    ih = idx[bb, jj]
    true_range = r[bb, jj]
    dl = np.stack([lx[bb, jj], ly[bb, jj], lz[bb, 0]])  # (3, N) unit directions
    # Intensity: material reflectance times the cosine of the incidence angle.
    dc = np.stack([-dl[1], -dl[2], dl[0]])  # camera axes
    if R is not None:
        dc = R @ dc  # world axes
    p = np.asarray(origin)[:, None] + dc * true_range
    n = surface_normals(world, ih, p)
    refl = _REFLECTANCE[world.mat[ih]]
    ground = world.mat[ih] == ROAD
    refl[ground] = np.where(road_markings(world, p[0, ground], p[2, ground]),
                            _MARKING_REFLECTANCE, refl[ground])
    cos_inc = np.abs((n * dc).sum(axis=0))
    intensity = refl * (0.3 + 0.7 * cos_inc) + rng.normal(0.0, 0.02, len(ih))

    measured = true_range + rng.normal(0.0, noise_std, len(ih)) if noise_std > 0 else true_range
    pts = np.empty((len(ih), 4), dtype=np.float32)
    pts[:, :3] = (dl * measured).T
    pts[:, 3] = np.clip(intensity, 0.0, 1.0)
    if return_index:
        return pts, bb.astype(np.int64), ih
    return pts, bb.astype(np.int64)

