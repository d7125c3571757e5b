"""Camera-view depth targets of a KITTI raw drive, written in KITTI's depth-completion layout (docs/design.md
section 14).

For each frame of a drive folder (``<day>/<drive>_sync`` with ``velodyne_points/data/*.bin`` and
``image_0X/data/*.png``; the calibration is the day folder's ``calib_cam_to_cam.txt`` and ``calib_velo_to_cam.txt``) the
scans ``t - k .. t + k`` are registered with the drive's poses (:func:`crfdepth.sequences.pose_source.drive_poses`)
and accumulated into the frame's camera by :func:`crfdepth.sequences.targets.camera_view_targets`, which keeps only
the returns the camera sees (movers and occluded returns dropped, the frame's own scan first).

:func:`write_drive_targets` writes under ``out_dir`` (OUT):

- ``OUT/<drive>/proj_depth/groundtruth/image_0X/<frame>.png``: the targets, KITTI depth PNG
  (uint16, metres * 256, 0 = no target);
- ``OUT/<drive>/proj_depth/support/image_0X/<frame>.png``: per pixel, how many scans of the window agree with the target
  (uint8 PNG; uint16 when the window holds more than 255 scans);
- ``OUT/<drive>/poses.txt``: the poses used, KITTI odometry format (rectified camera-0 poses ``[R | t]``, 12 numbers a
  line, relative to the first scan used), one line per scan the run used in frame order (frames ``index_image_0X.csv``
  names in ``first_scan`` / ``last_scan``); a run over the whole drive writes one line per frame, so the file can be
  given back as ``poses``;
- ``OUT/<drive>/index_image_0X.csv``: one row per frame (see :data:`INDEX_COLUMNS`);
- with ``vis_dir``: ``vis_dir/<drive>_image_0X_<frame>.png``, the picture ``picture`` draws of the targets (the
  command's: :func:`crfdepth.pictures.figures.targets_picture`, dropped returns coloured by reason);
- with ``recorder`` (the command's ``--rerun``): each frame handed to ``recorder.targets_frame``.

Everything is checked before anything is written (the drive's files, frame numbers, the calibration, every scan used,
the poses, the odometry). Frame numbers must be consecutive: a gap is refused, naming the first one, unless ``frames``
(A, B) selects a gap-free range (its windows then stop at the gap). A drive of one frame is refused (accumulation needs
neighbouring scans). Errors name the options as ``crfdepth targets`` spells them (``--drive``, ``--frames``).
"""

from __future__ import annotations

import csv
import dataclasses
import io
import re
import time
from collections.abc import Callable
from pathlib import Path

import cv2
import numpy as np

from crfdepth.errors import BAD_INPUT, InputError
from crfdepth.io.calibration import load_any_calibration
from crfdepth.io.decoder_noise import quiet_decoders
from crfdepth.io.file_errors import flagged
from crfdepth.io.files import atomic_write_bytes
from crfdepth.io.kitti import read_rgb, read_velodyne, write_depth_png
from crfdepth.sequences.pose_source import drive_poses
from crfdepth.sequences.stereo import baseline_from_projections, remove_stereo_contradicted
from crfdepth.sequences.targets import MOVED, OCCLUDED, OUTSIDE, Targets, camera_view_targets

__all__ = ["INDEX_COLUMNS", "DriveTargets", "select_frames", "write_drive_targets"]


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


def _drive_frames(path: str | Path, camera: int) -> tuple[Path, list[int], dict[int, Path], dict[int, Path], int]:
    """The drive folder, its frames (sorted), scan and image files by frame, the width of the stems."""
    flag = f"--drive {path}"
    drive = Path(path)
    if not drive.is_dir():
        raise FileNotFoundError(f"--drive: no such directory: {drive}")
    cam = f"image_0{camera}"
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


