"""KITTI's calibration text format: ``key: values`` lines, each value a row of numbers.

Every KITTI calibration file is written this way (a raw-data day's ``calib_cam_to_cam.txt``,
``calib_velo_to_cam.txt`` and ``calib_imu_to_velo.txt``, an object benchmark's
``calib/*.txt``), so the calibration readers (:mod:`crfdepth.io.calibration`, docs/design.md
section 1) and the IMU-to-Velodyne reader of the poses given
(:mod:`crfdepth.sequences.poses`, section 12) share these two functions. A failure is an
:class:`~crfdepth.errors.InputError` naming the file and the key.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from crfdepth.errors import InputError
from crfdepth.io.files import read_text

__all__ = ["entry_array", "read_key_values"]


def read_key_values(path: Path, what: str) -> dict[str, str]:
    """``key: values`` lines of a KITTI calibration file (values kept as text)."""
    entries = {}
    for line in read_text(path, what, "'key: values' lines (a KITTI calibration)").splitlines():
        if line.lstrip().startswith("#"):  # a comment (e.g. of a rig YAML given by mistake)
            continue
        key, sep, value = line.partition(":")
        if sep and key.strip():
            entries[key.strip()] = value.strip()
    if not entries:
        raise InputError(f"{what}: expected 'key: values' lines in {path}, found none")
    return entries


def entry_array(entries: dict[str, str], key: str, shape: tuple[int, ...], path: Path) -> np.ndarray:
    """Entry ``key`` of a calibration file as a float64 array of ``shape``."""
    if key not in entries:
        raise InputError(f"calibration: key '{key}' not found in {path} (keys present: "
                         f"{', '.join(sorted(entries))})")
    try:
        values = np.array([float(token) for token in entries[key].split()], dtype=np.float64)
    except ValueError:
        raise InputError(f"calibration: key '{key}' in {path}: expected numbers, "
                         f"got {entries[key][:60]!r}") from None
    if values.size != int(np.prod(shape)):
        raise InputError(f"calibration: key '{key}' in {path}: expected {int(np.prod(shape))} numbers "
                         f"{shape}, got {values.size}")
    return values.reshape(shape)
