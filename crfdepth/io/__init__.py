"""File formats crfdepth reads and writes (docs/design.md section 8).

KITTI data files: :mod:`crfdepth.io.kitti`; calibration of KITTI and of any rig:
:mod:`crfdepth.io.calibration` (KITTI's ``key: values`` text: :mod:`crfdepth.io.key_values`);
point clouds: :mod:`crfdepth.io.pointcloud`; safe output paths and atomic writes:
:mod:`crfdepth.io.files`.
"""

from crfdepth.io.calibration import (
    Calibration,
    RigCalibration,
    load_any_calibration,
    load_calibration,
    read_object_calibration,
    read_raw_calibration,
    read_rig_calibration,
)
from crfdepth.io.kitti import read_depth_png, read_intrinsics, read_rgb, read_velodyne, write_depth_png
from crfdepth.io.pointcloud import read_points, write_pcd, write_ply

__all__ = [
    "Calibration",
    "RigCalibration",
    "load_any_calibration",
    "load_calibration",
    "read_depth_png",
    "read_intrinsics",
    "read_object_calibration",
    "read_points",
    "read_raw_calibration",
    "read_rgb",
    "read_rig_calibration",
    "read_velodyne",
    "write_depth_png",
    "write_pcd",
    "write_ply",
]