def select_frames(selection: tuple[int, int] | None, window: int, frames: list[int], width: int,
                  flag: str) -> tuple[list[int], list[int]]:
    """The frames to write (``selection``: frames A to B, both included; None: every one of ``frames``, which
    must then be consecutive) and the scans the run uses (the selected frames +- ``window``, within the run of
    consecutive frame numbers holding them), both as frame numbers; ``flag`` names the input."""
    if len(frames) < 2:
        raise InputError(f"{flag}: expected at least 2 frames (accumulation needs neighbouring scans), got 1 "
                         f"(frame {_stem(frames[0], width)})")
    if selection is None:
        gaps = [i for i in range(1, len(frames)) if frames[i] != frames[i - 1] + 1]
        if gaps:
            i = gaps[0]
            raise InputError(f"{flag}: expected consecutive frame numbers, got a gap after frame "
                             f"{_stem(frames[i - 1], width)} (next: {_stem(frames[i], width)}; {len(gaps)} gap(s)); "
                             f"give --frames A:B for a gap-free range")
        chosen = frames
    else:
        first, last = selection
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
    while lo > 0 and frames[lo - 1] == frames[lo] - 1 and frames[lo - 1] >= chosen[0] - window:
        lo -= 1
    hi = position[chosen[-1]]
    while hi + 1 < len(frames) and frames[hi + 1] == frames[hi] + 1 and frames[hi + 1] <= chosen[-1] + window:
        hi += 1
    used = frames[lo:hi + 1]
    if len(used) < 2 and window > 0:
        raise InputError(f"--frames {selection[0]}:{selection[1]}: expected a frame with neighbouring scans "
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


# --------------------------------------------------------------------------- writing


def _poses_text(lidar_poses: np.ndarray, T_cam0_lidar: np.ndarray) -> str:
    """KITTI odometry poses.txt of the rectified camera-0 poses ``Tr L(t) Tr^-1``."""
    inv = np.linalg.inv(T_cam0_lidar)
    lines = []
    for L in lidar_poses:
        P = T_cam0_lidar @ L @ inv
        lines.append(" ".join(f"{v:.9e}" for v in P[:3, :].ravel()))
    return "\n".join(lines) + "\n"


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


def _stereo_pair(camera: int, drive: Path, chosen: list[int], width: int, calib) -> tuple[dict[int, Path], float]:
    """``--stereo-check``: the other colour camera's image of every chosen frame and the pair's baseline (metres)."""
    other = 5 - camera
    folder = drive / f"image_0{other}" / "data"
    if not folder.is_dir():
        raise InputError(f"--stereo-check: expected the other colour camera's folder {folder} beside "
                         f"image_0{camera} (a stereo check needs both cameras), got no such folder")
    images = {f: folder / f"{_stem(f, width)}.png" for f in chosen}
    if missing := [path for path in images.values() if not path.is_file()]:
        raise InputError(f"--stereo-check: expected an image of camera {other} for every frame, got {len(missing)} "
                         f"missing (the first: {missing[0]})")
    return images, baseline_from_projections(calib.kitti.P_rect, load_any_calibration(drive.parent, other).kitti.P_rect)


@dataclasses.dataclass(frozen=True)
class DriveTargets:
    """What :func:`write_drive_targets` wrote."""

    drive: Path          # the drive folder read
    out: Path            # OUT/<drive>: the targets, poses.txt and the index
    camera: str          # image_02 or image_03
    frames: int          # frames written
    source: str          # how the poses were obtained
    density: float       # mean share of pixels with a target, over the frames written
    scan_density: float  # mean share of pixels the frame's own scan covers
    seconds: float       # wall time of the run


def _write_picture(path: Path, rgb: np.ndarray) -> None:
    """An (H, W, 3) uint8 RGB picture as PNG, atomically; errors name ``--vis``."""
    ok, encoded = cv2.imencode(".png", cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR))
    if not ok:  # pragma: no cover - cv2 encodes any uint8 array of 3 channels
        raise InputError(f"--vis: could not encode an array of shape {rgb.shape} {rgb.dtype} as PNG for {path}")
    with flagged("--vis", path, "write"):
        atomic_write_bytes(path, encoded.tobytes())


