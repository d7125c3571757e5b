"""Lens distortion coefficients of a calibration, checked as a camera could have them (docs/design.md section 1).

A raw image with lens distortion is undistorted before anything else
(``cv2.undistort(image, K, distortion)``, new camera matrix ``K``): each pixel ``(u, v)`` of
the undistorted image is filled from the raw image at ``K distort(K^-1 [u v 1])``, OpenCV's
distortion model (k1 k2 p1 p2 [k3 [k4 k5 k6 [s1 s2 s3 s4 [tx ty]]]]). :func:`check_distortion`
refuses coefficients no lens has, by mapping a ``DISTORTION_GRID`` x ``DISTORTION_GRID``
(64 x 64) grid of the image's pixels so (``cv2.projectPoints``, all 14 coefficients):

- fewer than ``MIN_IN_VIEW`` (half) of them inside the raw image: most of the image would
  be black (coefficients of another camera or image size, or mistyped; a real lens keeps
  every pixel: KITTI's four cameras, a wide-angle plumb-bob lens and an Azure Kinect's
  rational model keep 100%);
- the mapping folds (the Jacobian's determinant, from the grid's cells, is not positive or
  not finite) in a cell that lands inside the raw image: two parts of the undistorted image
  would show the same raw pixels (a polynomial used beyond the radius it was fitted on).
"""

from __future__ import annotations

import numpy as np

from crfdepth.errors import InputError
from crfdepth.io.key_values import quote_value

__all__ = ["DISTORTION_GRID", "DISTORTION_LENGTHS", "MIN_IN_VIEW", "check_distortion"]

DISTORTION_LENGTHS = (4, 5, 8, 12, 14)
"""The numbers of distortion coefficients OpenCV accepts (k1 k2 p1 p2 [k3 [k4 k5 k6 [s1 s2 s3 s4 [tx ty]]]])."""
DISTORTION_GRID = 64  # grid points along each image axis
MIN_IN_VIEW = 0.5  # share of the grid that must land inside the raw image


def check_distortion(value: object, K: np.ndarray, image_size: tuple[int, int] | None,
                     what: str = "distortion") -> np.ndarray:
    """(D,) float64 copy of the OpenCV coefficients ``value`` after the checks of the module docstring.

    Args:
        value: D numbers, D in ``DISTORTION_LENGTHS``, finite.
        K: (3, 3) checked intrinsics of the undistorted image, pixels
            (:func:`crfdepth.intrinsics.check_intrinsics`).
        image_size: (height, width) in pixels; None: the image centred on the principal point
            (``2 cy`` x ``2 cx``), the grid test skipped when that is under 2 pixels.
        what: the user's name of the coefficients (``distortion``, ``distortion (rig.yaml)``).

    Raises:
        InputError: not numbers, a count OpenCV does not know, NaN/inf, most of the image out of
            view, or a fold (the message quotes the coefficients).
    """
    try:
        array = np.array(value, dtype=np.float64).ravel()
    except (TypeError, ValueError, OverflowError):
        raise InputError(f"{what}: expected a list of numbers (OpenCV k1 k2 p1 p2 [k3 ...]), got "
                         f"{quote_value(value)}") from None
    if array.size not in DISTORTION_LENGTHS or not np.all(np.isfinite(array)):
        got = array.tolist() if array.size <= max(DISTORTION_LENGTHS) else f"{array.size} numbers"
        raise InputError(f"{what}: expected {', '.join(map(str, DISTORTION_LENGTHS))} finite numbers (OpenCV "
                         f"k1 k2 p1 p2 [k3 [k4 k5 k6 [s1 s2 s3 s4 [tx ty]]]]), got {got}")
    if image_size is None:
        image_size = (int(round(2 * K[1, 2])), int(round(2 * K[0, 2])))
        if min(image_size) < 2:
            return array
    inside, folded, radius = _grid_mapping(K, array, image_size)
    height, width = image_size
    coefficients = " ".join(f"{c:g}" for c in array)
    if inside.mean() < MIN_IN_VIEW:
        raise InputError(f"{what}: expected distortion coefficients that keep the {width}x{height} (WxH) image in view "
                         f"(at least {MIN_IN_VIEW:.0%} of its pixels mapped inside the raw image), got {coefficients}, "
                         f"which map {1 - inside.mean():.0%} of them outside: coefficients of another camera or image "
                         f"size, or mistyped?")
    if folded.any():
        raise InputError(f"{what}: expected distortion coefficients whose mapping does not fold over the "
                         f"{width}x{height} (WxH) image, got {coefficients}, which fold it from a normalised radius of "
                         f"{radius:.3g} ({folded.mean():.0%} of the image): the polynomial is used beyond the radius "
                         f"it was fitted on; coefficients of another camera or image size, or mistyped?")
    return array


def _grid_mapping(K: np.ndarray, distortion: np.ndarray, image_size: tuple[int, int]
                  ) -> tuple[np.ndarray, np.ndarray, float]:
    """Map the grid of the undistorted image into the raw one: (G, G) bool inside the raw image, (G-1, G-1)
    bool folded cells, and the smallest normalised radius ``|K^-1 [u v 1]|`` of a folded cell (inf: none)."""
    import cv2

    height, width = image_size
    u, v = np.meshgrid(np.linspace(0.0, width - 1.0, DISTORTION_GRID), np.linspace(0.0, height - 1.0, DISTORTION_GRID))
    rays = np.linalg.solve(K, np.stack([u.ravel(), v.ravel(), np.ones(u.size)]))  # (3, N), last row 1
    with np.errstate(all="ignore"):
        distorted, _ = cv2.projectPoints(rays.T[:, None, :].copy(), np.zeros(3), np.zeros(3), np.eye(3), distortion)
        xd, yd = distorted.reshape(-1, 2).T
        raw_u = (K[0, 0] * xd + K[0, 1] * yd + K[0, 2]).reshape(u.shape)
        raw_v = (K[1, 1] * yd + K[1, 2]).reshape(u.shape)
        inside = (np.isfinite(raw_u) & np.isfinite(raw_v) & (raw_u >= -0.5) & (raw_u <= width - 0.5)
                  & (raw_v >= -0.5) & (raw_v <= height - 0.5))
        # each cell's Jacobian determinant (u right, v down in both images: positive where nothing folds)
        du_u, du_v = raw_u[:-1, 1:] - raw_u[:-1, :-1], raw_v[:-1, 1:] - raw_v[:-1, :-1]
        dv_u, dv_v = raw_u[1:, :-1] - raw_u[:-1, :-1], raw_v[1:, :-1] - raw_v[:-1, :-1]
        det = du_u * dv_v - du_v * dv_u
    folded = (inside[:-1, :-1] | inside[1:, :-1] | inside[:-1, 1:]) & ~(det > 0)
    norm = np.hypot(rays[0], rays[1]).reshape(u.shape)[:-1, :-1]
    return inside, folded, float(norm[folded].min()) if folded.any() else float("inf")
