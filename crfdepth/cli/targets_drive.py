"""``crfdepth targets --drive``: camera-view depth targets from a KITTI raw drive (docs/design.md section 14).

For each frame of a drive folder (``<day>/<drive>_sync`` with ``velodyne_points/data/*.bin`` and
``image_0X/data/*.png``; the calibration is the day folder's ``calib_cam_to_cam.txt`` and ``calib_velo_to_cam.txt``) the
scans ``t - k .. t + k`` are registered with the drive's poses and accumulated into the frame's camera by
:func:`crfdepth.sequences.targets.camera_view_targets`, which keeps only the returns the camera sees (movers and
occluded returns dropped, the frame's own scan first).

Poses (``--poses``): ``auto`` (the drive's ``oxts/data`` GPS/IMU when present, else LiDAR odometry), ``odometry``
(KISS-ICP over the scans the run uses, every step checked, the registration too
(:func:`crfdepth.sequences.registration.step_alignment`); when the registration slid it is retried without the ground
(:func:`crfdepth.sequences.odometry.lidar_odometry_with_fallback`); a failed step is an error naming the frame, never
accumulated), ``oxts``, or a KITTI odometry ``poses.txt`` (one camera-0 pose per frame of the drive, in frame order).

Written under ``--out-dir OUT`` in KITTI's depth-completion layout:

- ``OUT/<drive>/proj_depth/groundtruth/image_0X/<frame>.png``: the targets, KITTI depth PNG
  (uint16, metres * 256, 0 = no target);
- ``OUT/<drive>/proj_depth/support/image_0X/<frame>.png``: per pixel, how many scans of the window agree with the target
  (uint8 PNG; uint16 when the window holds more than 255 scans);
- ``OUT/<drive>/poses.txt``: the poses used, KITTI odometry format (rectified camera-0 poses ``[R | t]``, 12 numbers a
  line, relative to the first scan used), one line per scan the run used in frame order (frames ``index_image_0X.csv``
  names in ``first_scan`` / ``last_scan``); a run over the whole drive writes one line per frame, so the file can be
  given back as ``--poses``;
- ``OUT/<drive>/index_image_0X.csv``: one row per frame (see :data:`INDEX_COLUMNS`);
- with ``--vis [DIR]``: ``DIR/<drive>_image_0X_<frame>.png``, the targets coloured by depth and the dropped returns by
  reason (:func:`crfdepth.pictures.figures.targets_picture`);
- with ``--rerun FILE.rrd``: a Rerun recording, one time step per frame: the camera at its pose, its trajectory,
  the image, the frame's scan and its targets (:mod:`crfdepth.pictures.rerun_recording`).

Everything is checked before anything is written (the drive's files, frame numbers, the calibration, every scan used,
the poses, the odometry, the output folder). Frame numbers must be consecutive: a gap is refused, naming the first one,
unless ``--frames A:B`` selects a gap-free range (its windows then stop at the gap). A drive of one frame is refused
(accumulation needs neighbouring scans).
"""

from __future__ import annotations

import argparse
import csv
import dataclasses
import importlib.util
import io
import logging
import os
import re
import sys
import time
from pathlib import Path

import cv2
import numpy as np
from tqdm import tqdm

from crfdepth.cli.arguments import BAD_INPUT
from crfdepth.cli.decoder_noise import quiet_decoders
from crfdepth.cli.file_errors import flagged
from crfdepth.cli.outputs import check_output_folders, output_folders, write_rgb_png
from crfdepth.data.kitti.raw_scans import remove_stereo_contradicted
from crfdepth.errors import InputError
from crfdepth.io.calibration import load_any_calibration
from crfdepth.io.files import atomic_write_bytes
from crfdepth.io.kitti import read_rgb, read_velodyne, write_depth_png
from crfdepth.pictures.figures import targets_picture
from crfdepth.sequences import odometry
from crfdepth.sequences.poses import read_imu_to_velo, read_kitti_poses, read_oxts
from crfdepth.sequences.stereo import baseline_from_projections
from crfdepth.sequences.targets import MOVED, OCCLUDED, OUTSIDE, camera_view_targets

logger = logging.getLogger(__name__)

__all__ = ["INDEX_COLUMNS", "kiss_installed", "run_drive", "select_frames"]

