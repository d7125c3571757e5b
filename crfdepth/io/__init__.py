"""File formats crfdepth reads and writes (docs/design.md section 8).

KITTI data files: :mod:`crfdepth.io.kitti`; depth images of RGB-D cameras (16-bit PNGs of
millimetres, metres or KITTI codes, checked): :mod:`crfdepth.io.depth_image`; calibration of KITTI and of any rig:
:mod:`crfdepth.io.calibration` (KITTI's ``key: values`` text: :mod:`crfdepth.io.key_values`);
point clouds: :mod:`crfdepth.io.pointcloud`; safe output paths and atomic writes:
:mod:`crfdepth.io.files`.
"""

from typing import TYPE_CHECKING

from crfdepth.lazy import lazy_names

if TYPE_CHECKING:
    from crfdepth.io.calibration import (
        Calibration,
        RigCalibration,
        load_any_calibration,
        load_calibration,
        read_object_calibration,
        read_raw_calibration,
        read_rig_calibration,
    )
    from crfdepth.io.depth_image import DEPTH_UNITS, check_depth_matches_image, check_depth_units, read_depth_image
    from crfdepth.io.kitti import read_depth_png, read_intrinsics, read_rgb, read_velodyne, write_depth_png
    from crfdepth.io.pointcloud import read_points, write_pcd, write_ply

# Where each name lives, imported at its first use (PEP 562): writing a file (crfdepth.io.files) does not import
# the point-cloud readers (pypcd4, 70 ms) and every format.
_LAZY = {
    **dict.fromkeys(["Calibration", "RigCalibration", "load_any_calibration", "load_calibration",
                     "read_object_calibration", "read_raw_calibration", "read_rig_calibration"], "crfdepth.io.calibration"),
    **dict.fromkeys(["DEPTH_UNITS", "check_depth_matches_image", "check_depth_units", "read_depth_image"],
                    "crfdepth.io.depth_image"),
    **dict.fromkeys(["read_depth_png", "read_intrinsics", "read_rgb", "read_velodyne", "write_depth_png"],
                    "crfdepth.io.kitti"),
    **dict.fromkeys(["read_points", "write_pcd", "write_ply"], "crfdepth.io.pointcloud"),
}


__getattr__, __dir__ = lazy_names(__name__, _LAZY)


__all__ = [
    "DEPTH_UNITS",
    "Calibration",
    "RigCalibration",
    "check_depth_matches_image",
    "check_depth_units",
    "load_any_calibration",
    "load_calibration",
    "read_depth_image",
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
