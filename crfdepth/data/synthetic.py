"""The built-in synthetic street scene: RGB image, dense depth and a simulated LiDAR scan.

No download, runs anywhere: :func:`make_scene` builds a seeded, procedurally generated
street (road with lane markings, raised sidewalks, building façades with windows, parked
and moving cars, poles, street lamps, signs, trees, sky) and renders it by vectorised ray
casting from a pinhole camera:

- ``image``: Lambertian shading from a sun direction, with cast shadows, per-object base
  colours and procedural texture (asphalt noise, lane markings, paving tiles, windows,
  car lights, foliage), a sky gradient with clouds, a mild optical blur (one ray per pixel
  would alias) and a little sensor noise.
- ``depth``: dense ground-truth camera z-depth in metres, **0 where the pixel sees sky**
  (no surface), the same convention as KITTI's ground truth (0 = no value).
- ``sparse``: a simulated Velodyne HDL-64E-like scan (64 beams by default) with range
  noise, random dropouts and a maximum range, mounted like KITTI's LiDAR (0.27 m behind,
  0.08 m above and 0.06 m to the right of the camera) and projected into the camera with
  :func:`crfdepth.projection.project_to_depth` (z-buffer, nearest point per pixel). Because
  the LiDAR sees the scene from another viewpoint, background points leak through at the
  edges of foreground objects, as they do in KITTI's ``velodyne_raw``.

Coordinate frames. Camera: x right, y down, z forward (metres), the camera 1.65 m above a
flat ground (KITTI). LiDAR: KITTI Velodyne axes, x forward, y left, z up.
``T_cam_lidar`` maps homogeneous LiDAR points to camera points: ``p_cam = T @ p_lidar``.

All randomness comes from ``numpy.random.default_rng(seed)``: one seed gives identical
arrays on every run; nothing happens at import.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from numbers import Integral, Real

import numpy as np
import torch

from crfdepth.errors import InputError
from crfdepth.projection import project_to_depth

__all__ = ["SyntheticScene", "make_scene", "camera_intrinsics", "lidar_elevations"]

KITTI_FOCAL_PX = 721.5377
"""KITTI's rectified focal length in pixels, for the 1216-pixel-wide benchmark crop."""
KITTI_CROP_WIDTH = 1216
CAMERA_HEIGHT_M = 1.65
"""Height of the camera above the ground, metres (KITTI)."""
LIDAR_IN_CAMERA_M = (0.06, -0.08, -0.27)
"""Position of the LiDAR origin in the camera frame (x right, y down, z forward), metres:
0.06 m to the right, 0.08 m above and 0.27 m behind the camera, like KITTI's Velodyne
seen from the left colour camera."""
EVAL_MAX_DEPTH_M = 80.0
"""Farthest ground truth used for metrics, metres (KITTI's annotations end near 80 m)."""
MIN_RANGE_M = 1.0
"""Returns closer than this are discarded (the sensor's blind zone)."""

# Primitive kinds.
_PLANE, _BOX, _CYLINDER, _SPHERE = 0, 1, 2, 3
# Materials.
(_ROAD, _SIDEWALK, _FACADE, _CAR_BODY, _CAR_CABIN, _WHEEL, _SIGN, _POLE, _TRUNK,
 _FOLIAGE) = range(10)
_N_MATERIALS = 10
# LiDAR reflectance per material (lane markings get their own value).
_REFLECTANCE = np.array([0.22, 0.35, 0.3, 0.55, 0.08, 0.1, 0.95, 0.6, 0.3, 0.25])
_MARKING_REFLECTANCE = 0.8
_NEAR = 0.05  # camera near plane, metres
_EPS = 1e-6
_TINY = 1e-12


