"""File formats crfdepth reads and writes (KITTI: :mod:`crfdepth.io.kitti`)."""

from crfdepth.io.kitti import (
    Calibration,
    load_calibration,
    read_depth_png,
    read_intrinsics,
    read_object_calibration,
    read_raw_calibration,
    read_rgb,
    read_velodyne,
    write_depth_png,
)

__all__ = [
    "Calibration",
    "load_calibration",
    "read_depth_png",
    "read_intrinsics",
    "read_object_calibration",
    "read_raw_calibration",
    "read_rgb",
    "read_velodyne",
    "write_depth_png",
]
