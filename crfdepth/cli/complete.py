"""``crfdepth complete``: sparse LiDAR + RGB -> dense depth PNG(s) with :class:`~crfdepth.model.CRFDepth`.

One frame::

    crfdepth complete --image RGB.png --sparse SPARSE.png --intrinsics K.txt \\
        --out DEPTH.png [--out-std STD.png] [--vis [DIR]]

One frame from a raw point cloud and a calibration (instead of --sparse/--intrinsics)::

    crfdepth complete --image RGB.png --points CLOUD --calib CALIB --out DEPTH.png [--camera 2]

``CLOUD`` is a ``.bin`` (KITTI), ``.npy``, ``.ply`` or ``.pcd`` file
(:func:`crfdepth.io.pointcloud.read_points`); ``CALIB`` a rig YAML/JSON file or any KITTI
calibration (:func:`crfdepth.io.calibration.load_any_calibration`; ``--camera`` picks the KITTI
camera). The cloud is projected by :func:`crfdepth.inputs.points_to_sparse` (KITTI: the
exact KITTI projection) and the image undistorted when the calibration has
``distortion`` (:mod:`crfdepth.api`).

A folder in the ``val_selection_cropped`` or ``test_depth_completion_anonymous`` layout
(``image/``, ``velodyne_raw/``, ``intrinsics/``; docs/design.md section 7)::

    crfdepth complete --input-dir val_selection_cropped --out-dir pred/ [--out-std-dir std/] \\
        [--batch-size B] [--workers N]

A KITTI raw drive folder the same way (:mod:`crfdepth.runs.folder`): each scan projected whole
into the ``--camera`` image (2 or 3, uncropped), as ``--points``/``--calib`` do for one frame, written as
``<frame number>.png``::

    crfdepth complete --input-dir 2011_09_26/2011_09_26_drive_0060_sync --out-dir pred/ [--camera 3]

Folder mode reads the frames with a ``torch.utils.data.DataLoader``: ``--workers N``
processes (default 0: this process) read, decode and check frames ahead of the model, and
up to ``--batch-size B`` (default 1) consecutive frames of the same size are completed by
one model call (a size change starts a new batch; :func:`crfdepth.runs.batches.frame_batches`).
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
``<drive>_velodyne_raw_<frame>_image_0X.png`` or ``0000000000.png`` ...; a raw drive's frame as
``<frame number>.png``).

Pictures (``--vis``): ``<stem>_vis_depth.png`` (:func:`crfdepth.pictures.colour.colorize_depth`,
TURBO on inverse depth, near = red) and ``<stem>_vis_std.png``
(:func:`crfdepth.pictures.colour.colorize_std`, VIRIDIS, yellow = uncertain), with ``<stem>``
the stem of ``--out`` (one frame) or the frame name (folder). ``--vis DIR`` writes them
into DIR; a bare ``--vis`` writes them next to ``--out`` (one frame) or into
``<out-dir>_vis`` beside the output folder (folder mode: the submission folder holds only
the depth PNGs). ``--vis`` computes the std map even without ``--out-std``.

Checks before any computation: ``--vis-range`` is two finite numbers 0 < MIN < MAX (a usage
error when the arguments are read); every output file name ends in ``.png``; the folder of
``--out`` / ``--out-std`` exists and takes new files, and so does the ``--vis`` folder or the
folder it will be created in (a probe file is created and removed, so ``/proc`` or a
read-only mount fails here, naming the flag; it is not created); no output is an input.
Then the inputs are read and checked, naming the flag and the file in every message: image and
sparse map of the same size; sparse a 16-bit single-channel PNG; image an 8-bit picture
(a greyscale one is used as grey RGB, with a warning); K nine finite numbers with focal
lengths > 0 and last row (0, 0, 1); at least one LiDAR pixel. A file that does not decode
is told by that one line, without the decoders' own warnings on stderr
(:mod:`crfdepth.cli.decoder_noise`). Then the model is built
(``--checkpoint`` loaded, ``--device`` checked). Only then are the ``--out-dir``,
``--out-std-dir`` and ``--vis`` folders created if missing (parents included; they must
be writable). A frame's PNGs (depth, std, pictures) are written to temporary files and
renamed into place together once all are written (:func:`crfdepth.runs.outputs.write_files`),
so a failed run leaves no partial file and no part of a frame; the error names the flag and
the file asked for (``--out: cannot write d/depth.png: No space left on device``), never the
temporary file. An error of the system on any file the user named (a name too long, a
read-only or full disk, a folder where a file is expected) is one line naming its flag
(:mod:`crfdepth.cli.file_errors`).

The model (:func:`~crfdepth.cli.model_options.build_model`): without ``--checkpoint``, the shipped weights named by
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
A failure that only the model reveals (a non-finite depth), an output that cannot be written
(a full disk: stops the run even with ``--skip-bad``) or Ctrl-C stops the run
midway; the message says how many frames were written (``interrupted after 3 of 10
frame(s) written to OUT; --resume completes the others``, exit status 130), and they stay;
nothing of the frame being written stays. A run stopped before its first frame was written
leaves nothing behind: no PNG, no run record, no ``skipped.csv``, and the folders it created
are removed.
The same command with ``--resume`` completes the others, and the folders end as one
uninterrupted run's, byte for byte (:mod:`crfdepth.runs.resume`).

The ``--out-dir``, ``--out-std-dir`` and ``--vis`` folders are locked while the run writes
(``.crfdepth.lock``: pid, host, start time, command; :func:`crfdepth.io.files.lock_folder`):
a second run into one of them exits 2 naming the first. A folder holding a finished run's
outputs may be written again: each PNG is replaced atomically; PNGs this run does not
write stay, with a warning counting them.

An RGB-D camera's depth image with holes (Kinect, RealSense: :mod:`crfdepth.cli.complete_rgbd`, docs/rgbd.md),
its holes filled and its measured pixels kept, written in its own unit::

    crfdepth complete --image RGB.png --depth DEPTH.png [--depth-units mm] (--intrinsics K.txt | --known-camera nyu) \\
        --out FILLED.png [--out-std STD.png] [--vis [DIR]]

and a folder of RGB-D pairs the same way (NYU's ``rgb_XXXXX.jpg`` + ``sync_depth_XXXXX.png``, or ``image/`` +
``depth/``; :mod:`crfdepth.cli.complete_rgbd_folder`)::

    crfdepth complete --input-dir DIR --known-camera nyu --out-dir OUT [--out-std-dir STD] [--depth-units mm]

A ROS 1 / ROS 2 recording (:mod:`crfdepth.cli.complete_bag`)::

    crfdepth complete --bag RUN.bag --image-topic /cam/image_raw --points-topic /lidar/points \\
        --out-dir depth/ [--out-std-dir std/] [--out-bag RUN_depth.bag]

``--rerun FILE.rrd`` (one frame, ``--input-dir``, ``--bag``) also writes a Rerun recording, one time step
per frame completed (:mod:`crfdepth.pictures.rerun_recording`: the camera, the image, the LiDAR points in 3D
and on the image, the depth, and the std when one is asked for); a bare ``--rerun`` streams to a viewer.
Checked with the other outputs, before any computation (a ``.rrd`` name in a folder that takes new files;
rerun-sdk installed); the file appears when the run ends and not at all when it fails. One process
records: ``--input-list``, ``--devices``, ``--num-nodes``, ``--strategy`` and a launcher's rank are refused with it.
"""

