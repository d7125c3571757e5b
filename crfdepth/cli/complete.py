"""``crfdepth complete``: sparse LiDAR + RGB -> dense depth PNG(s) with :class:`~crfdepth.model.CRFDepth`.

One frame::

    crfdepth complete --image RGB.png --sparse SPARSE.png --intrinsics K.txt \\
        --out DEPTH.png [--out-std STD.png] [--vis [DIR]]

One frame from a raw point cloud and a calibration (instead of --sparse/--intrinsics)::

    crfdepth complete --image RGB.png --points CLOUD --calib CALIB --out DEPTH.png [--camera 2]

``CLOUD`` is a ``.bin`` (KITTI), ``.npy``, ``.ply`` or ``.pcd`` file
(:func:`crfdepth.io.pointcloud.read_points`); ``CALIB`` a rig YAML/JSON file or any KITTI
calibration (:func:`crfdepth.io.calibration.load_any_calibration`; ``--camera`` picks the KITTI
camera). The cloud is projected by :func:`crfdepth.api.points_to_sparse` (KITTI: the
exact KITTI projection) and the image undistorted when the calibration has
``distortion`` (:mod:`crfdepth.api`).

A folder in the ``val_selection_cropped`` or ``test_depth_completion_anonymous`` layout
(``image/``, ``velodyne_raw/``, ``intrinsics/``; docs/design.md section 7)::

    crfdepth complete --input-dir val_selection_cropped --out-dir pred/ [--out-std-dir std/] \\
        [--batch-size B] [--workers N]

Folder mode reads the frames with a ``torch.utils.data.DataLoader``: ``--workers N``
processes (default 0: this process) read, decode and check frames ahead of the model, and
up to ``--batch-size B`` (default 1) consecutive frames of the same size are completed by
one model call (a size change starts a new batch; :func:`crfdepth.cli.common.frame_batches`).
A batch's CG solves run together, each frozen once converged, so depths differ from batch 1
by the solver tolerance only: at most one unit (1/256 m) of the depth PNG, measured on the
two KITTI validation frames and on synthetic frames of two sizes (the std PNG: one unit
plus 0.04% of the std). Output names and the frames written do not depend on B or N. On
CPU, batch 1 was the fastest measured (4 KITTI frames: 0.45 s one by one, 0.57 s as one
batch, pixel mode), so batches are for ``--device cuda``. Workers pay off when reading is
slow (network storage): a KITTI frame reads in about 20 ms.

Outputs (docs/design.md sections 1 and 7): the depth is a KITTI depth PNG of the input's size
(uint16, metres * 256), > 0 at every pixel; the standard deviation is written
the same way (metres * 256). Both are clipped below at 1/256 m, so that no pixel reads
as 0 ("no value"), and the depth above at 65535/256 m by the PNG format. In folder mode
each frame is written as ``<velodyne_raw file name>`` (the KITTI submission naming:
``<drive>_velodyne_raw_<frame>_image_0X.png`` or ``0000000000.png`` ...).

Pictures (``--vis``): ``<stem>_vis_depth.png`` (:func:`crfdepth.pictures.colour.colorize_depth`,
TURBO on inverse depth, near = red) and ``<stem>_vis_std.png``
(:func:`crfdepth.pictures.colour.colorize_std`, VIRIDIS, yellow = uncertain), with ``<stem>``
the stem of ``--out`` (one frame) or the frame name (folder). ``--vis DIR`` writes them
into DIR; a bare ``--vis`` writes them next to ``--out`` (one frame) or into
``<out-dir>_vis`` beside the output folder (folder mode: the submission folder holds only
the depth PNGs). ``--vis`` computes the std map even without ``--out-std``.

Checks before any computation: every output file name ends in ``.png``; the folder of
``--out`` / ``--out-std`` exists and takes new files (a probe file is created and removed,
so ``/proc`` or a read-only mount fails here, naming the flag; it is not created); no
output is an input. Then the inputs are read and checked, naming the file in every message: image and
sparse map of the same size; sparse a 16-bit single-channel PNG; image an 8-bit picture
(a greyscale one is used as grey RGB, with a warning); K nine finite numbers with focal
lengths > 0 and last row (0, 0, 1); at least one LiDAR pixel. Then the model is built
(``--checkpoint`` loaded, ``--device`` checked). Only then are the ``--out-dir``,
``--out-std-dir`` and ``--vis`` folders created if missing (parents included; they must
be writable). Each PNG is written atomically, so a failed run leaves no partial file.

The model (:func:`build_model`): without ``--checkpoint``, the shipped weights named by
``--weights`` (default ``kitti``, learned on KITTI; ``paper`` = the hand-set initial
values of ``CRFDepth()``) with the options given. ``--checkpoint`` is read by
:func:`crfdepth.load_model` (a Lightning ``.ckpt`` of ``train/``, a file of
:func:`crfdepth.save_model` or a JSON weights file; a bare state dict, which holds
no configuration, is refused): the checkpoint's configuration defines the model, and the model options
given explicitly (``--mode``, ``--superpixels``, ``--potentials``, ``--no-refine``)
override it, e.g. ``--mode pixel`` runs superpixel-trained weights on the pixel graph.

Folder mode checks the layout, the output folders (not locked by another run: see below)
and the model first, then reads and checks every frame (the checks above, naming the
frame; in the workers that read them) before it writes anything: with a bad frame it
writes nothing and exits 2, the first bad frame's message on the first line (the same for
any ``--workers`` and ``--batch-size``), the other bad frames (up to 20) on the lines
below. ``--skip-bad`` completes the good frames instead, lists the bad ones with their
reason in ``<out-dir>/skipped.csv`` (columns ``frame``, ``reason``; a run that skips
nothing removes an earlier one) and in the summary, and exits 0. The extra read costs
23-56 ms per 1216x352 frame, under 10% of its completion (docs/design.md section 10).
A failure that only the model reveals (a non-finite depth) or Ctrl-C stops the run
midway; the message says how many frames were written (``interrupted after 3 of 10
frame(s) written to OUT``, exit status 130), and they stay.

The ``--out-dir``, ``--out-std-dir`` and ``--vis`` folders are locked while the run writes
(``.crfdepth.lock``: pid, host, start time, command; :func:`crfdepth.io.files.lock_folder`):
a second run into one of them exits 2 naming the first. A folder holding a finished run's
outputs may be written again: each PNG is replaced atomically; PNGs this run does not
write stay, with a warning counting them.

A ROS 1 / ROS 2 recording (:mod:`crfdepth.cli.bag`)::

    crfdepth complete --bag RUN.bag --image-topic /cam/image_raw --points-topic /lidar/points \\
        --out-dir depth/ [--out-std-dir std/] [--out-bag RUN_depth.bag]
"""

