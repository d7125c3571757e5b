"""The synthetic street as a list of primitives in the camera frame (docs/design.md section 1).

:func:`build_world` draws one street from a random generator: a road with lane markings,
raised sidewalks, building façades, parked and moving cars, poles, street lamps, signs and
trees, as axis-aligned boxes, vertical cylinders, spheres and the ground plane. Coordinates
are the camera frame (x right, y down, z forward, metres) with the camera at the origin,
1.65 m above the flat ground (KITTI).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

__all__ = [
    "BOX", "CAMERA_HEIGHT_M", "CAR_BODY", "CAR_CABIN", "CYLINDER", "FACADE", "FOLIAGE",
    "N_MATERIALS", "PLANE", "POLE", "ROAD", "SIDEWALK", "SIGN", "SPHERE", "TINY", "TRUNK",
    "WHEEL", "World", "build_world", "road_markings",
]

CAMERA_HEIGHT_M = 1.65
"""Height of the camera above the ground, metres (KITTI)."""

# Primitive kinds.
PLANE, BOX, CYLINDER, SPHERE = 0, 1, 2, 3
# Materials.
(ROAD, SIDEWALK, FACADE, CAR_BODY, CAR_CABIN, WHEEL, SIGN, POLE, TRUNK,
 FOLIAGE) = range(10)
N_MATERIALS = 10
TINY = 1e-12


@dataclass
class World:
    """The primitives of one street, camera frame (x right, y down, z forward, metres).

    Kinds are ``PLANE``, ``BOX``, ``CYLINDER`` (vertical) and ``SPHERE``, each given by
    its axis-aligned bounding box; materials are ``ROAD`` ... ``FOLIAGE``. The ground
    plane is the last primitive.
    """

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
        self.half_t = np.ascontiguousarray(np.maximum(0.5 * (self.hi - self.lo), TINY).T,
                                           dtype=np.float32)
        self.albedo_t = np.ascontiguousarray(self.albedo.T, dtype=np.float32)


class _Builder:
    """Collects primitives as rows (kind, material, lo, hi, albedo, style)."""

    def __init__(self) -> None:
        self.rows: list[tuple] = []

    def add(self, kind, mat, lo, hi, albedo, style=(0.0, 0.0, 0.0, 0.0)) -> None:
        self.rows.append((kind, mat, lo, hi, albedo, style))

    def box(self, mat, x, y, z, albedo, style=(0.0, 0.0, 0.0, 0.0)) -> None:
        """Box with x, y, z = (min, max) intervals."""
        self.add(BOX, mat, (x[0], y[0], z[0]), (x[1], y[1], z[1]), albedo, style)

    def cylinder(self, mat, cx, cz, r, y, albedo) -> None:
        """Vertical cylinder (axis along y) of radius r over y = (min, max)."""
        self.add(CYLINDER, mat, (cx - r, y[0], cz - r), (cx + r, y[1], cz + r), albedo)

    def sphere(self, mat, c, r, albedo) -> None:
        self.add(SPHERE, mat, tuple(np.subtract(c, r)), tuple(np.add(c, r)), albedo)


_FACADE_COLOURS = np.array([
    [0.80, 0.74, 0.62], [0.66, 0.38, 0.30], [0.72, 0.72, 0.70], [0.86, 0.82, 0.72],
    [0.55, 0.47, 0.40], [0.75, 0.62, 0.48], [0.62, 0.66, 0.70], [0.83, 0.70, 0.55],
])
_CAR_COLOURS = np.array([
    [0.75, 0.10, 0.08], [0.10, 0.20, 0.55], [0.85, 0.85, 0.85], [0.08, 0.08, 0.09],
    [0.55, 0.56, 0.58], [0.25, 0.35, 0.28], [0.80, 0.65, 0.15], [0.35, 0.12, 0.10],
])
_SIGN_COLOURS = np.array([[0.8, 0.1, 0.1], [0.1, 0.3, 0.75], [0.9, 0.75, 0.1]])


def build_world(rng: np.random.Generator) -> World:
    """Draw one street from ``rng`` (the only source of randomness; consumed in a fixed order)."""
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
    b.box(SIDEWALK, (x_curb_r, x_curb_r + walk_r), (g - curb, g), (z_start, z_end), walk_col)
    b.box(SIDEWALK, (x_curb_l - walk_l, x_curb_l), (g - curb, g), (z_start, z_end), walk_col)
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
            b.box(FACADE, xs, (g - h, g), (z, z + length), np.clip(col, 0, 1), style)
            z += length
    h_end = rng.uniform(8.0, 20.0)
    col = _FACADE_COLOURS[rng.integers(len(_FACADE_COLOURS))]
    b.box(FACADE, (x_curb_l - walk_l - 60.0, x_curb_r + walk_r + 60.0), (g - h_end, g),
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
        b.box(CAR_BODY, x, (g - belt, g - 0.3), (z0, z0 + length), col)
        c0 = z0 + length * rng.uniform(0.22, 0.32)
        c1 = z0 + length * rng.uniform(0.72, 0.82)
        b.box(CAR_CABIN, (x[0] + 0.08, x[1] - 0.08), (g - top, g - belt), (c0, c1), col)
        for za in (z0 + 0.55, z0 + length - 0.55 - 0.64):
            b.box(WHEEL, (x[0] + 0.03, x[1] - 0.03), (g - 0.64, g), (za, za + 0.64),
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
                b.cylinder(POLE, px, z, rng.uniform(0.09, 0.14), (g - h, g - curb),
                           (0.45, 0.46, 0.47))
                arm = (px - side * 1.8, px) if side > 0 else (px, px + 1.8)
                b.box(POLE, arm, (g - h, g - h + 0.15), (z - 0.1, z + 0.1), (0.45, 0.46, 0.47))
            else:  # sign post
                h = rng.uniform(2.6, 3.2)
                b.cylinder(POLE, px, z, 0.05, (g - h, g - curb), (0.55, 0.56, 0.57))
                b.box(SIGN, (px - 0.32, px + 0.32), (g - h - 0.3, g - h + 0.34), (z - 0.04, z),
                      _SIGN_COLOURS[rng.integers(len(_SIGN_COLOURS))])
            z += rng.uniform(14.0, 35.0)
        for _ in range(int(rng.integers(1, 5))):
            tz = rng.uniform(4.0, 80.0)
            tx = x_curb + side * rng.uniform(1.1, 1.6)
            r = rng.uniform(1.3, 2.4)
            h = rng.uniform(2.4, 3.4)
            b.cylinder(TRUNK, tx, tz, rng.uniform(0.12, 0.2), (g - h - 0.5 * r, g - curb),
                       (0.33, 0.24, 0.16))
            green = np.array([0.22, 0.36, 0.12]) * rng.uniform(0.8, 1.2, 3)
            b.sphere(FOLIAGE, (tx, g - h - 0.7 * r, tz), r, np.clip(green, 0, 1))

    # Ground plane (road material) last: index n-1.
    b.add(PLANE, ROAD, (-1e6, g, -1e6), (1e6, g, 1e6), (0.33, 0.33, 0.34))

    kind, mat, lo, hi, albedo, style = zip(*b.rows)
    sun_el = math.radians(rng.uniform(35.0, 65.0))
    sun_az = math.radians(rng.uniform(-160.0, 160.0))
    sun = np.array([math.cos(sun_el) * math.sin(sun_az), -math.sin(sun_el),
                    math.cos(sun_el) * math.cos(sun_az)])
    road = {"line_r": x_line_r, "line_l": x_line_l, "dividers": np.array(dividers),
            "dash_phase": rng.uniform(0.0, 9.0)}
    return World(
        kind=np.array(kind, dtype=np.int64), mat=np.array(mat, dtype=np.uint8),
        lo=np.array(lo, dtype=np.float64), hi=np.array(hi, dtype=np.float64),
        albedo=np.array(albedo, dtype=np.float64), style=np.array(style, dtype=np.float64),
        ground_y=g, road=road, sun=sun,
        noise=rng.random((256, 256), dtype=np.float32),
    )


def road_markings(world: World, x: np.ndarray, z: np.ndarray) -> np.ndarray:
    """Boolean mask of lane markings at ground points (x, z), metres."""
    road = world.road
    half = 0.075
    m = (np.abs(x - road["line_r"]) < half) | (np.abs(x - road["line_l"]) < half)
    dashed = np.mod(z + road["dash_phase"], 9.0) < 3.0
    for xd in road["dividers"]:
        m |= (np.abs(x - xd) < half) & dashed
    return m