from __future__ import annotations

import argparse
import logging

from crfdepth import api
from crfdepth.cli.arguments import VisRange, add_batch_arguments, add_rerun_argument, vis_range_type
from crfdepth.cli.complete_bag import BAG_ONLY, run_bag
from crfdepth.cli.complete_bag import add_arguments as add_bag_arguments
from crfdepth.cli.complete_folder import folder_run, run_folder
from crfdepth.cli.complete_list import run_list
from crfdepth.cli.complete_one import read_one, write_one
from crfdepth.cli.complete_rgbd import KNOWN_CAMERAS, complete_rgbd_frame, rgbd_input
from crfdepth.cli.complete_rgbd_folder import complete_rgbd_folder
from crfdepth.cli.completion import frame_errors
from crfdepth.cli.model_options import add_model_arguments
from crfdepth.cli.outputs import rerun_recording
from crfdepth.errors import InputError
from crfdepth.io.calibration import is_rig_file
from crfdepth.io.depth_image import DEPTH_UNITS
from crfdepth.plausibility import SPARSE_UNITS
from crfdepth.runs.folder import complete_folder
from crfdepth.runs.ranks import launcher_world_size

logger = logging.getLogger(__name__)

# --------------------------------------------------------------------------- arguments


HELP = ("complete sparse LiDAR into dense depth (one frame, a KITTI folder or raw drive, or a ROS bag), or fill the "
        "holes of an RGB-D depth image")
