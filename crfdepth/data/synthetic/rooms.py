"""Synthetic indoor rooms at NYU Depth v2's protocol size, for learning indoor weights (docs/design.md section 17).

:func:`make_room` draws a room as axis-aligned boxes and renders it by ray casting from NYU's camera, at the
protocol's 304 x 228 (320 x 240 centre-cropped):

- **the room**: floor, ceiling and four walls (2.4-3 m high, 2-6 m wide, 2.5-7 m deep), the camera 1-1.6 m
  above the floor, pitched down up to 17 degrees and turned up to 29 degrees either way;
- **furniture**: 2-6 boxes standing on the floor (cupboards, beds, sofas), some against a wall; three in
  ten are tables, a thin top on four thin legs;
- **colour edges that are not depth edges**: pictures and doors on the back wall and a rug on the floor,
  2 cm or 1 cm proud. Without them every colour edge would be a depth edge and learning would trust colour
  more than real rooms allow;
- **the image**: each surface's colour with low-frequency texture, floor boards, Lambertian shading from one
  light under the ceiling with distance fall-off, and sensor noise;
- **the depth**: camera z-depth in metres, quantised as a Kinect's disparity is (steps of z^2 / 348 m: 4.6 cm
  at 4 m), dense (the protocol's target: NYU's filled depth).

The sample's ``sparse`` is its whole depth (as :func:`crfdepth.data.nyu.layouts.build_nyu_dataset` gives with
``protocol=True``): draw the input with :class:`crfdepth.data.sampling.SparseSamples`. All randomness comes
from ``numpy.random.default_rng(seed)``.
"""

from __future__ import annotations

import numpy as np
import torch
import torch.nn.functional as F

from crfdepth.data.nyu.camera import nyu_intrinsics
from crfdepth.data.sample import Sample
from crfdepth.data.synthetic._checks import check_int

__all__ = ["KINECT_DISPARITY_SCALE", "ROOM_SIZE", "make_room"]

ROOM_SIZE = (228, 304)
"""(height, width) of a room's frame: NYU's protocol, 320 x 240 centre-cropped to 304 x 228."""
KINECT_DISPARITY_SCALE = 348.0
"""``f b / step`` of the quantised depth, metres: focal 580 px x baseline 7.5 cm x 1/8 px disparity steps."""
_FLOOR, _CEILING, _WALL = -1, -2, -3  # what a ray hits when it hits no box


def _rotation(pitch: float, yaw: float) -> np.ndarray:
    """World <- camera rotation: pitch about x (positive looks down), then yaw about y."""
    cp, sp, cy, sy = np.cos(pitch), np.sin(pitch), np.cos(yaw), np.sin(yaw)
    return np.array([[cy, 0, sy], [0, 1, 0], [-sy, 0, cy]]) @ np.array([[1, 0, 0], [0, cp, -sp], [0, sp, cp]])


def _furniture(rng: np.random.Generator, lo: np.ndarray, hi: np.ndarray, floor: float) -> list:
    """``(lo, hi, colour)`` boxes: furniture, tables, pictures and a rug."""
    boxes = []
    for _ in range(int(rng.integers(2, 7))):
        w, d, h = rng.uniform(0.3, 2.0), rng.uniform(0.3, 1.2), rng.uniform(0.3, 2.0)
        x = lo[0] if rng.random() < 0.2 else hi[0] - w if rng.random() < 0.25 else rng.uniform(lo[0], hi[0] - w)
        z = rng.uniform(1.0, hi[2] - d) if hi[2] - d > 1.0 else hi[2] - d
        colour = rng.uniform(0.1, 0.9, 3) * rng.uniform(0.5, 1.0)
        if rng.random() < 0.3:  # a table: a 4 cm top 0.65-0.8 m high on four 5 cm legs
            top = floor - rng.uniform(0.65, 0.8)
            boxes.append(((x, top, z), (x + w, top + 0.04, z + d), colour))
            boxes += [((lx, top + 0.04, lz), (lx + 0.05, floor, lz + 0.05), 0.8 * colour)
                      for lx in (x, x + w - 0.05) for lz in (z, z + d - 0.05)]
        else:
            boxes.append(((x, floor - h, z), (x + w, floor, z + d), colour))
    for _ in range(int(rng.integers(0, 4))):  # pictures and doors on the back wall
        w, h = rng.uniform(0.3, 1.2), rng.uniform(0.3, 1.5)
        x, y = rng.uniform(lo[0], hi[0] - w), rng.uniform(lo[1] + 0.3, floor - h - 0.1)
        boxes.append(((x, y, hi[2] - 0.02), (x + w, y + h, hi[2]), rng.uniform(0.0, 1.0, 3)))
    if rng.random() < 0.6:  # a rug
        w, d = rng.uniform(1.0, 2.5), rng.uniform(1.0, 2.5)
        x, z = rng.uniform(lo[0], hi[0] - w), rng.uniform(0.5, max(0.6, hi[2] - d))
        boxes.append(((x, floor - 0.01, z), (x + w, floor, z + d), rng.uniform(0.1, 0.8, 3)))
    return [(np.array(a, float), np.array(b, float), np.clip(c, 0.0, 1.0)) for a, b, c in boxes]