@dataclass(frozen=True)
class SyntheticScene:
    """One rendered frame of the synthetic street.

    Attributes:
        image: (H, W, 3) float32 RGB in [0, 1].
        depth: (H, W) float32 dense ground-truth camera z-depth in metres; 0 = sky (no
            surface), like KITTI's ground truth.
        sparse: (H, W) float32 LiDAR z-depth in metres projected into the camera (nearest
            return per pixel); 0 = no LiDAR return.
        K: (3, 3) float64 pinhole intrinsics of ``image`` (pixels).
        points: (N, 4) float32 LiDAR returns in the LiDAR frame (x forward, y left, z up,
            metres) and intensity in [0, 1]; ordered by ring, then azimuth.
        rings: (N,) int64 beam index of each point; 0 = lowest beam (most downward),
            ``beams - 1`` = highest, as in the ROS Velodyne driver.
        T_cam_lidar: (4, 4) float64 rigid transform, LiDAR frame to camera frame.
        name: identifies the frame, e.g. ``"synthetic-seed0"``.
    """

    image: np.ndarray
    depth: np.ndarray
    sparse: np.ndarray
    K: np.ndarray
    points: np.ndarray
    rings: np.ndarray
    T_cam_lidar: np.ndarray
    name: str

    def to_tensors(self) -> dict[str, torch.Tensor]:
        """The frame as torch tensors in the library convention (DESIGN.md section 1).

        Returns:
            ``{"image": (3, H, W) float32 in [0, 1], "sparse": (1, H, W) float32 metres
            (0 = no return), "depth": (1, H, W) float32 metres (0 = sky), "K": (3, 3)
            float32 pixels, "target": (1, H, W) float32 metres, :meth:`target`}``. New
            tensors; the scene's arrays are not shared.
        """
        return {
            "image": torch.tensor(self.image.transpose(2, 0, 1), dtype=torch.float32),
            "sparse": torch.tensor(self.sparse[None], dtype=torch.float32),
            "depth": torch.tensor(self.depth[None], dtype=torch.float32),
            "K": torch.tensor(self.K, dtype=torch.float32),
            "target": torch.tensor(self.target()[None], dtype=torch.float32),
        }

    def target(self, max_depth: float = EVAL_MAX_DEPTH_M) -> np.ndarray:
        """(H, W) float32 ground truth restricted like KITTI's: metres, 0 = not evaluated.

        The dense ``depth`` reaches the horizon; KITTI's ground truth (accumulated LiDAR)
        covers only the image below the top scan line and up to about 80 m. Metrics on
        this scene use ``depth`` there: rows below the first row holding a LiDAR return,
        depths in (0, ``max_depth``].
        """
        target = self.depth.copy()
        rows = np.flatnonzero((self.sparse > 0).any(axis=1))
        target[: rows[0] if rows.size else target.shape[0]] = 0.0
        target[target > max_depth] = 0.0
        return target


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
    _check_int("height", height, 1, 16384)
    _check_int("width", width, 1, 16384)
    f = KITTI_FOCAL_PX * width / KITTI_CROP_WIDTH
    return np.array([[f, 0.0, 0.4906 * width], [0.0, f, 0.4257 * height], [0.0, 0.0, 1.0]])


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
    _check_int("beams", beams, 1, 128)
    s = np.linspace(0.0, 1.0, beams) if beams > 1 else np.zeros(1)
    top_down = np.interp(s, [0.0, 31 / 63, 32 / 63, 1.0], [2.0, -8.33, -8.83, -24.8])
    return top_down[::-1].copy()


def make_scene(
    seed: int = 0,
    height: int = 352,
    width: int = 1216,
    beams: int = 64,
    *,
    azimuth_step_deg: float = 0.17,
    max_range: float = 100.0,
    range_noise_std: float = 0.02,
    dropout: float = 0.03,
    image_noise_std: float = 0.008,
) -> SyntheticScene:
    """Generate and render one synthetic street frame.

    Args:
        seed: non-negative integer; the same seed gives identical arrays.
        height: image height in pixels, >= 1 (default 352, the KITTI crop).
        width: image width in pixels, >= 1 (default 1216). The focal length scales with
            it (see :func:`camera_intrinsics`).
        beams: number of LiDAR beams, 1 to 128 (64: HDL-64E-like; 32 and 16 sample the
            same vertical field more coarsely, see :func:`lidar_elevations`).
        azimuth_step_deg: horizontal angle between two firings of one beam, degrees, in
            (0, 10]. The scan covers 360 degrees. The default gives 4-5 % of the pixels
            of a 1216x352 frame a return with 64 beams, like KITTI's ``velodyne_raw``.
        max_range: farthest return in metres, > 1 (surfaces beyond give no return).
        range_noise_std: standard deviation of the Gaussian range noise, metres, >= 0.
        dropout: probability that a return is lost, in [0, 1).
        image_noise_std: standard deviation of Gaussian noise added to the RGB image,
            >= 0 (before clipping to [0, 1]).

    Returns:
        A :class:`SyntheticScene`. ``sparse`` is the scan projected with
        :func:`crfdepth.projection.project_to_depth` using ``T_cam_lidar`` and ``K``.

    Raises:
        InputError: an argument is of the wrong type or out of range.
    """
    _check_int("seed", seed, 0, None)
    _check_int("height", height, 1, 16384)
    _check_int("width", width, 1, 16384)
    _check_int("beams", beams, 1, 128)
    _check_real("azimuth_step_deg", azimuth_step_deg, 0.0, 10.0, low_open=True)
    _check_real("max_range", max_range, MIN_RANGE_M, None, low_open=True)
    _check_real("range_noise_std", range_noise_std, 0.0, None)
    _check_real("dropout", dropout, 0.0, 1.0, high_open=True)
    _check_real("image_noise_std", image_noise_std, 0.0, None)
    seed, height, width, beams = int(seed), int(height), int(width), int(beams)

    rng = np.random.default_rng(seed)
    world = _build_world(rng)
    K = camera_intrinsics(height, width)
    image, depth = _render_camera(world, K, height, width, rng, float(image_noise_std))
    points, rings = _scan_lidar(
        world, rng, beams, float(azimuth_step_deg), float(max_range),
        float(range_noise_std), float(dropout),
    )
    T = _T_cam_lidar()
    points_cam = points[:, :3].astype(np.float64) @ T[:3, :3].T + T[:3, 3]
    sparse = project_to_depth(points_cam, K, (height, width))
    return SyntheticScene(
        image=image, depth=depth, sparse=sparse, K=K, points=points, rings=rings,
        T_cam_lidar=T, name=f"synthetic-seed{seed}",
    )