DESCRIPTION = ("Complete a sparse LiDAR depth PNG into a dense KITTI depth PNG (uint16, "
               "metres * 256) with the CRF model, for one frame (--image, --sparse, "
               "--intrinsics, --out; or --image, --points, --calib, --out from a raw point "
               "cloud) or every frame of a val_selection_cropped / "
               "test_depth_completion_anonymous folder or of a KITTI raw drive folder (--input-dir, "
               "--out-dir), or every camera "
               "image of a ROS 1 / ROS 2 recording with the LiDAR cloud nearest in time (--bag, "
               "--image-topic, --points-topic, --out-dir). With --depth (or an --input-dir of RGB-D pairs) it "
               "fills the holes of an RGB-D camera's depth image instead, keeping its measured pixels, and "
               "writes it in its own unit (docs/rgbd.md).")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """The options of ``crfdepth complete``."""
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
    rgbd = parser.add_argument_group(
        "RGB-D hole filling", "A depth camera's image registered to --image (Kinect, RealSense): its holes filled, "
                              "its measured pixels kept, the output PNGs in its own unit (docs/rgbd.md)")
    rgbd.add_argument("--depth", metavar="DEPTH.png",
                      help="instead of --sparse: 16-bit depth PNG registered to --image, 0 = hole, in "
                           "--depth-units; needs --intrinsics or --known-camera")
    rgbd.add_argument("--depth-units", choices=DEPTH_UNITS, default=None,
                      help="the codes of the --depth PNG (or of the depth PNGs of an --input-dir of RGB-D pairs) "
                           "and of the outputs: mm = millimetres (the default; NYU, most RGB-D cameras), m = whole "
                           "metres, kitti = metres * 256. A map that is not plausibly depth in the unit is refused "
                           "with the likely one")
    rgbd.add_argument("--known-camera", choices=tuple(KNOWN_CAMERAS), default=None,
                      help="instead of --intrinsics for RGB-D input: the intrinsics of a known camera, scaled to "
                           "the image's size; " + "; ".join(f"{k} = {v}" for k, v in KNOWN_CAMERAS.items()))
    one.add_argument("--points", metavar="CLOUD",
                     help="instead of --sparse/--intrinsics: LiDAR point cloud (.bin KITTI, .npy, .ply, .pcd; "
                          "x y z in metres in the LiDAR frame), projected with --calib")
    one.add_argument("--calib", metavar="CALIB",
                     help="with --points: rig calibration YAML/JSON (K, T_cam_lidar, optional distortion and "
                          "image_size) or a KITTI calibration (raw day folder, calib_*.txt, object calib file)")
    one.add_argument("--camera", type=int, choices=(0, 1, 2, 3), default=None,
                     help="with a KITTI --calib, or --input-dir of a KITTI raw drive (2 or 3): camera index "
                          "(default: 2, left colour)")
    one.add_argument("--out", metavar="DEPTH.png", help="output depth PNG (its folder must exist)")
    one.add_argument("--out-std", metavar="STD.png",
                     help="also write the std (metres * 256) to this PNG")
    folder = parser.add_argument_group("a folder")
    folder.add_argument("--input-dir", metavar="DIR",
                        help="folder with image/, velodyne_raw/, intrinsics/ (val_selection_cropped "
                             "if it also has groundtruth_depth/, else test_depth_completion_anonymous), or a "
                             "KITTI raw drive folder <day>/<day>_drive_NNNN_sync (velodyne_points/data/*.bin, "
                             "image_0X/data/*.png, the day's calib_*.txt above it): each scan projected whole "
                             "into the --camera image, uncropped; or a folder of RGB-D pairs (rgb_XXXXX.jpg with "
                             "sync_depth_XXXXX.png, or image/ with depth/ of the same stems), each depth image's "
                             "holes filled (with --intrinsics or --known-camera)")
    folder.add_argument("--out-dir", metavar="OUT",
                        help="output folder (created if missing): one <velodyne_raw name>.png per frame "
                             "(a raw drive: <frame number>.png; RGB-D pairs: <depth file's stem>.png)")
    folder.add_argument("--out-std-dir", metavar="OUT",
                        help="also write each frame's std PNG here (created if missing)")
    add_batch_arguments(folder)
    parser.add_argument("--vis", nargs="?", const="", default=None, metavar="DIR",
                        help="write colour pictures <stem>_vis_depth.png and <stem>_vis_std.png into "
                             "DIR (created if missing); without DIR: next to --out, or into "
                             "<out-dir>_vis")
    parser.add_argument("--vis-range", nargs=2, type=vis_range_type, action=VisRange, default=None,
                        metavar=("MIN", "MAX"),
                        help="fixed depth colour scale of the pictures in metres, 0 < MIN < MAX (same colours for "
                             "the same depth in every frame of a sequence); default: each frame's 2nd-98th "
                             "percentile")
    one.add_argument("--trust-transform", action="store_true",
                     help="with --points: use T_cam_lidar even when its inverse lands more points in the image "
                          "(by default that is refused as a probably inverted transform)")
    parser.add_argument("--skip-bad", action="store_true",
                        help="--input-dir / --bag: every frame is checked before anything is written; a bad frame "
                             "makes the run write nothing and exit 2, listing the bad frames. With --skip-bad the "
                             "bad frames are left out instead, listed with the reason in <out-dir>/skipped.csv "
                             "and in the summary, and the run exits 0")
    parser.add_argument("--resume", action="store_true",
                        help="--input-dir: leave out the frames an earlier run of the same model and options "
                             "finished in these folders (every output file there; <out-dir>/.crfdepth-run.json says which "
                             "model and options wrote them, and another run's folder is refused), and complete "
                             "the others: a run stopped part-way and resumed writes the same files as one "
                             "uninterrupted run")
    folder.add_argument("--input-list", metavar="FILE",
                        help="complete many inputs in turn: FILE names one per line (a KITTI depth-completion "
                             "folder or raw drive folder, as --input-dir takes, or a ROS recording, as --bag "
                             "takes; # comments), each "
                             "completed into <out-dir>/<its name>; every line is checked first")
    parser.add_argument("--quiet", action="store_true", help="no progress bar and no summary line")
    add_rerun_argument(parser, "the image, its LiDAR points, the depth and the std (when --out-std, --out-std-dir "
                               "or --vis asks for it)")
    add_bag_arguments(parser)
    add_model_arguments(parser)