# Columns of OUT/<drive>/index_image_0X.csv, one row per frame written.
INDEX_COLUMNS = (
    "frame",          # the frame's number (file stem)
    "first_scan",     # the window's first and last frame (cut at the ends of the drive or a gap)
    "last_scan",
    "points",         # returns of the window that land in the image
    "target_pixels",  # pixels with a target
    "density",        # target_pixels / pixels of the image
    "scan_density",   # share of pixels the frame's own scan alone covers (every return in the image)
    "own_share",      # share of the target pixels whose target is from the frame's own scan
    "occluded",       # returns dropped as occluded (rule a)
    "moved",          # returns dropped as moved (rule b)
    "stereo_dropped",  # target pixels the stereo pair contradicts, dropped (--stereo-check; empty without it)
)
_STEM = re.compile(r"^\d+$")


# --------------------------------------------------------------------------- the drive


def _frame_files(folder: Path, suffix: str, what: str, drive_flag: str, cam: str) -> dict[int, Path]:
    """``{frame number: file}`` of ``folder/data/*<suffix>``."""
    data = folder / "data"
    if not data.is_dir():
        raise InputError(f"{drive_flag}: expected a KITTI raw drive folder with velodyne_points/data/*.bin and "
                         f"{cam}/data/*.png, got no {folder.name}/data")
    found = {}
    for path in sorted(data.glob(f"*{suffix}")):
        if not _STEM.match(path.stem):
            raise InputError(f"{drive_flag}: expected {what} named by frame number (0000000000{suffix}), got "
                             f"{path.name}")
        found[int(path.stem)] = path
    if not found:
        raise InputError(f"{drive_flag}: expected {what} in {data}, got none")
    return found


def _stem(frame: int, width: int) -> str:
    return f"{frame:0{width}d}"


def _drive_frames(args) -> tuple[Path, list[int], dict[int, Path], dict[int, Path], int]:
    """The drive folder, its frames (sorted), scan and image files by frame, the width of the stems."""
    flag = f"--drive {args.drive}"
    drive = Path(args.drive)
    if not drive.is_dir():
        raise FileNotFoundError(f"--drive: no such directory: {drive}")
    cam = f"image_0{args.camera}"
    scans = _frame_files(drive / "velodyne_points", ".bin", "scans", flag, cam)
    images = _frame_files(drive / cam, ".png", "images", flag, cam)
    no_image = sorted(set(scans) - set(images))
    no_scan = sorted(set(images) - set(scans))
    width = len(next(iter(scans.values())).stem)
    for missing, have, lacks in ((no_scan, "image", "scan"), (no_image, "scan", "image")):
        if missing:
            folder = "velodyne_points/data" if lacks == "scan" else f"{cam}/data"
            raise InputError(f"{flag}: expected a scan and an image for every frame, got {len(missing)} "
                             f"{have}(s) without a {lacks} (the first: frame {_stem(missing[0], width)}, missing in "
                             f"{folder})")
    frames = sorted(scans)
    return drive, frames, scans, images, width


def select_frames(args, frames: list[int], width: int, flag: str) -> tuple[list[int], list[int]]:
    """The frames to write and the scans the run uses (the selected frames +- k, within the run of
    consecutive frame numbers holding them), both as frame numbers; ``flag`` names the input."""
    if len(frames) < 2:
        raise InputError(f"{flag}: expected at least 2 frames (accumulation needs neighbouring scans), got 1 "
                         f"(frame {_stem(frames[0], width)})")
    if args.frames is None:
        gaps = [i for i in range(1, len(frames)) if frames[i] != frames[i - 1] + 1]
        if gaps:
            i = gaps[0]
            raise InputError(f"{flag}: expected consecutive frame numbers, got a gap after frame "
                             f"{_stem(frames[i - 1], width)} (next: {_stem(frames[i], width)}; {len(gaps)} gap(s)); "
                             f"give --frames A:B for a gap-free range")
        chosen = frames
    else:
        first, last = args.frames
        present = set(frames)
        text = f"--frames {first}:{last}"
        if first < frames[0] or last > frames[-1]:
            raise InputError(f"{text}: expected frames within the drive's {frames[0]} to {frames[-1]}, got "
                             f"{first} to {last}")
        missing = [f for f in range(first, last + 1) if f not in present]
        if missing:
            raise InputError(f"{text}: expected a gap-free range, got frame {_stem(missing[0], width)} missing "
                             f"({len(missing)} of {last - first + 1})")
        chosen = list(range(first, last + 1))
    # the run of consecutive frames around the selection, then +- k
    position = {f: i for i, f in enumerate(frames)}
    lo = position[chosen[0]]
    while lo > 0 and frames[lo - 1] == frames[lo] - 1 and frames[lo - 1] >= chosen[0] - args.window:
        lo -= 1
    hi = position[chosen[-1]]
    while hi + 1 < len(frames) and frames[hi + 1] == frames[hi] + 1 and frames[hi + 1] <= chosen[-1] + args.window:
        hi += 1
    used = frames[lo:hi + 1]
    if len(used) < 2 and args.window > 0:
        raise InputError(f"--frames {args.frames[0]}:{args.frames[1]}: expected a frame with neighbouring scans "
                         f"(accumulation needs them), got frame {_stem(chosen[0], width)} alone between gaps")
    return chosen, used