# ----------------------------------------------------------------------------------------
# Argument checks


def _check_int(name: str, value, low: int, high: int | None) -> None:
    if isinstance(value, bool) or not isinstance(value, Integral):
        raise InputError(f"{name}: expected an integer, got {value!r} ({type(value).__name__})")
    if value < low or (high is not None and value > high):
        upper = "" if high is None else f" and <= {high}"
        raise InputError(f"{name}: expected an integer >= {low}{upper}, got {value}")


def _check_real(name: str, value, low: float, high: float | None, *, low_open: bool = False,
                high_open: bool = False) -> None:
    if isinstance(value, bool) or not isinstance(value, Real) or not math.isfinite(value):
        raise InputError(f"{name}: expected a finite number, got {value!r}")
    bad_low = value <= low if low_open else value < low
    bad_high = high is not None and (value >= high if high_open else value > high)
    if bad_low or bad_high:
        lo_b = "(" if low_open else "["
        hi_b = ")" if high_open or high is None else "]"
        hi_s = "inf" if high is None else f"{high:g}"
        raise InputError(f"{name}: expected a value in {lo_b}{low:g}, {hi_s}{hi_b}, got {value!r}")


# ----------------------------------------------------------------------------------------
# The world: a list of primitives in the camera frame (x right, y down, z forward).


@dataclass
class _World:
    kind: np.ndarray  # (n,) primitive kind
    mat: np.ndarray  # (n,) material
    lo: np.ndarray  # (n, 3) axis-aligned bounding box, min corner
    hi: np.ndarray  # (n, 3) max corner
    albedo: np.ndarray  # (n, 3) base colour
    style: np.ndarray  # (n, 4) per-object texture parameters
    ground_y: float  # the ground plane y = ground_y (camera frame, y down)
    road: dict  # lane lines: solid "line_r", "line_l", dashed "dividers", "dash_phase"
    sun: np.ndarray  # (3,) unit vector towards the sun
    noise: np.ndarray  # (256, 256) float32 value-noise table

    def __post_init__(self) -> None:
        # Channel-first copies for gathering per-hit values as (3, M).
        self.centre_t = np.ascontiguousarray((0.5 * (self.lo + self.hi)).T, dtype=np.float32)
        self.half_t = np.ascontiguousarray(np.maximum(0.5 * (self.hi - self.lo), _TINY).T,
                                           dtype=np.float32)
        self.albedo_t = np.ascontiguousarray(self.albedo.T, dtype=np.float32)


class _Builder:
    def __init__(self) -> None:
        self.rows: list[tuple] = []

    def add(self, kind, mat, lo, hi, albedo, style=(0.0, 0.0, 0.0, 0.0)) -> None:
        self.rows.append((kind, mat, lo, hi, albedo, style))

    def box(self, mat, x, y, z, albedo, style=(0.0, 0.0, 0.0, 0.0)) -> None:
        """Box with x, y, z = (min, max) intervals."""
        self.add(_BOX, mat, (x[0], y[0], z[0]), (x[1], y[1], z[1]), albedo, style)

    def cylinder(self, mat, cx, cz, r, y, albedo) -> None:
        """Vertical cylinder (axis along y) of radius r over y = (min, max)."""
        self.add(_CYLINDER, mat, (cx - r, y[0], cz - r), (cx + r, y[1], cz + r), albedo)

    def sphere(self, mat, c, r, albedo) -> None:
        self.add(_SPHERE, mat, tuple(np.subtract(c, r)), tuple(np.add(c, r)), albedo)


_FACADE_COLOURS = np.array([
    [0.80, 0.74, 0.62], [0.66, 0.38, 0.30], [0.72, 0.72, 0.70], [0.86, 0.82, 0.72],
    [0.55, 0.47, 0.40], [0.75, 0.62, 0.48], [0.62, 0.66, 0.70], [0.83, 0.70, 0.55],
])
_CAR_COLOURS = np.array([
    [0.75, 0.10, 0.08], [0.10, 0.20, 0.55], [0.85, 0.85, 0.85], [0.08, 0.08, 0.09],
    [0.55, 0.56, 0.58], [0.25, 0.35, 0.28], [0.80, 0.65, 0.15], [0.35, 0.12, 0.10],
])
_SIGN_COLOURS = np.array([[0.8, 0.1, 0.1], [0.1, 0.3, 0.75], [0.9, 0.75, 0.1]])