def _warn_ignored(args: argparse.Namespace) -> None:
    """A warning for each option given that the mode run does not read (the options refused in a mode are refused
    where the mode is checked): ``--trust-transform`` without a point cloud to project (``--sparse``, or a folder
    whose drive scans are projected with KITTI's own calibration), ``--camera`` with ``--sparse`` (whose map is
    already in one camera) or with a rig ``--calib`` (one camera), and a KITTI ``--calib`` picking the camera."""
    points = args.points is not None or args.calib is not None
    if args.trust_transform and not points and args.bag is None:
        logger.warning("--trust-transform is ignored with %s (it applies to a point cloud projected with a rig "
                       "transform: --points with --calib, or --bag)",
                       "--input-dir" if args.input_dir is not None else
                       "--input-list" if args.input_list is not None else "--sparse")
    if args.camera is not None and args.bag is None and args.input_dir is None and args.input_list is None:
        if not points:
            logger.warning("--camera is ignored with --sparse (the depth map is already in its camera's image; "
                           "--camera picks the camera of a KITTI --calib or raw drive)")
        elif args.calib is not None and is_rig_file(args.calib):
            logger.warning("--camera is ignored with the rig calibration --calib %s (it holds one camera; --camera "
                           "picks the camera of a KITTI calibration)", args.calib)
    if args.camera is None:
        args.camera = 2  # the default, None when parsed so that a --camera given to no use is told