def _read_scans(used: list[int], files: dict[int, Path], width: int) -> list[np.ndarray]:
    scans = []
    for f in used:
        with flagged("--drive", files[f], labels=("velodyne",)):
            scan = read_velodyne(files[f])
        if len(scan) == 0:
            raise InputError(f"--drive: expected a scan with at least one return, got an empty scan in {files[f]} "
                             f"(frame {_stem(f, width)})")
        scans.append(scan)
    return scans


def _image_size(path: Path) -> tuple[int, int]:
    with quiet_decoders():  # a damaged PNG: the message below, not libpng's
        image = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if image is None or image.dtype != np.uint8 or image.ndim != 3:
        raise InputError(f"--drive: expected an 8-bit colour PNG, got a file that does not read as one: {path}")
    return image.shape[:2]


# --------------------------------------------------------------------------- poses


def kiss_installed() -> bool:
    try:
        return importlib.util.find_spec("kiss_icp") is not None
    except (ImportError, ValueError):  # a module set to None (tests) or without a spec
        return False


def _poses(args, drive: Path, frames: list[int], used: list[int], scans: list[np.ndarray], calib,
           width: int) -> tuple[np.ndarray, str]:
    """``T_lidar(first used)<-lidar(t)`` of every used scan, and how they were obtained."""
    mode = args.poses
    oxts = drive / "oxts" / "data"
    if mode == "auto":
        mode = "oxts" if oxts.is_dir() else "odometry"
    positions = [frames.index(f) for f in used]
    if mode == "odometry":
        if not kiss_installed():
            why = "the drive has no oxts/data, and " if args.poses == "auto" else ""
            raise InputError(f"--poses {args.poses}: {why}LiDAR odometry needs the kiss-icp package, not installed; "
                             f"{odometry.EXTRA_HINT}, or give --poses FILE")
        odo, note = odometry.lidar_odometry_with_fallback(scans)
        if odo.failures:
            listed = "; ".join(f"frame {_stem(used[k], width)}: {why}" for k, why in odo.failures[:5])
            more = f"; and {len(odo.failures) - 5} more" if len(odo.failures) > 5 else ""
            raise InputError(f"--poses {args.poses}: expected LiDAR odometry without failures, got "
                             f"{len(odo.failures)} failed step(s) ({listed}{more}); nothing written; choose "
                             f"--frames that avoid them or give --poses FILE")
        frames_used = f"over frames {_stem(used[0], width)}-{_stem(used[-1], width)}"
        return odo.poses, f"LiDAR odometry (KISS-ICP{'; ' + note if note else ''}) {frames_used}"
    if mode == "oxts":
        if not oxts.is_dir():
            raise InputError(f"--poses oxts: expected the drive's oxts/data folder, got no {oxts}")
        try:
            T_velo_imu = read_imu_to_velo(drive.parent)
            poses = read_oxts(oxts.parent, T_velo_imu)
        except (InputError, FileNotFoundError) as exc:
            raise type(exc)(f"--poses {args.poses}: {exc}") from None
        if len(poses) != len(frames):
            raise InputError(f"--poses {args.poses}: expected {len(frames)} oxts packets (one per frame) in {oxts}, "
                             f"got {len(poses)}")
        source = "oxts (GPS/IMU)"
    else:
        if calib.kitti is None:  # pragma: no cover - the day folder is always a KITTI calibration
            raise InputError(f"--poses {mode}: expected a KITTI calibration to read camera-0 poses with")
        try:
            poses = read_kitti_poses(mode, calib.kitti.velo_to_rect_cam())
        except (InputError, FileNotFoundError, PermissionError, IsADirectoryError) as exc:
            raise type(exc)(f"--poses {mode}: {str(exc).removeprefix('poses: ')}") from None
        if len(poses) != len(frames):
            raise InputError(f"--poses {mode}: expected {len(frames)} poses (one per frame of the drive, in frame "
                             f"order), got {len(poses)}")
        source = f"poses file {mode}"
    chosen = poses[positions]
    first_inv = np.linalg.inv(chosen[0])
    return np.stack([first_inv @ P for P in chosen]), source