def _build_world(rng: np.random.Generator) -> _World:
    g = CAMERA_HEIGHT_M
    b = _Builder()
    lane_w = rng.uniform(3.2, 3.7)
    n_lanes = int(rng.integers(2, 4))  # driving lanes; the camera is in the rightmost
    park_w = 2.3  # parking strip on both sides
    own = rng.uniform(-0.3, 0.3)  # camera offset inside its lane
    x_line_r = lane_w / 2 + own  # solid edge line, right
    x_line_l = x_line_r - n_lanes * lane_w
    x_curb_r, x_curb_l = x_line_r + park_w, x_line_l - park_w
    dividers = [x_line_r - k * lane_w for k in range(1, n_lanes)]
    z_end = rng.uniform(120.0, 200.0)  # the street ends at a cross building
    z_start = -80.0
    curb = 0.15

    # Sidewalks (raised boxes) and façades.
    walk_r, walk_l = rng.uniform(2.5, 4.5), rng.uniform(2.5, 4.5)
    walk_col = np.array([0.62, 0.61, 0.58]) * rng.uniform(0.9, 1.1)
    b.box(_SIDEWALK, (x_curb_r, x_curb_r + walk_r), (g - curb, g), (z_start, z_end), walk_col)
    b.box(_SIDEWALK, (x_curb_l - walk_l, x_curb_l), (g - curb, g), (z_start, z_end), walk_col)
    for side, x_face in ((1, x_curb_r + walk_r), (-1, x_curb_l - walk_l)):
        z = z_start
        while z < z_end:
            length = min(rng.uniform(8.0, 28.0), z_end - z)
            h = rng.uniform(5.0, 16.0) if rng.random() < 0.7 else rng.uniform(16.0, 28.0)
            setback = rng.uniform(0.0, 2.0) if rng.random() < 0.5 else 0.0
            col = _FACADE_COLOURS[rng.integers(len(_FACADE_COLOURS))] * rng.uniform(0.85, 1.1, 3)
            style = (rng.uniform(2.9, 3.6), rng.uniform(2.2, 3.6), rng.uniform(0.35, 0.6),
                     rng.uniform(0.0, 4.0))
            x0 = x_face + side * setback
            xs = (x0, x0 + 20.0) if side > 0 else (x0 - 20.0, x0)
            b.box(_FACADE, xs, (g - h, g), (z, z + length), np.clip(col, 0, 1), style)
            z += length
    h_end = rng.uniform(8.0, 20.0)
    col = _FACADE_COLOURS[rng.integers(len(_FACADE_COLOURS))]
    b.box(_FACADE, (x_curb_l - walk_l - 60.0, x_curb_r + walk_r + 60.0), (g - h_end, g),
          (z_end, z_end + 20.0), col, (3.3, 3.0, 0.5, rng.uniform(0.0, 4.0)))

    # Cars: parked in both parking strips, and moving in the driving lanes.
    placed: list[tuple[float, float, float]] = []  # (x centre, z start, z end)

    def car(cx: float, z0: float) -> None:
        length, wid = rng.uniform(3.9, 4.8), rng.uniform(1.7, 1.9)
        if any(abs(cx - c) < 2.2 and z0 < e + 1.0 and s < z0 + length + 1.0
               for c, s, e in placed):
            return  # would overlap another car
        placed.append((cx, z0, z0 + length))
        col = _CAR_COLOURS[rng.integers(len(_CAR_COLOURS))] * rng.uniform(0.9, 1.05)
        col = np.clip(col, 0, 1)
        top = rng.uniform(1.38, 1.55)
        belt = rng.uniform(0.9, 1.0)
        x = (cx - wid / 2, cx + wid / 2)
        b.box(_CAR_BODY, x, (g - belt, g - 0.3), (z0, z0 + length), col)
        c0 = z0 + length * rng.uniform(0.22, 0.32)
        c1 = z0 + length * rng.uniform(0.72, 0.82)
        b.box(_CAR_CABIN, (x[0] + 0.08, x[1] - 0.08), (g - top, g - belt), (c0, c1), col)
        for za in (z0 + 0.55, z0 + length - 0.55 - 0.64):
            b.box(_WHEEL, (x[0] + 0.03, x[1] - 0.03), (g - 0.64, g), (za, za + 0.64),
                  (0.06, 0.06, 0.07))

    for cx in (x_line_r + park_w / 2, x_line_l - park_w / 2):
        z = rng.uniform(3.0, 9.0)
        while z < 70.0:
            if rng.random() < 0.7:
                car(cx + rng.uniform(-0.2, 0.2), z)
            z += rng.uniform(5.0, 12.0)
    for _ in range(int(rng.integers(1, 4))):
        lane = int(rng.integers(0, n_lanes))
        cx = x_line_r - (lane + 0.5) * lane_w + rng.uniform(-0.3, 0.3)
        car(cx, rng.uniform(9.0 if lane == 0 else 4.0, 55.0))

    # Poles (street lamps, sign posts) near the curb; trees further in.
    for side, x_curb in ((1, x_curb_r), (-1, x_curb_l)):
        z = rng.uniform(2.0, 15.0)
        while z < z_end - 5:
            px = x_curb + side * 0.45
            if rng.random() < 0.6:  # street lamp with an arm over the road
                h = rng.uniform(6.0, 8.5)
                b.cylinder(_POLE, px, z, rng.uniform(0.09, 0.14), (g - h, g - curb),
                           (0.45, 0.46, 0.47))
                arm = (px - side * 1.8, px) if side > 0 else (px, px + 1.8)
                b.box(_POLE, arm, (g - h, g - h + 0.15), (z - 0.1, z + 0.1), (0.45, 0.46, 0.47))
            else:  # sign post
                h = rng.uniform(2.6, 3.2)
                b.cylinder(_POLE, px, z, 0.05, (g - h, g - curb), (0.55, 0.56, 0.57))
                b.box(_SIGN, (px - 0.32, px + 0.32), (g - h - 0.3, g - h + 0.34), (z - 0.04, z),
                      _SIGN_COLOURS[rng.integers(len(_SIGN_COLOURS))])
            z += rng.uniform(14.0, 35.0)
        for _ in range(int(rng.integers(1, 5))):
            tz = rng.uniform(4.0, 80.0)
            tx = x_curb + side * rng.uniform(1.1, 1.6)
            r = rng.uniform(1.3, 2.4)
            h = rng.uniform(2.4, 3.4)
            b.cylinder(_TRUNK, tx, tz, rng.uniform(0.12, 0.2), (g - h - 0.5 * r, g - curb),
                       (0.33, 0.24, 0.16))
            green = np.array([0.22, 0.36, 0.12]) * rng.uniform(0.8, 1.2, 3)
            b.sphere(_FOLIAGE, (tx, g - h - 0.7 * r, tz), r, np.clip(green, 0, 1))

    # Ground plane (road material) last: index n-1.
    b.add(_PLANE, _ROAD, (-1e6, g, -1e6), (1e6, g, 1e6), (0.33, 0.33, 0.34))

    kind, mat, lo, hi, albedo, style = zip(*b.rows)
    sun_el = math.radians(rng.uniform(35.0, 65.0))
    sun_az = math.radians(rng.uniform(-160.0, 160.0))
    sun = np.array([math.cos(sun_el) * math.sin(sun_az), -math.sin(sun_el),
                    math.cos(sun_el) * math.cos(sun_az)])
    road = {"line_r": x_line_r, "line_l": x_line_l, "dividers": np.array(dividers),
            "dash_phase": rng.uniform(0.0, 9.0)}
    return _World(
        kind=np.array(kind, dtype=np.int64), mat=np.array(mat, dtype=np.uint8),
        lo=np.array(lo, dtype=np.float64), hi=np.array(hi, dtype=np.float64),
        albedo=np.array(albedo, dtype=np.float64), style=np.array(style, dtype=np.float64),
        ground_y=g, road=road, sun=sun,
        noise=rng.random((256, 256), dtype=np.float32),
    )