def write_drive_targets(drive: str | Path, out_dir: str | Path, *, camera: int = 2,
                        frames: tuple[int, int] | None = None, window: int = 5, poses: str = "auto",
                        stereo_check: bool = False, vis_dir: str | Path | None = None,
                        picture: Callable[[np.ndarray, Targets], np.ndarray] | None = None, recorder=None,
                        progress: Callable[[int, int], None] | None = None) -> DriveTargets:
    """Write the targets of the KITTI raw drive ``drive`` under ``out_dir`` (see the module docstring).

    The arguments are those of :func:`crfdepth.sequences.make_targets`, which checks them; ``progress(written,
    total)`` is called before the first frame and after each one.
    """
    start = time.perf_counter()
    given = drive
    drive, numbers, scan_files, image_files, width = _drive_frames(given, camera)
    chosen, used = select_frames(frames, window, numbers, width, f"--drive {given}")
    calib = load_any_calibration(drive.parent, camera)
    other = _stereo_pair(camera, drive, chosen, width, calib) if stereo_check else None
    scans = _read_scans(used, scan_files, width)
    sizes = {f: _image_size(image_files[f]) for f in chosen}
    lidar_poses, source = drive_poses(poses, drive, numbers, used, scans, calib, width)

    cam = f"image_0{camera}"
    name = drive.name
    wide = 2 * window + 1 > 255
    rows: list[dict] = []
    out = Path(out_dir) / name
    depth_dir = out / "proj_depth" / "groundtruth" / cam
    support_dir = out / "proj_depth" / "support" / cam
    vis = None if vis_dir is None else Path(vis_dir)
    if vis is not None:
        vis.mkdir(parents=True, exist_ok=True)
    written = 0
    try:
        for directory in (depth_dir, support_dir):
            directory.mkdir(parents=True, exist_ok=True)
        atomic_write_bytes(out / "poses.txt", _poses_text(lidar_poses, calib.kitti.velo_to_rect_cam()).encode())
        if progress is not None:
            progress(0, len(chosen))
        for frame in chosen:
            index = used.index(frame)
            size = sizes[frame]
            targets = camera_view_targets(scans, lidar_poses, calib.T_cam_lidar, calib.K, size, index, k=window)
            stem = _stem(frame, width)
            dropped = ""
            if other is not None:
                kept = remove_stereo_contradicted(targets.depth.astype(np.float32), read_rgb(image_files[frame]),
                                                  read_rgb(other[0][frame]), calib.K, other[1])
                dropped = int(np.count_nonzero((targets.depth > 0) & (kept == 0)))
                targets = dataclasses.replace(targets, depth=kept, support=np.where(kept > 0, targets.support, 0))
            write_depth_png(depth_dir / f"{stem}.png", targets.depth)
            _write_support(support_dir / f"{stem}.png", targets.support, wide)
            if recorder is not None:  # --rerun
                recorder.targets_frame(read_rgb(image_files[frame]), targets.depth, scan=scans[index],
                                       calibration=calib, pose=lidar_poses[index])
            if vis is not None:
                with quiet_decoders():
                    image = cv2.imread(str(image_files[frame]), cv2.IMREAD_COLOR)
                image = cv2.cvtColor(image, cv2.COLOR_BGR2RGB)
                # the legend names the window by frame numbers, not by positions in the scans used
                shown = dataclasses.replace(targets, window=tuple(used[i] for i in targets.window))
                _write_picture(vis / f"{name}_{cam}_{stem}.png", picture(image, shown))
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
            if progress is not None:
                progress(written, len(chosen))
    except BAD_INPUT as exc:  # after the checks: a file changed or vanished during the run
        where = _stem(chosen[written], width) if written < len(chosen) else "the end"
        raise type(exc)(f"{exc} [stopped at frame {where}; {written} of {len(chosen)} frame(s) written to "
                        f"{out}]") from None
    except KeyboardInterrupt:
        raise KeyboardInterrupt(f"after {written} of {len(chosen)} frame(s) written to {out}") from None
    finally:
        if rows:  # the index lists exactly the frames written
            text = io.StringIO()
            writer = csv.DictWriter(text, fieldnames=INDEX_COLUMNS, lineterminator="\n")
            writer.writeheader()
            writer.writerows(rows)
            atomic_write_bytes(out / f"index_{cam}.csv", text.getvalue().encode())
    return DriveTargets(drive=drive, out=out, camera=cam, frames=written, source=source,
                        density=float(np.mean([float(r["density"]) for r in rows])),
                        scan_density=float(np.mean([float(r["scan_density"]) for r in rows])),
                        seconds=time.perf_counter() - start)