def _poses_text(lidar_poses: np.ndarray, T_cam0_lidar: np.ndarray) -> str:
    """KITTI odometry poses.txt of the rectified camera-0 poses ``Tr L(t) Tr^-1``."""
    inv = np.linalg.inv(T_cam0_lidar)
    lines = []
    for L in lidar_poses:
        P = T_cam0_lidar @ L @ inv
        lines.append(" ".join(f"{v:.9e}" for v in P[:3, :].ravel()))
    return "\n".join(lines) + "\n"


# --------------------------------------------------------------------------- writing


def _write_support(path: Path, support: np.ndarray, wide: bool) -> None:
    codes = support.astype(np.uint16 if wide else np.uint8)
    ok, encoded = cv2.imencode(".png", codes)
    if not ok:  # pragma: no cover
        raise InputError(f"support: could not encode an array of shape {codes.shape} as PNG")
    atomic_write_bytes(path, encoded.tobytes())


def _scan_density(scan: np.ndarray, T_cam_lidar: np.ndarray, K: np.ndarray, size: tuple[int, int]) -> float:
    """Share of the image's pixels that the scan's returns land in (rounded projection, as the targets)."""
    height, width = size
    cam = scan[:, :3].astype(np.float64) @ T_cam_lidar[:3, :3].T + T_cam_lidar[:3, 3]
    z = cam[:, 2]
    front = z > 0.1
    z = np.where(front, z, 1.0)
    u = np.rint(K[0, 0] * cam[:, 0] / z + K[0, 2]).astype(np.int64)
    v = np.rint(K[1, 1] * cam[:, 1] / z + K[1, 2]).astype(np.int64)
    inside = front & (u >= 0) & (u < width) & (v >= 0) & (v < height)
    return float(len(np.unique(v[inside] * width + u[inside]))) / (height * width)


def _stereo_pair(args, drive: Path, chosen: list[int], width: int, calib) -> tuple[dict[int, Path], float]:
    """``--stereo-check``: the other colour camera's image of every chosen frame and the pair's baseline (metres)."""
    other = 5 - args.camera
    folder = drive / f"image_0{other}" / "data"
    if not folder.is_dir():
        raise InputError(f"--stereo-check: expected the other colour camera's folder {folder} beside "
                         f"image_0{args.camera} (a stereo check needs both cameras), got no such folder")
    images = {f: folder / f"{_stem(f, width)}.png" for f in chosen}
    if missing := [path for path in images.values() if not path.is_file()]:
        raise InputError(f"--stereo-check: expected an image of camera {other} for every frame, got {len(missing)} "
                         f"missing (the first: {missing[0]})")
    return images, baseline_from_projections(calib.kitti.P_rect, load_any_calibration(drive.parent, other).kitti.P_rect)


def _inside(path: Path, folder: Path) -> bool:
    path, folder = Path(os.path.realpath(path)), Path(os.path.realpath(folder))
    return path == folder or folder in path.parents