def _T_cam_lidar() -> np.ndarray:
    """(4, 4) LiDAR (x fwd, y left, z up) to camera (x right, y down, z fwd)."""
    T = np.zeros((4, 4))
    T[0, 1] = -1.0  # x_cam = -y_lidar
    T[1, 2] = -1.0  # y_cam = -z_lidar
    T[2, 0] = 1.0  # z_cam = x_lidar
    T[:3, 3] = LIDAR_IN_CAMERA_M
    T[3, 3] = 1.0
    return T


# ----------------------------------------------------------------------------------------
# Ray casting. A ray bundle is a 2-D grid (rows, cols) whose origin and direction
# components are arrays that broadcast to the grid shape: a pinhole camera's x direction
# depends only on the column and its y direction only on the row, so most of the work of
# an intersection is done on 1-D arrays. Each primitive is only tested on a window of the
# grid that can see it.


def _win(a, rs: slice, cs: slice):
    """Slice a broadcastable (R, C), (R, 1), (1, C) or (1, 1) array to a window."""
    if np.ndim(a) == 0:
        return a
    return a[rs if a.shape[0] > 1 else slice(None), cs if a.shape[1] > 1 else slice(None)]


def _intersect(world: _World, i: int, o, d, inv, any_hit: bool = False):
    """Ray parameter t of the first hit with primitive ``i`` (inf for no hit).

    ``o``, ``d``, ``inv`` are 3-tuples of broadcastable arrays (origin, direction,
    1/direction). With ``any_hit`` (shadow rays) any crossing at t > eps counts, even one
    starting inside the primitive.
    """
    kind = world.kind[i]
    lo, hi = world.lo[i], world.hi[i]
    if kind == _BOX:
        tn, tf = -np.inf, np.inf
        for k in range(3):
            a = (lo[k] - o[k]) * inv[k]
            c = (hi[k] - o[k]) * inv[k]
            tn = np.maximum(tn, np.minimum(a, c))
            tf = np.minimum(tf, np.maximum(a, c))
        if any_hit:
            return np.where((tf >= tn) & (tf > _EPS), 1.0, np.inf)
        return np.where((tf >= tn) & (tn > _EPS), tn, np.inf)
    if kind == _CYLINDER:  # vertical, lateral surface only (caps are never seen)
        r = 0.5 * (hi[0] - lo[0])
        fx = o[0] - 0.5 * (lo[0] + hi[0])
        fz = o[2] - 0.5 * (lo[2] + hi[2])
        a = d[0] * d[0] + d[2] * d[2] + _TINY
        bh = fx * d[0] + fz * d[2]
        disc = bh * bh - a * (fx * fx + fz * fz - r * r)
        sq = np.sqrt(np.maximum(disc, 0.0))
        t = (-bh - sq) / a
        if any_hit:
            t = np.where(t > _EPS, t, (-bh + sq) / a)
        y = o[1] + t * d[1]
        ok = (disc >= 0) & (t > _EPS) & (y >= lo[1]) & (y <= hi[1])
        return np.where(ok, t, np.inf)
    if kind == _SPHERE:
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


