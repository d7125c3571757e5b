"""Camera-view depth targets of a recording, written as files: :func:`make_targets` (docs/design.md section 14).

A KITTI raw drive (``drive``, :mod:`crfdepth.sequences.drive_targets`) or a ROS bag (``bag``, first written as a
KITTI raw drive ``OUT/<date>/<bag name>_sync``, :mod:`crfdepth.sequences.bag_drive`): each frame's targets are the
scans ``t - k .. t + k`` registered with the recording's poses (:mod:`crfdepth.sequences.pose_source`) and
accumulated into its camera, keeping only the returns the camera sees; they are written in KITTI's
depth-completion layout with a per-pixel support count, the poses used and an index CSV. ``crfdepth targets`` is
this function on the command line; its messages name the options as that command spells them (``--poses``,
``--frames``), or the argument of this function where the command cannot give a bad one (``window``).
"""

from __future__ import annotations

import os
from collections.abc import Callable
from pathlib import Path

import numpy as np

from crfdepth.checks import check_number
from crfdepth.errors import InputError
from crfdepth.sequences.bag_drive import write_bag_targets
from crfdepth.sequences.drive_targets import DriveTargets, write_drive_targets
from crfdepth.sequences.targets import Targets

__all__ = ["DriveTargets", "check_targets_options", "make_targets"]

_BAG_OPTIONS = ("image_topic", "points_topic", "camera_info_topic", "calib", "max_dt")


def _inside(path: Path, folder: Path) -> bool:
    path, folder = Path(os.path.realpath(path)), Path(os.path.realpath(folder))
    return path == folder or folder in path.parents


def check_targets_options(out_dir: str | Path, *, drive: str | Path | None = None, bag: str | Path | None = None,
                          camera: int = 2, frames: tuple[int, int] | None = None, window: int = 5,
                          poses: str | Path = "auto", stereo_check: bool = False, vis_dir: str | Path | None = None,
                          **bag_options) -> None:
    """Refuse (``InputError``) the options of :func:`make_targets` that cannot work together, before anything is
    read: ``bag_options`` are its ``image_topic``, ``points_topic``, ``camera_info_topic``, ``calib`` and
    ``max_dt``. Files are not read here."""
    if camera not in (2, 3):
        raise InputError(f"camera: expected 2 or 3 (a colour camera of KITTI's rig), got {camera!r}")
    check_number("window", window, low=0, low_open=False, integer=True)
    if frames is not None and not (len(frames) == 2 and all(isinstance(f, int) and f >= 0 for f in frames)
                                   and frames[0] <= frames[1]):
        raise InputError(f"frames: expected (A, B), two frame numbers with 0 <= A <= B (both included), got "
                         f"{frames!r}")
    if not isinstance(poses, (str, os.PathLike)):
        raise InputError(f"poses: expected auto, tf, odometry, oxts or a poses file, got {type(poses).__name__}")
    if unknown := sorted(set(bag_options) - set(_BAG_OPTIONS)):
        raise TypeError(f"check_targets_options() got unexpected keyword argument(s): {', '.join(unknown)}")
    if bag_options.get("max_dt") is not None:
        check_number("max_dt", bag_options["max_dt"], low=0)
    if (drive is None) == (bag is None):
        raise InputError(f"--drive / --bag: expected one of them (a KITTI raw drive folder or a ROS bag), got "
                         f"{'neither' if drive is None else 'both'}")
    if bag is not None and stereo_check:
        raise InputError("--stereo-check: expected a KITTI raw drive with both colour cameras (--drive), got a "
                         "bag (one camera)")
    if bag is None:
        stray = [f"--{name.replace('_', '-')}" for name in _BAG_OPTIONS if bag_options.get(name) is not None]
        if stray:
            raise InputError(f"{', '.join(stray)}: cannot be combined with --drive (options of --bag)")
        if poses == "tf":
            raise InputError("--poses tf: expected auto, odometry, oxts or a poses file with --drive, got tf (the "
                             "odometry on a bag's /tf, for --bag)")
        for flag, value in (("--out-dir", out_dir), ("--vis", vis_dir)):
            if value is not None and _inside(Path(value), Path(drive)):
                raise InputError(f"{flag}: {value} is inside the input drive {Path(drive)}; refusing to write there")
    elif camera != 2:
        raise InputError(f"--camera {camera}: cannot be combined with --bag (a bag's camera is written as "
                         f"image_02)")


