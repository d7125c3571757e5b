"""Free space along a LiDAR scan's rays: which points a scan sees *through* (docs/design.md
section 14, rule b of the camera-view targets).

A scan's range image (nearest range per azimuth x elevation bin, in its own LiDAR frame)
says how far each beam reached. A point that two beams of the scan, just above and below
its direction, both pass well beyond lies in space that was empty when the scan was taken:
at another time, something that has since moved was there.

Pure numpy.
"""

from __future__ import annotations

import math

import numpy as np

__all__ = ["range_image", "seen_through"]


def range_image(xyz: np.ndarray, az_step: float, el_step: float):
    """Nearest range per (elevation, azimuth) bin of a scan in its own LiDAR frame, with the
    bins' geometry. Empty bins hold +inf."""
    r = np.linalg.norm(xyz, axis=1)
    ok = r > 1e-6
    xyz, r = xyz[ok], r[ok]
    az = np.arctan2(xyz[:, 1], xyz[:, 0])
    el = np.arcsin(np.clip(xyz[:, 2] / r, -1.0, 1.0))
    n_az = max(1, math.ceil(2.0 * math.pi / az_step))
    el0 = float(el.min()) - el_step
    n_el = math.floor((float(el.max()) - el0) / el_step) + 2
    ia = np.floor((az + math.pi) / az_step).astype(np.int64) % n_az
    ie = np.floor((el - el0) / el_step).astype(np.int64)
    image = np.full((n_el, n_az), np.inf)
    np.minimum.at(image, (ie, ia), r)
    return image, el0, n_el, n_az


def seen_through(query: np.ndarray, own_scan: np.ndarray, *, az_step: float, el_step: float,
                  beam_gap: float, free_rel: float, free_m: float) -> np.ndarray:
    """(M,) bool: the own scan sees through each query point (both in the own LiDAR frame).

    In the own scan's range image (nearest range per bin, then the nearest over +-1
    azimuth bin), the query's direction is bracketed by the nearest beams above and below
    it (the nearest non-empty elevation rows, each within ``beam_gap`` radians). The query
    is seen through when both exist and both lie beyond ``r (1 + free_rel) + free_m``.
    Directions without a return (sky, out of range, dropouts) are no evidence either way.
    Asking both bracketing beams keeps a ground or wall point between two beams (the beam
    below hits the ground nearer) and a point just beside a static edge.
    """
    image, el0, n_el, n_az = range_image(own_scan, az_step, el_step)
    padded = np.pad(image, ((0, 0), (1, 1)), mode="wrap")
    nearest = np.minimum(np.minimum(padded[:, :-2], padded[:, 1:-1]), padded[:, 2:])
    rows = np.arange(n_el)[:, None]
    present = np.isfinite(nearest)
    below = np.maximum.accumulate(np.where(present, rows, -n_el - 1), axis=0)
    above = np.minimum.accumulate(np.where(present, rows, 2 * n_el + 1)[::-1], axis=0)[::-1]
    r = np.linalg.norm(query, axis=1)
    az = np.arctan2(query[:, 1], query[:, 0])
    el = np.arcsin(np.clip(query[:, 2] / np.maximum(r, 1e-9), -1.0, 1.0))
    ia = np.floor((az + math.pi) / az_step).astype(np.int64) % n_az
    ie = np.floor((el - el0) / el_step).astype(np.int64)
    inside = (ie >= 0) & (ie < n_el)
    ie, ia, r_in = ie[inside], ia[inside], r[inside]
    gap = math.floor(beam_gap / el_step)
    lo, hi = below[ie, ia], above[ie, ia]
    found = (ie - lo <= gap) & (hi - ie <= gap)
    limit = r_in * (1.0 + free_rel) + free_m
    lo_r = nearest[np.clip(lo, 0, n_el - 1), ia]
    hi_r = nearest[np.clip(hi, 0, n_el - 1), ia]
    beyond = np.zeros(len(query), dtype=bool)
    beyond[inside] = found & (lo_r > limit) & (hi_r > limit)
    return beyond