def run(args: argparse.Namespace) -> int:
    """Complete one frame or a folder as ``args`` asks; returns 0.

    Bad input raises InputError / FileNotFoundError / PermissionError naming the file or
    option, which ``crfdepth.cli.main`` turns into exit status 2 and a one-line message.
    A folder goes to :func:`crfdepth.runs.folder.complete_folder` and one frame to
    :func:`crfdepth.api.complete_depth` from here, so that neither passes a call more on its way to the CG loop
    than it needs (docs/design.md section 8).
    """
    many = args.bag is not None or args.input_dir is not None or args.input_list is not None
    given = [flag for flag, value in (("--input-list", args.input_list), ("--input-dir", args.input_dir),
                                      ("--bag", args.bag)) if value is not None]
    if len(given) > 1:
        raise InputError(f"{' / '.join(given)}: give one of them (--input-list names folders and recordings itself)")
    if args.vis_range is not None and args.vis is None:
        raise InputError(f"--vis-range {args.vis_range[0]:g} {args.vis_range[1]:g}: sets the colour scale of the "
                         f"pictures --vis writes; add --vis (or leave --vis-range out)")
    if args.skip_bad and not many:
        raise InputError("--skip-bad: applies to the runs over many frames (--input-dir, --bag or --input-list); a "
                         "single frame is either completed or refused")
    if args.sparse_units is not None and many:
        raise InputError(f"--sparse-units {args.sparse_units}: applies to --sparse only; "
                         f"{'--bag reads point clouds in metres' if args.bag is not None else '--input-dir and --input-list read KITTI velodyne_raw PNGs (metres * 256) or raw scans (metres)'}")
    scale = [f"{flag} {value}" for flag, value, default in (("--devices", args.devices, 1), ("--num-nodes",
             args.num_nodes, 1), ("--strategy", args.strategy, "auto")) if value != default]
    if scale and args.input_dir is None and args.input_list is None:
        raise InputError(f"{' '.join(scale)}: applies to --input-dir and --input-list (folders of frames)")
    if args.resume and args.input_dir is None and args.input_list is None:
        raise InputError("--resume: applies to --input-dir and --input-list (folders of frames); a single frame is "
                         "simply run again" + (", and --bag writes its index.csv afresh" if args.bag is not None
                                               else ""))
    launched = launcher_world_size() > 1  # a rank of torchrun / srun
    if args.rerun is not None and (args.input_list is not None or scale or launched):
        raise InputError(f"--rerun: records the frames of one process (one frame, --input-dir or --bag), got "
                         f"{' '.join(scale) or ('--input-list' if args.input_list is not None else 'a launcher')}")
    rgbd = rgbd_input(args)  # None: LiDAR; "frame" (--depth) or the layout of an --input-dir of RGB-D pairs
    if rgbd is None:
        _warn_ignored(args)
    if args.input_list is not None:
        return run_list(args, run_folder, run_bag)
    stray = [flag for flag in BAG_ONLY if getattr(args, flag[2:].replace("-", "_")) not in (None, False)]
    if stray and args.bag is None:
        raise InputError(f"{', '.join(stray)}: bag options need --bag")
    with rerun_recording(args) as args.recorder:  # checked now, written when the run ends
        if rgbd == "frame":
            return complete_rgbd_frame(args)
        if rgbd is not None:
            return complete_rgbd_folder(args, rgbd)
        if args.bag is not None:
            return run_bag(args)
        if args.input_dir is not None:
            return complete_folder(folder_run(args))
        frame = read_one(args)
        with frame_errors(args, frame.model, frame.rgb.shape[:2], frame.where, frame.units):
            depth, std = api.complete_depth(frame.rgb, model=frame.model, device=args.device,
                                            trust_transform=args.trust_transform,
                                            return_std=frame.out_std is not None or args.vis is not None,
                                            **frame.inputs)
        return write_one(args, frame, depth, std)