from __future__ import annotations

import argparse
import functools
import logging
import os
import sys
import time
from pathlib import Path

import numpy as np
from torch.utils.data import Subset
from tqdm import tqdm

from crfdepth.cli.bag import BAG_ONLY, run_bag
from crfdepth.cli.bag import add_arguments as add_bag_arguments
from crfdepth.cli.common import (
    BAD_INPUT,
    add_batch_arguments,
    bad_frames,
    skipped_frames,
    write_skipped,
    complete_frame,
    flag_names,
    write_frame,
    add_model_arguments,
    build_model,
    check_output_folders,
    check_sample,
    complete_batch_with_cli_advice,
    frame_batches,
    make_output_dir,
    output_folders,
    same_file,
    vis_range_type,
)
from crfdepth.data.kitti import open_completion_folder
from crfdepth.checks import check_intrinsics
from crfdepth.plausibility import SPARSE_UNITS, check_sparse_plausible
from crfdepth.errors import InputError
from crfdepth.io.calibration import load_any_calibration
from crfdepth.io.files import check_output_file
from crfdepth.io.kitti import read_depth_png, read_intrinsics, read_rgb
from crfdepth.io.pointcloud import read_points
from crfdepth.memory import check_image_file, cli_advice

logger = logging.getLogger(__name__)