def _cast(world: _World, shape, o, d, inv, windows):
    """Nearest hit over the primitives. ``windows``: list of (i, row_slice, col_slice).

    Returns (t, idx): (R, C) ray parameter (inf = no hit) and primitive index (-1 = none).
    """
    best_t = np.full(shape, np.inf)
    best_i = np.full(shape, -1, dtype=np.int64)
    for i, rs, cs in windows:
        ow, dw, iw = ([_win(a, rs, cs) for a in v] for v in (o, d, inv))
        t = _intersect(world, i, ow, dw, iw)
        bt = best_t[rs, cs]
        t = np.broadcast_to(t, bt.shape)
        closer = t < bt
        if closer.any():
            np.copyto(bt, t, where=closer)
            np.copyto(best_i[rs, cs], i, where=closer)
    return best_t, best_i


def _normals(world: _World, idx: np.ndarray, p: np.ndarray) -> np.ndarray:
    """Unit outward normals (3, M) float32 at hit points p (3, M) of primitives idx (M,)."""
    kind = world.kind[idx]
    rel = (p.astype(np.float32) - world.centre_t[:, idx]) / world.half_t[:, idx]
    n = np.zeros_like(rel)
    m = kind == _BOX
    if m.any():  # the face is on the axis where the point is farthest out (|rel| = 1)
        r = rel[:, m]
        a = np.abs(r)
        on_x = (a[0] >= a[1]) & (a[0] >= a[2])
        on_y = ~on_x & (a[1] >= a[2])
        on_z = ~on_x & ~on_y
        n[:, m] = np.sign(r) * np.stack([on_x, on_y, on_z])
    m = (kind == _CYLINDER) | (kind == _SPHERE)
    if m.any():
        v = rel[:, m]
        v[1] *= kind[m] == _SPHERE  # cylinders: horizontal normals
        n[:, m] = v / np.maximum(np.sqrt((v * v).sum(axis=0)), _TINY)
    n[1, kind == _PLANE] = -1.0
    return n


def _camera_windows(world: _World, K: np.ndarray, height: int, width: int, lo=None, hi=None):
    """Pixel windows that can see each primitive's box (lo, hi) from a camera at 0."""
    lo = world.lo if lo is None else lo
    hi = world.hi if hi is None else hi
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    out = []
    for i in range(len(world.kind)):
        if world.kind[i] == _PLANE:
            r0 = max(0, min(height, int(math.floor(cy))))
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


# ----------------------------------------------------------------------------------------
# Camera rendering. Per-hit arrays are channel-first, (3, M), so that numpy's inner loops
# run over the hits.

_SUN_COLOUR = np.array([1.0, 0.95, 0.85], dtype=np.float32)[:, None] * 0.75
_SKY_LIGHT = np.array([0.80, 0.86, 1.0], dtype=np.float32)[:, None] * 0.42
_HORIZON = np.array([0.78, 0.84, 0.90], dtype=np.float32)[:, None]
_ZENITH = np.array([0.38, 0.56, 0.86], dtype=np.float32)[:, None]
_CLOUD = np.array([0.95, 0.95, 0.96], dtype=np.float32)[:, None]


def _render_camera(world: _World, K, height, width, rng, noise_std):
    """Ray-cast the camera: (H, W, 3) float32 image in [0, 1], (H, W) float32 z-depth."""
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    dx = ((np.arange(width) - cx) / fx)[None, :]
    dy = ((np.arange(height) - cy) / fy)[:, None]
    dx = np.where(np.abs(dx) < _TINY, _TINY, dx)
    dy = np.where(np.abs(dy) < _TINY, _TINY, dy)
    dz = np.ones((1, 1))
    d = (dx, dy, dz)
    inv = (1.0 / dx, 1.0 / dy, dz)
    windows = _camera_windows(world, K, height, width)
    t, idx = _cast(world, (height, width), (0.0, 0.0, 0.0), d, inv, windows)

    hit = idx >= 0
    depth = np.where(hit, t, 0.0).astype(np.float32)  # camera rays have d_z = 1: t = z

    flat = np.flatnonzero(hit)
    ih = idx.ravel()[flat]
    # Hits sorted by material, so that texturing works on contiguous slices.
    order = np.argsort(world.mat[ih], kind="stable")
    flat, ih = flat[order], ih[order]
    th = t.ravel()[flat]
    rows, cols = np.divmod(flat, width)
    p = np.empty((3, len(flat)), dtype=np.float32)
    p[0] = dx[0, cols] * th
    p[1] = dy[rows, 0] * th
    p[2] = th
    n = _normals(world, ih, p)
    col, n = _albedo(world, ih, p, n)
    lit = _sunlit(world, K, height, width, flat, p, n)

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
    return np.ascontiguousarray(image.transpose(1, 2, 0)), depth


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
    c = _noise(world.noise, u, w) * 0.6 + _noise(world.noise, 2.3 * u + 17, 2.3 * w) * 0.4
    c = np.clip((c - 0.55) * 3.0, 0.0, 1.0) * np.clip(el / 0.08, 0.0, 1.0) * 0.8
    return img + (_CLOUD - img) * c


