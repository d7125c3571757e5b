"""LiDAR points to a sparse camera depth map (paper Sec. 3.1, DESIGN.md section 1)."""

from __future__ import annotations

import numpy as np


def project_to_depth(points_cam: np.ndarray, P: np.ndarray, image_size: tuple[int, int]) -> np.ndarray:
    """Z-buffer projection of camera-frame points into a sparse depth map.

    Args:
        points_cam: (N, 3) points in the (rectified) camera frame, metres, z forward.
        P: (3, 4) projection matrix of the target camera (KITTI ``P_rect_0X``); a (3, 3)
            K is accepted and treated as ``[K | 0]``.
        image_size: (height, width) of the image, pixels.

    Returns:
        (H, W) float32 sparse depth: camera z-depth in metres of the nearest point that
        lands in each pixel (pixel = rounded projection), 0 where no point lands. Points
        with z <= 0 (behind the camera) are dropped. The stored value is the z of the
        point in the frame of ``P``'s camera, i.e. ``(P @ [x, y, z, 1])[2]``.
    """
    height, width = image_size
    P = np.asarray(P, dtype=np.float64)
    if P.shape == (3, 3):
        P = np.concatenate([P, np.zeros((3, 1))], axis=1)
    pts = np.asarray(points_cam, dtype=np.float64)[:, :3]
    uvw = pts @ P[:, :3].T + P[:, 3]
    z = uvw[:, 2]
    front = z > 0
    uvw, z = uvw[front], z[front]
    u = np.round(uvw[:, 0] / z).astype(np.int64)
    v = np.round(uvw[:, 1] / z).astype(np.int64)
    inside = (u >= 0) & (u < width) & (v >= 0) & (v < height)
    u, v, z = u[inside], v[inside], z[inside]
    # Nearest point wins: sort by (pixel, z) and keep the first entry of each pixel.
    flat = v * width + u
    order = np.lexsort((z, flat))
    flat, z = flat[order], z[order]
    first = np.ones(flat.shape[0], dtype=bool)
    first[1:] = flat[1:] != flat[:-1]
    depth = np.zeros(height * width, dtype=np.float32)
    depth[flat[first]] = z[first]
    return depth.reshape(height, width)