# --------------------------------------------------------------------------- arguments


def add_parser(subparsers: argparse._SubParsersAction) -> argparse.ArgumentParser:
    """Register the ``complete`` sub-command on ``subparsers`` (sets ``func=run``)."""
    parser = subparsers.add_parser(
        "complete",
        help="complete sparse LiDAR into dense depth (one frame, a KITTI folder or a ROS bag)",
        description="Complete a sparse LiDAR depth PNG into a dense KITTI depth PNG (uint16, "
                    "metres * 256) with the CRF model, for one frame (--image, --sparse, "
                    "--intrinsics, --out; or --image, --points, --calib, --out from a raw point "
                    "cloud) or every frame of a val_selection_cropped / "
                    "test_depth_completion_anonymous folder (--input-dir, --out-dir), or every camera "
                    "image of a ROS 1 / ROS 2 recording with the LiDAR cloud nearest in time (--bag, "
                    "--image-topic, --points-topic, --out-dir).",
    )
    one = parser.add_argument_group("one frame")
    one.add_argument("--image", metavar="RGB.png", help="8-bit RGB camera image")
    one.add_argument("--sparse", metavar="SPARSE.png",
                     help="sparse LiDAR depth, KITTI 16-bit PNG (metres * 256, 0 = no point)")
    one.add_argument("--sparse-units", choices=SPARSE_UNITS, default=None,
                     help="what the --sparse PNG's 16-bit codes are: kitti = metres * 256 (the KITTI format, the "
                          "default), mm = millimetres, m = whole metres. A map that is not plausibly metres in "
                          "the chosen unit is refused with the likely one; given explicitly, it also overrules "
                          "the guess that the camera is at most 4 m above the ground (a mast, a drone)")
    one.add_argument("--intrinsics", metavar="K.txt", help="3x3 camera matrix as 9 numbers, row-major")
    one.add_argument("--points", metavar="CLOUD",
                     help="instead of --sparse/--intrinsics: LiDAR point cloud (.bin KITTI, .npy, .ply, .pcd; "
                          "x y z in metres in the LiDAR frame), projected with --calib")
    one.add_argument("--calib", metavar="CALIB",
                     help="with --points: rig calibration YAML/JSON (K, T_cam_lidar, optional distortion and "
                          "image_size) or a KITTI calibration (raw day folder, calib_*.txt, object calib file)")
    one.add_argument("--camera", type=int, choices=(0, 1, 2, 3), default=2,
                     help="with a KITTI --calib: camera index (default: 2, left colour)")
    one.add_argument("--out", metavar="DEPTH.png", help="output depth PNG (its folder must exist)")
    one.add_argument("--out-std", metavar="STD.png",
                     help="also write the std (metres * 256) to this PNG")
    folder = parser.add_argument_group("a folder")
    folder.add_argument("--input-dir", metavar="DIR",
                        help="folder with image/, velodyne_raw/, intrinsics/ (val_selection_cropped "
                             "if it also has groundtruth_depth/, else test_depth_completion_anonymous)")
    folder.add_argument("--out-dir", metavar="OUT",
                        help="output folder (created if missing): one <velodyne_raw name>.png per frame")
    folder.add_argument("--out-std-dir", metavar="OUT",
                        help="also write each frame's std PNG here (created if missing)")
    add_batch_arguments(folder)
    parser.add_argument("--vis", nargs="?", const="", default=None, metavar="DIR",
                        help="write colour pictures <stem>_vis_depth.png and <stem>_vis_std.png into "
                             "DIR (created if missing); without DIR: next to --out, or into "
                             "<out-dir>_vis")
    parser.add_argument("--vis-range", nargs=2, type=vis_range_type, default=None, metavar=("MIN", "MAX"),
                        help="fixed depth colour scale of the pictures in metres (same colours for the same "
                             "depth in every frame of a sequence); default: each frame's 2nd-98th percentile")
    one.add_argument("--trust-transform", action="store_true",
                     help="with --points: use T_cam_lidar even when its inverse lands more points in the image "
                          "(by default that is refused as a probably inverted transform)")
    parser.add_argument("--skip-bad", action="store_true",
                        help="--input-dir / --bag: every frame is checked before anything is written; a bad frame "
                             "makes the run write nothing and exit 2, listing the bad frames. With --skip-bad the "
                             "bad frames are left out instead, listed with the reason in <out-dir>/skipped.csv "
                             "and in the summary, and the run exits 0")
    parser.add_argument("--quiet", action="store_true", help="no progress bar and no summary line")
    add_bag_arguments(parser)
    add_model_arguments(parser)
    parser.set_defaults(func=run)
    return parser