def _noise(table: np.ndarray, u, v) -> np.ndarray:
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


def _road_markings(world: _World, x: np.ndarray, z: np.ndarray) -> np.ndarray:
    """Boolean mask of lane markings at ground points (x, z), metres."""
    road = world.road
    half = 0.075
    m = (np.abs(x - road["line_r"]) < half) | (np.abs(x - road["line_l"]) < half)
    dashed = np.mod(z + road["dash_phase"], 9.0) < 3.0
    for xd in road["dividers"]:
        m |= (np.abs(x - xd) < half) & dashed
    return m


def _rgb(*c) -> np.ndarray:
    return np.array(c, dtype=np.float32)[:, None]


def _albedo(world: _World, idx, p, n):
    """Textured base colour (3, M) at each hit; foliage also perturbs the normals n.

    The hits must be sorted by material (``world.mat[idx]`` non-decreasing).
    """
    tab = world.noise
    mat = world.mat[idx]
    col = world.albedo_t[:, idx]
    bounds = np.searchsorted(mat, np.arange(_N_MATERIALS + 1))

    def seg(first: int, last: int | None = None) -> slice:
        return slice(bounds[first], bounds[(first if last is None else last) + 1])

    m = seg(_ROAD)
    if m.start < m.stop:
        xm, zm = p[0, m], p[2, m]
        v = 0.82 + 0.22 * _noise(tab, xm * 0.4, zm * 0.15) + 0.12 * _noise(tab, xm * 5 + 50, zm * 5)
        c = col[:, m]
        c *= v
        mark = _road_markings(world, xm, zm)
        c[:, mark] = _rgb(0.86, 0.86, 0.84) * (0.85 + 0.15 * _noise(tab, xm[mark] * 3, zm[mark]))
    m = seg(_SIDEWALK)
    if m.start < m.stop:
        xm, zm = p[0, m], p[2, m]
        top = n[1, m] < -0.5
        joint = (np.mod(xm, 0.6) < 0.035) | (np.mod(zm, 0.6) < 0.035)
        v = 0.9 + 0.15 * _noise(tab, xm * 2 + 90, zm * 2)
        v = np.where(top, np.where(joint, v * 0.8, v), 1.15)  # paving tiles; curb stone
        col[:, m] *= v
    m = seg(_FACADE)
    if m.start < m.stop:
        col[:, m] = _facade(world, idx[m], p[:, m], n[:, m], col[:, m])
    m = seg(_CAR_BODY, _CAR_CABIN)
    if m.start < m.stop:
        col[:, m] = _car(world, idx[m], mat[m], p[:, m], n[:, m], col[:, m])
    m = seg(_SIGN)
    if m.start < m.stop:
        lo, hi = world.lo[idx[m]].T, world.hi[idx[m]].T
        pm = p[:, m]
        border = ((pm[0] - lo[0] < 0.05) | (hi[0] - pm[0] < 0.05)
                  | (pm[1] - lo[1] < 0.05) | (hi[1] - pm[1] < 0.05))
        front = np.abs(n[2, m]) > 0.5
        c = col[:, m]
        c[:, border & front] = 0.9
        c[:, ~front] = 0.5
    m = seg(_POLE, _TRUNK)
    if m.start < m.stop:
        ang = np.arctan2(n[0, m], n[2, m])
        v = 0.8 + 0.35 * _noise(tab, ang * 3 + 7, p[1, m] * (6.0 * (mat[m] == _TRUNK) + 0.5))
        col[:, m] *= v
    m = seg(_FOLIAGE)
    if m.start < m.stop:
        nm = n[:, m]
        r = world.half_t[0, idx[m]]
        u = np.arctan2(nm[0], nm[2]) * r * 2.5 + idx[m] * 13.0
        w = np.arccos(np.clip(nm[1], -1, 1)) * r * 2.5
        c1 = _noise(tab, u, w)
        c2 = _noise(tab, 2.7 * u + 31, 2.7 * w)
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
    wall = col * (0.88 + 0.2 * _noise(tab, s * 1.5, h * 1.5) + 0.04 * _noise(tab, s * 9, h * 9))
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
    cabin = mat == _CAR_CABIN
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


def _sunlit(world: _World, K, height, width, flat, p, n) -> np.ndarray:
    """(M,) 1 where hit point p (3, M) at pixel ``flat`` sees the sun, 0 where shadowed."""
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
    inv = tuple(1.0 / (c if abs(c) > _TINY else _TINY) for c in L)
    lit2 = lit.reshape(height, width)
    for i, rs, cs in _camera_windows(world, K, height, width, lo, hi):
        if world.kind[i] == _PLANE:
            continue
        f = facing[rs, cs]
        if not f.any():
            continue
        o = tuple(g[rs, cs] for g in grid)
        occluded = np.isfinite(_intersect(world, i, o, L, inv, any_hit=True)) & f
        lit2[rs, cs][occluded] = 0.0
    return lit[flat]