def _face_normals(d: np.ndarray, axis: np.ndarray) -> np.ndarray:
    """(H, W, 3) unit normals of the faces hit across ``axis`` by rays ``d``, facing the rays."""
    normal = np.zeros_like(d)
    side = -np.sign(np.take_along_axis(d, axis[..., None], -1))
    np.put_along_axis(normal, axis[..., None], side, -1)
    return normal


def make_room(seed: int = 0) -> Sample:
    """One synthetic room at NYU's protocol size (module docstring); the same seed gives the same sample.

    Returns:
        A :class:`~crfdepth.data.sample.Sample` named ``room-seed<seed>``: ``image`` (3, 228, 304) in [0, 1],
        ``target`` and ``sparse`` (1, 228, 304) the quantised depth in metres (every pixel valid), ``K``
        NYU's camera at that size.

    Raises:
        InputError: ``seed`` is not an integer >= 0.
    """
    check_int("seed", seed, 0, None)
    rng = np.random.default_rng(int(seed))
    h, w = ROOM_SIZE
    K = nyu_intrinsics(320, 240).clone()
    K[0, 2] -= (320 - w) / 2
    K[1, 2] -= (240 - h) / 2
    floor, height = rng.uniform(1.0, 1.6), rng.uniform(2.4, 3.0)
    lo = np.array([-rng.uniform(1.0, 3.0), floor - height, -rng.uniform(0.3, 1.5)])
    hi = np.array([rng.uniform(1.0, 3.0), floor, rng.uniform(2.5, 7.0)])
    boxes = _furniture(rng, lo, hi, floor)
    R = _rotation(rng.uniform(-0.3, 0.05), rng.uniform(-0.5, 0.5))

    # Camera rays (z = 1 in the camera: the distance along a ray is the z-depth), turned into the room.
    k = K.double().numpy()
    u, v = np.meshgrid(np.arange(w), np.arange(h))
    d = np.stack([(u - k[0, 2]) / k[0, 0], (v - k[1, 2]) / k[1, 1], np.ones((h, w))], -1) @ R.T
    d = np.where(np.abs(d) < 1e-9, 1e-9, d)
    exits = np.where(d > 0, hi / d, lo / d)  # the room's six planes, from inside
    t, axis = exits.min(-1), exits.argmin(-1)
    hit = np.where(axis != 1, _WALL, np.where(np.take_along_axis(d, axis[..., None], -1)[..., 0] > 0, _FLOOR,
                                              _CEILING))
    normal = _face_normals(d, axis)
    for i, (b0, b1, _) in enumerate(boxes):  # slabs: the nearest box in front of the room's planes
        t0, t1 = b0 / d, b1 / d
        near, far = np.minimum(t0, t1), np.maximum(t0, t1)
        enter, leave, across = near.max(-1), far.min(-1), near.argmax(-1)
        front = (enter < leave) & (enter > 0) & (enter < t)
        t, hit = np.where(front, enter, t), np.where(front, i, hit)
        normal = np.where(front[..., None], _face_normals(d, across), normal)
    points = d * t[..., None]

    colour = np.empty((h, w, 3))
    colour[hit == _WALL] = rng.uniform(0.55, 0.9) * np.array([1.0, rng.uniform(0.9, 1.0), rng.uniform(0.8, 1.0)])
    colour[hit == _FLOOR] = rng.uniform(0.2, 0.6, 3) * np.array([1.0, 0.8, 0.6])
    colour[hit == _CEILING] = 0.9
    for i, (_, _, c) in enumerate(boxes):
        colour[hit == i] = c
    coarse = torch.from_numpy(rng.random((1, 1, 9, 9)))
    texture = F.interpolate(coarse, size=(64, 64), mode="bicubic", align_corners=True)[0, 0].numpy()
    at = (np.abs(points[..., 0] * 7 + points[..., 2] * 5) % 64).astype(int), \
        (np.abs(points[..., 1] * 7 + points[..., 2] * 3) % 64).astype(int)
    colour *= (0.85 + 0.3 * texture[at])[..., None]
    boards = (hit == _FLOOR) & (np.sin(points[..., 0] * rng.uniform(10.0, 30.0)) > 0.7)
    colour[boards] *= 0.85
    light = np.array([rng.uniform(lo[0], hi[0]), lo[1] + 0.2, rng.uniform(1.0, hi[2])])
    to_light = light - points
    distance = np.linalg.norm(to_light, axis=-1)
    lambert = np.clip((normal * to_light).sum(-1) / distance, 0.0, None) / (1.0 + 0.08 * distance ** 2)
    image = colour * (0.3 + 0.9 * lambert)[..., None] * rng.uniform(0.7, 1.2)
    image = np.clip(image + rng.normal(0.0, 0.01, image.shape), 0.0, 1.0)

    depth = np.clip(t, 0.1, 10.0)
    depth = KINECT_DISPARITY_SCALE / np.maximum(np.round(KINECT_DISPARITY_SCALE / depth), 1.0)
    target = torch.from_numpy(depth.astype(np.float32))[None]
    return Sample(image=torch.from_numpy(image.transpose(2, 0, 1).astype(np.float32)), sparse=target.clone(),
                  target=target, K=K, name=f"room-seed{int(seed)}")