# --------------------------------------------------------------------------- frames


def _where(index: int, total: int, name: str) -> str:
    """How folder mode names a frame: ``frame 2/5 <name>``."""
    return f"frame {index + 1}/{total} {name}"


def _check_frame(sample, index: int, *, total: int, positions: list[int] | None = None) -> None:
    """:func:`~crfdepth.cli.common.check_sample` in the DataLoader workers, naming the frame's files
    as the one-frame path names its flags (``frame 2/5 <name> (velodyne_raw/<name>.png): ...``);
    ``positions[index]`` is the frame's place in the folder when the run leaves frames out (--skip-bad)."""
    try:
        check_sample(sample)
    except InputError as exc:
        where = _where(index if positions is None else positions[index], total, sample.name)
        raise flag_names(exc, {"K": f"{where} (intrinsics/)", "sparse": f"{where} (velodyne_raw/{sample.name}.png)",
                                "image": f"{where} (image/)"}) from None


def _check_outputs(args, inputs: dict[str, Path]) -> tuple[Path, Path | None]:
    """``--out`` / ``--out-std`` checked before anything is read: PNG names in writable folders, not inputs."""
    out = check_output_file(args.out, "--out", suffix=".png")
    out_std = check_output_file(args.out_std, "--out-std", suffix=".png") if args.out_std is not None else None
    if out_std is not None and same_file(out, out_std):
        raise InputError(f"--out-std: must differ from --out, got {out_std} for both")
    for flag, path in ((f, p) for f, p in (("--out", out), ("--out-std", out_std)) if p is not None):
        for source, src_path in inputs.items():
            if same_file(path, src_path):
                raise InputError(f"{flag}: {path} is the {source} input; refusing to overwrite it")
    return out, out_std