# ----------------------------------------------------------------------------------------
# LiDAR


def _lidar_windows(world: _World, origin, az0: float, step: float, n_az: int, beams: int):
    """Column windows (azimuth intervals) of the scan grid that can see each primitive."""
    full = (slice(0, beams), slice(0, n_az))
    out = []
    for i in range(len(world.kind)):
        lo, hi = world.lo[i], world.hi[i]
        if world.kind[i] == _PLANE or (lo[0] - 0.1 <= origin[0] <= hi[0] + 0.1
                                       and lo[2] - 0.1 <= origin[2] <= hi[2] + 0.1):
            out.append((i,) + full)
            continue
        xs = np.array([lo[0], hi[0], lo[0], hi[0]]) - origin[0]
        zs = np.array([lo[2], lo[2], hi[2], hi[2]]) - origin[2]
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


def _scan_lidar(world: _World, rng, beams, step_deg, max_range, noise_std, dropout):
    """Simulate one 360-degree scan: points (N, 4) float32 in the LiDAR frame, rings (N,)."""
    elev = np.radians(lidar_elevations(beams))
    elev = elev + np.radians(rng.normal(0.0, 0.02, beams))  # per-beam calibration error
    n_az = max(1, int(round(360.0 / step_deg)))
    step = 2 * math.pi / n_az
    az0 = rng.uniform(-math.pi, -math.pi + step)
    az = az0 + step * np.arange(n_az)
    ce, se = np.cos(elev)[:, None], np.sin(elev)[:, None]
    ca, sa = np.cos(az)[None, :], np.sin(az)[None, :]
    # Unit directions in the LiDAR frame (x fwd, y left, z up) and in the camera frame.
    lx, ly, lz = ce * ca, ce * sa, se
    d = tuple(np.where(np.abs(c) < _TINY, _TINY, c) for c in (-ly, -lz, lx))
    inv = tuple(1.0 / c for c in d)
    origin = LIDAR_IN_CAMERA_M
    windows = _lidar_windows(world, origin, az0, step, n_az, beams)
    r, idx = _cast(world, (beams, n_az), origin, d, inv, windows)

    ok = (idx >= 0) & (r <= max_range) & (r >= MIN_RANGE_M)
    ok &= rng.random(ok.shape) >= dropout
    bb, jj = np.nonzero(ok)
    ih = idx[bb, jj]
    true_range = r[bb, jj]
    dl = np.stack([lx[bb, jj], ly[bb, jj], lz[bb, 0]])  # (3, N) unit directions
    # Intensity: material reflectance times the cosine of the incidence angle.
    dc = np.stack([-dl[1], -dl[2], dl[0]])
    p = np.asarray(origin)[:, None] + dc * true_range
    n = _normals(world, ih, p)
    refl = _REFLECTANCE[world.mat[ih]]
    ground = world.mat[ih] == _ROAD
    refl[ground] = np.where(_road_markings(world, p[0, ground], p[2, ground]),
                            _MARKING_REFLECTANCE, refl[ground])
    cos_inc = np.abs((n * dc).sum(axis=0))
    intensity = refl * (0.3 + 0.7 * cos_inc) + rng.normal(0.0, 0.02, len(ih))

    measured = true_range + rng.normal(0.0, noise_std, len(ih)) if noise_std > 0 else true_range
    pts = np.empty((len(ih), 4), dtype=np.float32)
    pts[:, :3] = (dl * measured).T
    pts[:, 3] = np.clip(intensity, 0.0, 1.0)
    return pts, bb.astype(np.int64)


class SyntheticScenes(torch.utils.data.Dataset):
    """``count`` built-in street scenes as :class:`~crfdepth.data.sample.Sample` items.

    Item ``i`` is ``make_scene(seed + i, ...)``; its target is :meth:`SyntheticScene.target`
    (the ground truth KITTI would have). Scenes are generated on access (about 0.25 s at
    1216x352), so DataLoader workers parallelise them; nothing is cached.

    Args:
        count: number of scenes, >= 1.
        seed: seed of the first scene; use disjoint ranges for train and validation.
        height, width, beams: as for :func:`make_scene`.
    """

    def __init__(self, count: int = 8, seed: int = 0, height: int = 352, width: int = 1216, beams: int = 64):
        _check_int("count", count, 1, None)
        _check_int("seed", seed, 0, None)
        self.count, self.seed, self.height, self.width, self.beams = count, seed, height, width, beams

    def __len__(self) -> int:
        return self.count

    def __getitem__(self, index: int):
        from crfdepth.data.sample import Sample

        if not 0 <= index < self.count:
            raise IndexError(f"index {index} out of range for {self.count} scenes")
        scene = make_scene(self.seed + index, self.height, self.width, self.beams)
        t = scene.to_tensors()
        return Sample(image=t["image"], sparse=t["sparse"], target=t["target"], K=t["K"], name=scene.name)

    @property
    def names(self) -> list[str]:
        return [f"synthetic-seed{self.seed + i}" for i in range(self.count)]