def make_targets(out_dir: str | Path, *, drive: str | Path | None = None, bag: str | Path | None = None,
                 camera: int = 2, frames: tuple[int, int] | None = None, window: int = 5, poses: str = "auto",
                 stereo_check: bool = False, vis_dir: str | Path | None = None,
                 picture: Callable[[np.ndarray, Targets], np.ndarray] | None = None,
                 image_topic: str | None = None, points_topic: str | None = None,
                 camera_info_topic: str | None = None, calib: str | Path | None = None, max_dt: float | None = None,
                 recorder=None, progress: Callable[[int, int], None] | None = None) -> DriveTargets:
    """Write the camera-view depth targets of a KITTI raw drive or a ROS bag under ``out_dir`` (OUT).

    Written: ``OUT/<drive>/proj_depth/groundtruth/image_0X/<frame>.png`` (KITTI depth PNG, metres * 256,
    0 = no target), ``OUT/<drive>/proj_depth/support/image_0X/<frame>.png`` (how many scans agree),
    ``OUT/<drive>/poses.txt`` and ``OUT/<drive>/index_image_0X.csv``
    (:data:`crfdepth.sequences.drive_targets.INDEX_COLUMNS`); with ``bag`` also the bag's frames as the KITTI raw
    drive ``OUT/<date>/<bag name>_sync``, so that layout ``"sequence"`` reads OUT as both root and targets_root.
    Everything is checked before anything is written.

    Args:
        out_dir: the output folder (created if missing).
        drive: a KITTI raw drive folder (``<day>/<drive>_sync``; the calibration is read from the day folder).
        bag: a ROS 1 or ROS 2 recording (needs ``pip install 'crfdepth[ros]'``); give ``drive`` or ``bag``.
        camera: the drive's colour camera, 2 (left) or 3; a bag's camera is written as camera 2.
        frames: ``(A, B)``: only frames A to B, both included (the windows still use the scans around them);
            None: every frame, whose numbers must then be consecutive.
        window: ``k``, the scans on each side of a frame to accumulate (>= 0; 0: the frame's own scan, cleaned of
            what the camera cannot see).
        poses: ``auto``, ``tf`` (a bag), ``odometry`` (KISS-ICP, ``pip install "crfdepth[odometry]"``), ``oxts``
            (a drive) or a KITTI odometry poses.txt (:mod:`crfdepth.sequences.pose_source`).
        stereo_check: a drive with both colour cameras: drop the target returns the stereo pair contradicts
            (:func:`crfdepth.sequences.stereo.remove_stereo_contradicted`).
        vis_dir: also write a picture per frame here, ``<drive>_image_0X_<frame>.png``, drawn by ``picture``.
        picture: ``picture(image, targets)``: (H, W, 3) uint8 RGB image and its :class:`Targets` (``window`` as
            frame numbers) to an (h, w, 3) uint8 RGB picture, e.g. :func:`crfdepth.pictures.figures.targets_picture`;
            needed with ``vis_dir``.
        image_topic, points_topic, camera_info_topic, calib, max_dt: a bag's topics (None: the bag's only one of
            its type; the CameraInfo beside the images), a calibration file replacing the CameraInfo and /tf, and
            the largest time between an image and its cloud (seconds, > 0;
            :data:`crfdepth.io.ros.frames.DEFAULT_MAX_DT_S`).
        recorder: an object whose ``targets_frame(image, depth, scan=, calibration=, pose=)`` is called with each
            frame written (the command's ``--rerun``: :class:`crfdepth.pictures.rerun_recording.Recorder`).
        progress: ``progress(written, total)``, called before a drive's first frame and after each one.

    Returns:
        :class:`DriveTargets`: the drive read (with ``bag``: the drive written), the folder of the targets, the
        frames written, the pose source and the mean densities of the targets and of the frames' own scans.

    Raises:
        InputError: bad options or input, named (also FileNotFoundError, PermissionError for files).
    """
    options = {"image_topic": image_topic, "points_topic": points_topic, "camera_info_topic": camera_info_topic,
               "calib": calib, "max_dt": max_dt}
    check_targets_options(out_dir, drive=drive, bag=bag, camera=camera, frames=frames, window=window, poses=poses,
                          stereo_check=stereo_check, vis_dir=vis_dir, **options)
    if vis_dir is not None and picture is None:
        raise InputError("picture: expected a function drawing a frame's picture for vis_dir (such as "
                         "crfdepth.pictures.figures.targets_picture), got None")
    frames = None if frames is None else (int(frames[0]), int(frames[1]))
    if bag is not None:
        return write_bag_targets(bag, out_dir, frames=frames, window=window, poses=str(poses), vis_dir=vis_dir,
                                 picture=picture, recorder=recorder, **options)
    return write_drive_targets(drive, out_dir, camera=camera, frames=frames, window=window, poses=str(poses),
                               stereo_check=stereo_check, vis_dir=vis_dir, picture=picture, recorder=recorder,
                               progress=progress)