def _run_one(args: argparse.Namespace) -> int:
    """One frame: ``--image`` with ``--sparse`` + ``--intrinsics``, or with ``--points`` + ``--calib``."""
    points_mode = args.points is not None or args.calib is not None
    needed = ("--image", "--points", "--calib", "--out") if points_mode else ("--image", "--sparse", "--intrinsics",
                                                                              "--out")
    given = {"--image": args.image, "--sparse": args.sparse, "--intrinsics": args.intrinsics, "--points": args.points,
             "--calib": args.calib, "--out": args.out, "--out-dir": args.out_dir, "--out-std-dir": args.out_std_dir,
             "--batch-size": None if args.batch_size == 1 else args.batch_size,  # given other than the default
             "--workers": None if args.workers == 0 else args.workers}
    missing = [flag for flag in needed if given[flag] is None]
    if missing:
        mode = "point-cloud mode" if points_mode else "one-frame mode"
        raise InputError(f"{mode} needs {', '.join(needed[:-1])} and --out; missing {', '.join(missing)}")
    given["--sparse-units"] = args.sparse_units
    folder_flags = ("--out-dir", "--out-std-dir", "--batch-size", "--workers")
    stray_flags = ("--sparse", "--sparse-units", "--intrinsics", *folder_flags) if points_mode else folder_flags
    stray = [flag for flag in stray_flags if given[flag] is not None]
    if stray and points_mode:
        raise InputError(f"{', '.join(stray)}: cannot be combined with --points/--calib (the cloud and the "
                         f"calibration replace --sparse and --intrinsics; one frame only)")
    if stray:
        raise InputError(f"{', '.join(stray)}: folder options need --input-dir; for one frame use --out / --out-std")
    out, out_std = _check_outputs(args, {flag: Path(given[flag]) for flag in needed[:-1]})
    check_image_file(args.image, f"--image {args.image}", device=args.device, dtype=args.dtype, mode=args.mode,
                     return_std=out_std is not None or args.vis is not None, advice=cli_advice(args.device))
    rgb = read_rgb(args.image)
    if points_mode:
        try:
            points = read_points(args.points)
        except InputError as exc:
            raise InputError(f"--points: {exc}") from None
        try:
            calibration = load_any_calibration(args.calib, camera=args.camera)
        except InputError as exc:
            raise InputError(f"--calib: {str(exc).removeprefix('calibration: ')}") from None
        inputs = dict(points=points, calibration=calibration)
        where = {"points": f"--points {args.points}", "calibration": f"--calib {args.calib}",
                 "K": f"--calib {args.calib}", "T_cam_lidar": f"--calib {args.calib}", "image": f"--image {args.image}",
                 f"K ({calibration.source})": f"--calib {args.calib}",
                 f"T_cam_lidar ({calibration.source})": f"--calib {args.calib}",
                 "*": f"--points {args.points} with --calib {args.calib}"}
    else:
        units = args.sparse_units or "kitti"
        sparse = read_depth_png(args.sparse, units=units)
        try:
            K = read_intrinsics(args.intrinsics)
        except InputError as exc:
            raise InputError(f"--intrinsics: {str(exc).removeprefix('intrinsics: ')}") from None
        if rgb.shape[:2] != sparse.shape:
            raise InputError(f"image and sparse sizes differ: --image {args.image} is {rgb.shape[0]}x{rgb.shape[1]} "
                             f"(HxW) but --sparse {args.sparse} is {sparse.shape[0]}x{sparse.shape[1]}")
        # the API checks both again; here the hints can name --sparse-units
        # an explicit --sparse-units overrules the guess about the rig (a camera more than 4 m up)
        explicit = args.sparse_units is not None
        Kn = check_intrinsics(K, f"--intrinsics {args.intrinsics}", sparse.shape)
        check_sparse_plausible(f"--sparse {args.sparse}", sparse, None if explicit else Kn, read_as=units)
        inputs = dict(sparse=sparse, K=K, trust_units=explicit)
        where = {"sparse": f"--sparse {args.sparse}", "K": f"--intrinsics {args.intrinsics}",
                 "image": f"--image {args.image}"}
    if np.array_equal(rgb[..., 0], rgb[..., 1]) and np.array_equal(rgb[..., 1], rgb[..., 2]):
        logger.warning("--image %s is greyscale; the colour potential sees intensity only", args.image)
    model = build_model(args)
    start = time.perf_counter()
    depth, std = complete_frame(args, model, rgb, where, out_std is not None or args.vis is not None, **inputs)
    vis_dir = None
    if args.vis is not None:  # created only once the frame is completed
        vis_dir = make_output_dir(args.vis, "--vis") if args.vis else out.parent
    written = write_frame(depth, std, out, out_std, vis_dir, out.stem, args.vis_range)
    if not args.quiet:
        print(f"wrote {', '.join(str(p) for p in written)}: {depth.shape[1]}x{depth.shape[0]} depth, "
              f"{float(depth.min()):.2f}-{float(depth.max()):.2f} m, in {time.perf_counter() - start:.1f} s")
    return 0


