"""Rigid-transform maths shared by every pose source and the ROS transform tree (docs/design.md section 12).

Transforms are (4, 4) float64 ``[R | t]`` matrices, metres, ``p_a = T_a<-b @ p_b``.

- :func:`invert_rigid`: ``[R^T | -R^T t]``, exact for a rigid transform (no general inverse).
- :func:`camera_relative_pose`: the camera's motion through the fixed LiDAR -> camera extrinsic.
- :func:`rotation_deg`, :func:`axis_rotation`: a rotation's angle, and a rotation about one axis.
"""

from __future__ import annotations

import math

import numpy as np

from crfdepth.checks import check_rigid

__all__ = ["axis_rotation", "camera_relative_pose", "invert_rigid", "rotation_deg"]


def invert_rigid(T: np.ndarray) -> np.ndarray:
    """(4, 4) float64 inverse of a rigid (4, 4) transform: ``[R^T | -R^T t]``."""
    inv = np.eye(4)
    inv[:3, :3] = T[:3, :3].T
    inv[:3, 3] = -T[:3, :3].T @ T[:3, 3]
    return inv


def rotation_deg(R: np.ndarray) -> float:
    """Angle of a rotation matrix, degrees."""
    c = (np.trace(R) - 1.0) / 2.0
    return math.degrees(math.acos(min(1.0, max(-1.0, c))))


def camera_relative_pose(T_w_lidar_s, T_w_lidar_t, T_cam_lidar) -> np.ndarray:
    """``T_cam(s)<-cam(t) = T_cam_lidar T_lidar(s)<-lidar(t) T_cam_lidar^-1`` (docs/design.md section 3c).

    Args:
        T_w_lidar_s, T_w_lidar_t: (4, 4) world<-LiDAR poses at times s and t.
        T_cam_lidar: (4, 4) LiDAR-to-camera extrinsic (rigidly mounted).

    Returns:
        (4, 4) float64: maps points of camera frame t into camera frame s.
    """
    T_cam_lidar = check_rigid(T_cam_lidar, "T_cam_lidar")
    s = check_rigid(T_w_lidar_s, "T_w_lidar_s")
    t = check_rigid(T_w_lidar_t, "T_w_lidar_t")
    return T_cam_lidar @ invert_rigid(s) @ t @ invert_rigid(T_cam_lidar)


def axis_rotation(axis: int, a: float) -> np.ndarray:
    """(3, 3) rotation by ``a`` radians about axis 0, 1 or 2 (x, y, z)."""
    c, s = math.cos(a), math.sin(a)
    i, j = [(1, 2), (2, 0), (0, 1)][axis]
    R = np.eye(3)
    R[i, i], R[i, j], R[j, i], R[j, j] = c, -s, s, c
    return R