def run_drive(args: argparse.Namespace) -> int:
    """Write the targets of the drive ``--drive`` as ``args`` asks; returns 0 (see the module docstring)."""
    start = time.perf_counter()
    drive, frames, scan_files, image_files, width = _drive_frames(args)
    for flag, value in (("--out-dir", args.out_dir), ("--vis", args.vis or None)):
        if value is not None and _inside(Path(value), drive):
            raise InputError(f"{flag}: {value} is inside the input drive {drive}; refusing to write there")
    outputs = check_output_folders(args, [drive], f"the input drive {drive}")
    chosen, used = select_frames(args, frames, width, f"--drive {args.drive}")
    calib = load_any_calibration(drive.parent, args.camera)
    other = _stereo_pair(args, drive, chosen, width, calib) if args.stereo_check else None
    scans = _read_scans(used, scan_files, width)
    sizes = {f: _image_size(image_files[f]) for f in chosen}
    poses, source = _poses(args, drive, frames, used, scans, calib, width)

    cam = f"image_0{args.camera}"
    name = drive.name
    wide = 2 * args.window + 1 > 255
    rows: list[dict] = []
    progress = tqdm(total=len(chosen), unit="frame", desc="targets", disable=args.quiet or not sys.stderr.isatty())
    with output_folders(outputs) as folders:
        out = folders[0] / name
        depth_dir = out / "proj_depth" / "groundtruth" / cam
        support_dir = out / "proj_depth" / "support" / cam
        vis_dir = folders[2] if args.vis is not None else None
        written = 0
        try:
            for directory in (depth_dir, support_dir):
                directory.mkdir(parents=True, exist_ok=True)
            atomic_write_bytes(out / "poses.txt", _poses_text(poses, calib.kitti.velo_to_rect_cam()).encode())
            for frame in chosen:
                index = used.index(frame)
                size = sizes[frame]
                targets = camera_view_targets(scans, poses, calib.T_cam_lidar, calib.K, size, index, k=args.window)
                stem = _stem(frame, width)
                dropped = ""
                if other is not None:
                    kept = remove_stereo_contradicted(targets.depth.astype(np.float32), read_rgb(image_files[frame]),
                                                      read_rgb(other[0][frame]), calib.K, other[1])
                    dropped = int(np.count_nonzero((targets.depth > 0) & (kept == 0)))
                    targets = dataclasses.replace(targets, depth=kept, support=np.where(kept > 0, targets.support, 0))
                write_depth_png(depth_dir / f"{stem}.png", targets.depth)
                _write_support(support_dir / f"{stem}.png", targets.support, wide)
                if args.recorder is not None:  # --rerun
                    args.recorder.targets_frame(read_rgb(image_files[frame]), targets.depth, scan=scans[index],
                                                calibration=calib, pose=poses[index])
                if vis_dir is not None:
                    with quiet_decoders():
                        image = cv2.imread(str(image_files[frame]), cv2.IMREAD_COLOR)
                    image = cv2.cvtColor(image, cv2.COLOR_BGR2RGB)
                    # the legend names the window by frame numbers, not by positions in the scans used
                    shown = dataclasses.replace(targets, window=tuple(used[i] for i in targets.window))
                    write_rgb_png(vis_dir / f"{name}_{cam}_{stem}.png", targets_picture(image, shown), "--vis")
                codes = np.concatenate(targets.point_reason)
                has = targets.depth > 0
                pixels = int(has.sum())
                rows.append({
                    "frame": stem, "first_scan": _stem(used[targets.window[0]], width),
                    "last_scan": _stem(used[targets.window[-1]], width),
                    "points": int(np.sum(codes != OUTSIDE)), "target_pixels": pixels,
                    "density": f"{targets.density:.6f}",
                    "scan_density": f"{_scan_density(scans[index], calib.T_cam_lidar, calib.K, size):.6f}",
                    "own_share": f"{(targets.own & has).sum() / max(pixels, 1):.6f}",
                    "occluded": int(np.sum(codes == OCCLUDED)), "moved": int(np.sum(codes == MOVED)),
                    "stereo_dropped": dropped,
                })
                written += 1
                progress.update(1)
        except BAD_INPUT as exc:  # after the checks: a file changed or vanished during the run
            where = _stem(chosen[written], width) if written < len(chosen) else "the end"
            raise type(exc)(f"{exc} [stopped at frame {where}; {written} of {len(chosen)} frame(s) written to "
                            f"{out}]") from None
        except KeyboardInterrupt:
            raise KeyboardInterrupt(f"after {written} of {len(chosen)} frame(s) written to {out}") from None
        finally:
            progress.close()
            if rows:  # the index lists exactly the frames written
                text = io.StringIO()
                writer = csv.DictWriter(text, fieldnames=INDEX_COLUMNS, lineterminator="\n")
                writer.writeheader()
                writer.writerows(rows)
                atomic_write_bytes(out / f"index_{cam}.csv", text.getvalue().encode())
    seconds = time.perf_counter() - start
    if not args.quiet:
        density = float(np.mean([float(r["density"]) for r in rows]))
        single = float(np.mean([float(r["scan_density"]) for r in rows]))
        ratio = f" ({density / single:.2f}x)" if single > 0 else ""
        print(f"wrote targets of {written} frame(s) of {name} ({cam}, k={args.window}, poses: {source}) to {out}: "
              f"mean density {density:.4f} against {single:.4f} for the single scan{ratio}, in {seconds:.1f} s")
    return 0