def _open_folder(path: str):
    """The ``depth_selection`` dataset of ``--input-dir`` (errors name the flag)."""
    folder = Path(path)
    if not folder.exists():
        raise FileNotFoundError(f"--input-dir: no such folder: {path}")
    if not folder.is_dir():
        raise InputError(f"--input-dir: expected a folder with image/, velodyne_raw/ and intrinsics/ (a KITTI "
                         f"val_selection_cropped or test_depth_completion_anonymous folder), got a file: {path}")
    try:
        return open_completion_folder(folder)
    except InputError as exc:
        raise InputError(f"--input-dir {path}: {exc}") from None


def _check_frames(dataset, args, total: int) -> list[tuple[int, type[BaseException], str]]:
    """Pass 1 of folder mode: every frame read and checked (:func:`~crfdepth.cli.common.bad_frames`); each
    message names its frame (``frame 3/6 <name>: ...``; a check names the file too)."""
    progress = tqdm(total=total, unit="frame", desc="check", disable=args.quiet or not sys.stderr.isatty())
    checked = []

    def step(index: int) -> None:
        checked.append(index)
        progress.update(1)

    try:
        bad = bad_frames(dataset, args.workers, functools.partial(_check_frame, total=total), step)
        return [(i, error, message if message.startswith(_where(i, total, dataset.names[i]))
                 else f"{_where(i, total, dataset.names[i])}: {message}") for i, error, message in bad]
    except KeyboardInterrupt:
        raise KeyboardInterrupt(f"while checking the frames ({len(checked)} of {total} checked); nothing "
                                f"written") from None
    finally:
        progress.close()


def _other_pngs(out_dir: Path, names: list[str]) -> int:
    """PNG files in ``out_dir`` that this run does not write (an earlier run's, on other frames)."""
    mine = {f"{name}.png" for name in names}
    return sum(1 for entry in os.scandir(out_dir) if entry.name.endswith(".png") and entry.name not in mine)


def _run_folder(args: argparse.Namespace) -> int:
    if args.out_dir is None:
        raise InputError("--input-dir needs --out-dir (the folder for the output PNGs)")
    stray = [flag for flag, value in (("--image", args.image), ("--sparse", args.sparse),
                                      ("--intrinsics", args.intrinsics), ("--points", args.points),
                                      ("--calib", args.calib), ("--out", args.out),
                                      ("--out-std", args.out_std)) if value is not None]
    if stray:
        raise InputError(f"{', '.join(stray)}: one-frame options cannot be combined with --input-dir")
    dataset = _open_folder(args.input_dir)
    inputs = [dataset.root / sub for sub in ("image", "velodyne_raw", "intrinsics", "groundtruth_depth")]
    targets = check_output_folders(args, inputs, f"an input folder of {dataset.root}")
    model = build_model(args)
    total = len(dataset)
    bad = _check_frames(dataset, args, total)
    skipped = skipped_frames(bad, total, f"--input-dir {args.input_dir}", args.skip_bad)
    good = [i for i in range(total) if i not in skipped]
    names = [dataset.names[i] for i in good]
    frames = Subset(dataset, good) if skipped else dataset
    with_std = args.out_std_dir is not None or args.vis is not None
    start = time.perf_counter()
    with output_folders(targets) as folders:
        out_dir, std_dir = folders[0], folders[1]
        vis_dir = folders[2] if args.vis is not None else None
        others = _other_pngs(out_dir, names)
        if others:
            logger.warning("--out-dir %s already holds %d PNG file(s) that this run does not write (an earlier "
                           "run on other frames?); they stay", out_dir, others)
        skipped_csv = write_skipped(out_dir, [(dataset.names[i], m) for i, m in skipped.items()])
        written = _complete_frames(args, model, frames, names, total, good, out_dir, std_dir, vis_dir, with_std)
    seconds = time.perf_counter() - start
    if not args.quiet:
        print(f"wrote {written} depth PNG(s) to {out_dir}" + (f", std to {std_dir}" if std_dir else "")
              + (f", pictures to {vis_dir}" if vis_dir else "") + f" in {seconds:.1f} s")
        if skipped:
            print(f"skipped {len(skipped)} bad frame(s) of {total} (--skip-bad), listed with the reasons in "
                  f"{skipped_csv}")
    return 0


