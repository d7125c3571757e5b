"""A synthetic drive (:func:`crfdepth.data.synthetic.make_sequence`) written in KITTI's raw layout.

Shared by the ``crfdepth targets`` tests (tests/cli/test_targets_cli.py), the sequence dataset's
tests (tests/data/test_sequences.py), the photometric training tests
(tests/train/test_photometric_training.py) and the raw drive's completion tests
(tests/data/kitti/test_drive.py, tests/cli/test_complete_drive.py).
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

DRIVE = "2011_01_01_drive_0001_sync"
DAY = "2011_01_01"


def stem(i: int) -> str:
    """KITTI's 10-digit frame stem."""
    return f"{i:010d}"


def matrix_text(a) -> str:
    return " ".join(f"{v:.12e}" for v in np.asarray(a, dtype=np.float64).ravel())


def write_drive(root: Path, seq, frames=None) -> Path:
    """``root/<day>/<drive>_sync`` with the sequence's scans (float32 N x 4, intensity 0) and images, the
    day's calibration (P_rect_02 = [K | 0], R_rect_00 = I, velo_to_cam = T_cam_lidar) and ``poses.txt``
    (the true camera poses, KITTI odometry format) beside the day folder. Returns the drive folder."""
    day = root / DAY
    drive = day / DRIVE
    (drive / "velodyne_points" / "data").mkdir(parents=True)
    (drive / "image_02" / "data").mkdir(parents=True)
    frame = seq[0]
    height, width = frame.image.shape[:2]
    P = np.hstack([frame.K, np.zeros((3, 1))])
    (day / "calib_cam_to_cam.txt").write_text(
        f"S_rect_02: {width} {height}\nP_rect_02: {matrix_text(P)}\nR_rect_00: {matrix_text(np.eye(3))}\n")
    T = frame.T_cam_lidar
    (day / "calib_velo_to_cam.txt").write_text(f"R: {matrix_text(T[:3, :3])}\nT: {matrix_text(T[:3, 3])}\n")
    for i in (range(len(seq)) if frames is None else frames):
        f = seq[i]
        points = np.zeros((len(f.points), 4), np.float32)
        points[:, :3] = f.points[:, :3]
        points.tofile(drive / "velodyne_points" / "data" / f"{stem(i)}.bin")
        rgb = np.round(np.clip(f.image, 0, 1) * 255).astype(np.uint8)
        cv2.imwrite(str(drive / "image_02" / "data" / f"{stem(i)}.png"), cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR))
    lines = [matrix_text(f.T_w_cam[:3, :]) for f in seq]
    (root / "poses.txt").write_text("\n".join(lines) + "\n")
    return drive


def poses_file(drive: Path) -> Path:
    """The true poses written by :func:`write_drive` (beside the day folder)."""
    return drive.parent.parent / "poses.txt"


def make_targets(drive: Path, out: Path, k: int = 2) -> Path:
    """Run ``crfdepth targets --drive drive --poses <true poses> -k k --out-dir out --quiet``; returns ``out``."""
    from crfdepth.cli import main

    code = main(["targets", "--drive", str(drive), "--poses", str(poses_file(drive)), "-k", str(k),
                 "--out-dir", str(out), "--quiet"])
    assert code == 0
    return out
