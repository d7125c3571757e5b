"""Synthetic frames written as a KITTI ``val_selection_cropped`` folder, so that the folder commands
(``crfdepth complete --input-dir``, ``crfdepth evaluate --layout val_selection``) can be tried, tested
and measured without KITTI: :func:`write_selection_folder`."""

from __future__ import annotations

from collections.abc import Iterable
from os import PathLike
from pathlib import Path

import cv2
import numpy as np

from crfdepth.data.synthetic.scene import SyntheticScene
from crfdepth.io.kitti import write_depth_png

__all__ = ["DRIVE", "selection_stem", "write_selection_folder"]

DRIVE = "2011_09_26_drive_0001_sync"  # the drive the frames are named after


def selection_stem(kind: str, index: int, drive: str = DRIVE) -> str:
    """The file stem KITTI gives frame ``index`` in ``kind`` ("image", "velodyne_raw", "groundtruth_depth")."""
    return f"{drive}_{kind}_{index:010d}_image_02"


def write_selection_folder(root: str | PathLike, scenes: Iterable[SyntheticScene], drive: str = DRIVE) -> Path:
    """``scenes`` written in order as frames 0, 1, ... of a ``val_selection_cropped`` folder at ``root``
    (created with ``image/``, ``velodyne_raw/``, ``groundtruth_depth/`` and ``intrinsics/``): the RGB as an
    8-bit PNG, the LiDAR and the ground truth (:meth:`SyntheticScene.target`) as KITTI depth PNGs, K as 9
    numbers. Returns ``root``."""
    root = Path(root)
    for sub in ("image", "velodyne_raw", "groundtruth_depth", "intrinsics"):
        (root / sub).mkdir(parents=True, exist_ok=True)
    for index, scene in enumerate(scenes):
        rgb = np.round(scene.image * 255).astype(np.uint8)
        cv2.imwrite(str(root / "image" / f"{selection_stem('image', index, drive)}.png"),
                    cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR))
        write_depth_png(root / "velodyne_raw" / f"{selection_stem('velodyne_raw', index, drive)}.png", scene.sparse)
        write_depth_png(root / "groundtruth_depth" / f"{selection_stem('groundtruth_depth', index, drive)}.png",
                        scene.target())
        np.savetxt(root / "intrinsics" / f"{selection_stem('image', index, drive)}.txt", scene.K.reshape(1, 9))
    return root