def _complete_frames(args, model, frames, names: list[str], total: int, positions: list[int], out_dir: Path,
                     std_dir: Path | None, vis_dir: Path | None, with_std: bool) -> int:
    """Pass 2 of folder mode: complete and write ``frames`` (frame ``k`` is frame ``positions[k]`` of the
    folder's ``total``); returns the number written. A failure now (the frame changed since pass 1, a
    non-finite model output) stops the run saying how many frames were written, as does Ctrl-C."""
    progress = tqdm(total=len(names), unit="frame", desc="complete", disable=args.quiet or not sys.stderr.isatty())
    check = functools.partial(_check_frame, total=total, positions=positions)
    batches = frame_batches(frames, args.batch_size, args.workers, check)
    written = 0
    where = _where(positions[0], total, names[0])
    try:
        for batch in batches:  # a frame that fails to read or check is raised here, after the frames before it
            if len(batch) > 1:
                where = (f"frames {positions[written] + 1}-{positions[written + len(batch) - 1] + 1}/{total} "
                         f"({', '.join(batch.names)})")
            depth, std = complete_batch_with_cli_advice(model, batch, with_std)
            depth = depth.double().cpu().numpy()
            std = std.double().cpu().numpy() if std is not None else [None] * len(batch)
            for name, frame_depth, frame_std in zip(batch.names, depth, std):
                where = _where(positions[written], total, name)
                write_frame(frame_depth, frame_std, out_dir / f"{name}.png",
                            std_dir / f"{name}.png" if std_dir is not None else None, vis_dir, name,
                            args.vis_range)
                written += 1
                progress.update(1)
            if written < len(names):
                where = _where(positions[written], total, names[written])
    except BAD_INPUT as exc:
        raise type(exc)(f"{exc} [stopped at {where}; {written} of {len(names)} frame(s) written to "
                        f"{out_dir}]") from None
    except KeyboardInterrupt:
        raise KeyboardInterrupt(f"after {written} of {len(names)} frame(s) written to {out_dir}") from None
    finally:
        batches.close()  # stops the DataLoader workers
        progress.close()
    return written


def run(args: argparse.Namespace) -> int:
    """Complete one frame or a folder as ``args`` asks; returns 0.

    Bad input raises InputError / FileNotFoundError / PermissionError naming the file or
    option, which ``crfdepth.cli.main`` turns into exit status 2 and a one-line message.
    """
    if args.skip_bad and args.bag is None and args.input_dir is None:
        raise InputError("--skip-bad: applies to the runs over many frames (--input-dir or --bag); a single frame "
                         "is either completed or refused")
    if args.sparse_units is not None and (args.bag is not None or args.input_dir is not None):
        raise InputError(f"--sparse-units {args.sparse_units}: applies to --sparse only; "
                         f"{'--input-dir reads KITTI velodyne_raw PNGs (metres * 256)' if args.bag is None else '--bag reads point clouds in metres'}")
    if args.bag is not None:
        return run_bag(args)
    stray = [flag for flag in BAG_ONLY if getattr(args, flag[2:].replace("-", "_")) not in (None, False)]
    if stray:
        raise InputError(f"{', '.join(stray)}: bag options need --bag")
    if args.input_dir is not None:
        return _run_folder(args)
    return _run_one(args)
