"""``crfdepth complete``: sparse LiDAR + RGB -> dense depth PNG(s) with :class:`~crfdepth.model.CRFDepth`.

One frame::

    crfdepth complete --image RGB.png --sparse SPARSE.png --intrinsics K.txt \\
        --out DEPTH.png [--out-std STD.png] [--vis [DIR]]

One frame from a raw point cloud and a calibration (instead of --sparse/--intrinsics)::

    crfdepth complete --image RGB.png --points CLOUD --calib CALIB --out DEPTH.png [--camera 2]

``CLOUD`` is a ``.bin`` (KITTI), ``.npy``, ``.ply`` or ``.pcd`` file
(:func:`crfdepth.io.pointcloud.read_points`); ``CALIB`` a rig YAML/JSON file or any KITTI
calibration (:func:`crfdepth.io.rig.load_any_calibration`; ``--camera`` picks the KITTI
camera). The cloud is projected by :func:`crfdepth.api.points_to_sparse` (KITTI: the
exact KITTI projection) and the image undistorted when the calibration has
``distortion`` (:mod:`crfdepth.api`).

A folder in the ``val_selection_cropped`` or ``test_depth_completion_anonymous`` layout
(``image/``, ``velodyne_raw/``, ``intrinsics/``; DESIGN.md section 7)::

    crfdepth complete --input-dir val_selection_cropped --out-dir pred/ [--out-std-dir std/]

Outputs (DESIGN.md sections 1 and 7): the depth is a KITTI depth PNG of the input's size
(uint16, metres * 256), > 0 at every pixel; the posterior standard deviation is written
the same way (metres * 256). Both are clipped below at 1/256 m, so that no pixel reads
as 0 ("no value"), and the depth above at 65535/256 m by the PNG format. In folder mode
each frame is written as ``<velodyne_raw file name>`` (the KITTI submission naming:
``<drive>_velodyne_raw_<frame>_image_0X.png`` or ``0000000000.png`` ...).

Pictures (``--vis``): ``<stem>_vis_depth.png`` (:func:`crfdepth.visualize.colorize_depth`,
TURBO on inverse depth, near = red) and ``<stem>_vis_std.png``
(:func:`crfdepth.visualize.colorize_std`, VIRIDIS, yellow = uncertain), with ``<stem>``
the stem of ``--out`` (one frame) or the frame name (folder). ``--vis DIR`` writes them
into DIR; a bare ``--vis`` writes them next to ``--out`` (one frame) or into
``<out-dir>_vis`` beside the output folder (folder mode: the submission folder holds only
the depth PNGs). ``--vis`` computes the std map even without ``--out-std``.

Checks before any computation: every output file name ends in ``.png``; the folder of
``--out`` / ``--out-std`` exists and is writable (it is not created); no output is an
input. Then the inputs are read and checked, naming the file in every message: image and
sparse map of the same size; sparse a 16-bit single-channel PNG; image an 8-bit picture
(a greyscale one is used as grey RGB, with a warning); K nine finite numbers with focal
lengths > 0 and last row (0, 0, 1); at least one LiDAR pixel. Then the model is built
(``--checkpoint`` loaded, ``--device`` checked). Only then are the ``--out-dir``,
``--out-std-dir`` and ``--vis`` folders created if missing (parents included; they must
be writable). Each PNG is written atomically, so a failed run leaves no partial file.

The model (:func:`build_model`): without ``--checkpoint``, the shipped weights named by
``--weights`` (default ``kitti``, learned on KITTI; ``paper`` = the hand-set initial
values of ``CRFDepth()``) with the options given. ``--checkpoint`` is read by
:func:`crfdepth.checkpoint.load_model` (a Lightning ``.ckpt`` of ``train/``, a file of
:func:`crfdepth.checkpoint.save_model`, or a bare state dict, which gets the default
configuration): the checkpoint's configuration defines the model, and the model options
given explicitly (``--mode``, ``--superpixels``, ``--potentials``, ``--no-refine``)
override it, e.g. ``--mode pixel`` runs superpixel-trained weights on the pixel graph.

Folder mode checks the layout and the model first, then each frame as it comes (the
checks above, naming the frame); it stops at the first bad frame with exit status 2. The
frames written before it stay (the message says how many), so a run can be resumed after
fixing the frame.
"""

from __future__ import annotations

import argparse
import logging
import os
import sys
import time
from pathlib import Path

import cv2
import numpy as np
import torch
from tqdm import tqdm

from crfdepth.api import complete_depth
from crfdepth.checkpoint import load_model
from crfdepth.pretrained import DEFAULT_WEIGHTS, WEIGHTS, load_pretrained
from crfdepth.data.kitti import KittiTestCompletion, KittiValSelection
from crfdepth.errors import InputError
from crfdepth.io.files import atomic_write_bytes
from crfdepth.io.kitti import read_depth_png, read_intrinsics, read_rgb, write_depth_png
from crfdepth.io.pointcloud import read_points
from crfdepth.io.rig import load_any_calibration
from crfdepth.model import POTENTIALS, CRFDepth
from crfdepth.visualize import colorize_depth, colorize_std

logger = logging.getLogger(__name__)

_MIN_DEPTH = 1.0 / 256.0  # smallest non-zero code of a KITTI depth PNG, metres
_VIS_SUFFIXES = ("_vis_depth.png", "_vis_std.png")


# --------------------------------------------------------------------------- arguments


def _potentials(text: str) -> tuple[str, ...]:
    """``--potentials`` value: comma list, a subset of POTENTIALS containing 'colour'."""
    names = tuple(p.strip() for p in text.split(",") if p.strip())
    unknown = [p for p in names if p not in POTENTIALS]
    if unknown or "colour" not in names:
        raise argparse.ArgumentTypeError(
            f"expected a comma list of {', '.join(POTENTIALS)} that includes colour, got {text!r}")
    return names


def int_at_least(low: int):
    """An argparse ``type`` accepting integers >= ``low`` (shared by the sub-commands)."""

    def parse(text: str) -> int:
        try:
            value = int(text)
        except ValueError:
            value = low - 1
        if value < low:
            raise argparse.ArgumentTypeError(f"expected an integer >= {low}, got {text!r}")
        return value

    return parse


def add_parser(subparsers: argparse._SubParsersAction) -> argparse.ArgumentParser:
    """Register the ``complete`` sub-command on ``subparsers`` (sets ``func=run``)."""
    parser = subparsers.add_parser(
        "complete",
        help="complete sparse LiDAR into dense depth (one frame or a KITTI folder)",
        description="Complete a sparse LiDAR depth PNG into a dense KITTI depth PNG (uint16, "
                    "metres * 256) with the CRF model, for one frame (--image, --sparse, "
                    "--intrinsics, --out; or --image, --points, --calib, --out from a raw point "
                    "cloud) or every frame of a val_selection_cropped / "
                    "test_depth_completion_anonymous folder (--input-dir, --out-dir).",
    )
    one = parser.add_argument_group("one frame")
    one.add_argument("--image", metavar="RGB.png", help="8-bit RGB camera image")
    one.add_argument("--sparse", metavar="SPARSE.png",
                     help="sparse LiDAR depth, KITTI 16-bit PNG (metres * 256, 0 = no point)")
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
                     help="also write the posterior std (metres * 256) to this PNG")
    folder = parser.add_argument_group("a folder")
    folder.add_argument("--input-dir", metavar="DIR",
                        help="folder with image/, velodyne_raw/, intrinsics/ (val_selection_cropped "
                             "if it also has groundtruth_depth/, else test_depth_completion_anonymous)")
    folder.add_argument("--out-dir", metavar="OUT",
                        help="output folder (created if missing): one <velodyne_raw name>.png per frame")
    folder.add_argument("--out-std-dir", metavar="OUT",
                        help="also write each frame's posterior std PNG here (created if missing)")
    folder.add_argument("--quiet", action="store_true", help="no progress bar")
    parser.add_argument("--vis", nargs="?", const="", default=None, metavar="DIR",
                        help="write colour pictures <stem>_vis_depth.png and <stem>_vis_std.png into "
                             "DIR (created if missing); without DIR: next to --out, or into "
                             "<out-dir>_vis")
    add_model_arguments(parser)
    parser.set_defaults(func=run)
    return parser


def add_model_arguments(parser: argparse.ArgumentParser) -> None:
    """The "model" option group (``--mode`` ... ``--checkpoint``, ``--device``, ``--dtype``),
    shared by ``complete`` and ``evaluate``; :func:`build_model` reads it."""
    model = parser.add_argument_group(
        "model", "With --checkpoint, the checkpoint's configuration defines the model and the "
                 "options --mode, --superpixels, --potentials and --no-refine, where given, override it.")
    model.add_argument("--mode", choices=("superpixel", "pixel"), default=None,
                       help="graph nodes (default: the checkpoint's, else superpixel)")
    model.add_argument("--superpixels", type=int_at_least(1), default=None, metavar="N",
                       help="SLIC segments for a 1216x352 image (default: the checkpoint's, else 5500)")
    model.add_argument("--potentials", type=_potentials, default=None, metavar="LIST",
                       help="comma list of colour,normal,distance; colour required (default: the "
                            "checkpoint's, else all)")
    model.add_argument("--no-refine", action="store_true",
                       help="superpixel mode: keep the piecewise-constant painting, no pixel refinement")
    model.add_argument("--weights", choices=WEIGHTS, default=None,
                       help=f"shipped weight set when no --checkpoint is given: kitti (learned on KITTI, "
                            f"crfdepth/weights/README.md) or paper (the hand-set initial values); "
                            f"default: {DEFAULT_WEIGHTS}")
    model.add_argument("--checkpoint", metavar="CKPT",
                       help="trained model instead of --weights: a Lightning .ckpt of train/ (configuration "
                            "in hyper_parameters['crf']), a crfdepth model file (crfdepth.checkpoint."
                            "save_model), a JSON weights file (crfdepth.pretrained) or a bare CRFDepth "
                            "state_dict (default configuration)")
    model.add_argument("--device", choices=("cpu", "cuda"), default="cpu", help="default: cpu")
    model.add_argument("--dtype", choices=("float32", "float64"), default="float32",
                       help="default: float32")


# --------------------------------------------------------------------------- output checks


def _check_writable_dir(directory: Path, what: str) -> None:
    if not directory.is_dir():
        raise FileNotFoundError(f"{what}: output folder does not exist: {directory}")
    if not os.access(directory, os.W_OK | os.X_OK):
        raise PermissionError(f"{what}: output folder is not writable: {directory}")


def _check_output_file(path: str, what: str) -> Path:
    """An output PNG path whose folder exists and is writable (nothing is created)."""
    out = Path(path)
    if out.suffix.lower() != ".png":
        raise InputError(f"{what}: expected a file name ending in .png, got {out}")
    if out.is_dir():
        raise IsADirectoryError(f"{what}: expected a file name, got a folder: {out}")
    _check_writable_dir(out.parent, what)
    return out


def _make_output_dir(path: str | Path, what: str) -> Path:
    """An output folder, created (with parents) if missing; must be writable."""
    directory = Path(path)
    if directory.exists() and not directory.is_dir():
        raise InputError(f"{what}: expected a folder, got a file: {directory}")
    try:
        directory.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise PermissionError(f"{what}: cannot create output folder {directory}: {exc.strerror}") from None
    _check_writable_dir(directory, what)
    return directory


def _same_file(a: Path, b: Path) -> bool:
    return os.path.realpath(a) == os.path.realpath(b)


def _write_rgb_png(path: Path, rgb: np.ndarray) -> None:
    """Write an (H, W, 3) uint8 RGB picture as PNG, atomically (temporary file + rename)."""
    ok, encoded = cv2.imencode(".png", cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR))
    if not ok:  # pragma: no cover - cv2 encodes any uint8 HxWx3 array
        raise InputError(f"vis: could not encode a picture of shape {rgb.shape} as PNG")
    atomic_write_bytes(path, encoded.tobytes())


# --------------------------------------------------------------------------- model


def _model_overrides(args: argparse.Namespace) -> dict:
    """CRFDepth keyword arguments given explicitly on the command line."""
    kwargs = {}
    if args.mode is not None:
        kwargs["mode"] = args.mode
    if args.superpixels is not None:
        kwargs["superpixels"] = args.superpixels
    if args.potentials is not None:
        kwargs["potentials"] = list(args.potentials)
    if args.no_refine:
        kwargs["refine"] = False
    return kwargs


def build_model(args: argparse.Namespace) -> CRFDepth:
    """The :class:`CRFDepth` the options ask for, weights loaded, on ``--device`` / ``--dtype``.

    Without ``--checkpoint``: the shipped weight set ``--weights`` (default "kitti",
    :func:`crfdepth.pretrained.load_pretrained`) with the options given overriding its
    configuration. With it: :func:`crfdepth.checkpoint.load_model` rebuilds the model
    from the checkpoint's configuration (the default one for a bare state dict), and the
    explicit options (``--mode``, ``--superpixels``, ``--potentials``, ``--no-refine``)
    override that configuration. Raises InputError for a CUDA request without CUDA and for
    a checkpoint that cannot be read or does not fit (file and problem named, prefixed
    ``--checkpoint:``); FileNotFoundError for a missing checkpoint.
    """
    if args.device == "cuda" and not torch.cuda.is_available():
        raise InputError("--device cuda: CUDA is not available in this PyTorch installation/machine; "
                         "use --device cpu")
    overrides = _model_overrides(args)
    if args.checkpoint is not None:
        if args.weights is not None:
            raise InputError(f"--weights {args.weights} / --checkpoint: give one of them, not both")
        try:
            model = load_model(args.checkpoint, overrides=overrides)
        except (InputError, FileNotFoundError) as exc:
            raise type(exc)(f"--checkpoint: {exc}") from None
    else:
        model = load_pretrained(args.weights or DEFAULT_WEIGHTS, **overrides)
    if model.mode == "pixel" and (args.superpixels is not None or args.no_refine):
        logger.warning("--superpixels and --no-refine only apply to --mode superpixel; ignored")
    dtype = torch.float64 if args.dtype == "float64" else torch.float32
    return model.to(device=args.device, dtype=dtype).eval()


# --------------------------------------------------------------------------- frames


def _check_intrinsics(K: np.ndarray, where: str) -> None:
    """Finite K with fx, fy > 0 and last row (0, 0, 1); ``where`` names the file."""
    if not np.all(np.isfinite(K)):
        raise InputError(f"intrinsics: expected finite numbers in {where}, got {K.ravel().tolist()}")
    if K[0, 0] <= 0 or K[1, 1] <= 0:
        raise InputError(f"intrinsics: expected focal lengths fx, fy > 0 (K[0,0], K[1,1]) in {where}, "
                         f"got fx={K[0, 0]:g}, fy={K[1, 1]:g}")
    if not np.allclose(K[2], (0.0, 0.0, 1.0)):
        raise InputError(f"intrinsics: expected the last row of K to be 0 0 1 in {where}, got "
                         f"{' '.join(f'{v:g}' for v in K[2])}")


def _check_sparse(sparse: np.ndarray, where: str) -> None:
    if not np.any(sparse > 0):
        raise InputError(f"sparse: no LiDAR point in {where} (every pixel is 0); the CRF needs at least "
                         f"one depth measurement")


def _complete(model: CRFDepth, image: torch.Tensor, sparse: torch.Tensor, K: torch.Tensor,
              with_std: bool) -> tuple[np.ndarray, np.ndarray | None]:
    """One frame: (3, H, W) RGB in [0, 1], (1, H, W) metres, (3, 3) K -> (H, W) depth and std."""
    param = next(model.parameters())
    device, dtype = param.device, param.dtype
    with torch.no_grad():
        out = model(image[None].to(device, dtype), sparse[None].to(device, dtype), K[None].to(device, dtype),
                    return_std=with_std)
    depth = out.depth[0, 0].double().cpu().numpy()
    std = out.std[0, 0].double().cpu().numpy() if with_std else None
    return depth, std


def _write_outputs(depth: np.ndarray, std: np.ndarray | None, out: Path, out_std: Path | None,
                   vis_dir: Path | None, stem: str) -> None:
    if not np.all(np.isfinite(depth)):
        raise InputError(f"{stem}: the model returned {int(np.sum(~np.isfinite(depth)))} non-finite "
                         f"depth value(s); nothing written")
    write_depth_png(out, np.maximum(depth, _MIN_DEPTH))
    if out_std is not None:
        write_depth_png(out_std, np.maximum(np.nan_to_num(std, nan=_MIN_DEPTH), _MIN_DEPTH))
    if vis_dir is not None:
        _write_rgb_png(vis_dir / f"{stem}{_VIS_SUFFIXES[0]}", colorize_depth(depth))
        _write_rgb_png(vis_dir / f"{stem}{_VIS_SUFFIXES[1]}", colorize_std(std))


def _run_points(args: argparse.Namespace) -> int:
    """One frame from ``--image``, ``--points`` and ``--calib`` (see the module docstring)."""
    missing = [flag for flag, value in (("--image", args.image), ("--points", args.points),
                                        ("--calib", args.calib), ("--out", args.out)) if value is None]
    if missing:
        raise InputError(f"point-cloud mode needs --image, --points, --calib and --out; missing {', '.join(missing)}")
    stray = [flag for flag, value in (("--sparse", args.sparse), ("--intrinsics", args.intrinsics),
                                      ("--out-dir", args.out_dir), ("--out-std-dir", args.out_std_dir))
             if value is not None]
    if stray:
        raise InputError(f"{', '.join(stray)}: cannot be combined with --points/--calib (the cloud and the "
                         f"calibration replace --sparse and --intrinsics; one frame only)")
    out = _check_output_file(args.out, "--out")
    out_std = _check_output_file(args.out_std, "--out-std") if args.out_std is not None else None
    if out_std is not None and _same_file(out, out_std):
        raise InputError(f"--out-std: must differ from --out, got {out_std} for both")
    inputs = {"--image": Path(args.image), "--points": Path(args.points), "--calib": Path(args.calib)}
    for flag, path in ((f, p) for f, p in (("--out", out), ("--out-std", out_std)) if p is not None):
        for source, src_path in inputs.items():
            if _same_file(path, src_path):
                raise InputError(f"{flag}: {path} is the {source} input; refusing to overwrite it")
    rgb = read_rgb(args.image)
    try:
        points = read_points(args.points)
    except InputError as exc:
        raise InputError(f"--points: {exc}") from None
    try:
        calibration = load_any_calibration(args.calib, camera=args.camera)
    except InputError as exc:
        raise InputError(f"--calib: {exc}") from None
    model = build_model(args)
    vis_dir = None
    if args.vis is not None:
        vis_dir = _make_output_dir(args.vis, "--vis") if args.vis else out.parent
    start = time.perf_counter()
    try:
        depth, std = complete_depth(rgb, points=points, calibration=calibration, model=model,
                                    device=args.device, return_std=out_std is not None or vis_dir is not None)
    except InputError as exc:
        raise InputError(f"--points {args.points} with --calib {args.calib}: {exc}") from None
    _write_outputs(depth.astype(np.float64), None if std is None else std.astype(np.float64), out, out_std,
                   vis_dir, out.stem)
    logger.info("completed %s in %.2f s -> %s", args.points, time.perf_counter() - start, out)
    return 0


def _run_one(args: argparse.Namespace) -> int:
    if args.points is not None or args.calib is not None:
        return _run_points(args)
    missing = [flag for flag, value in (("--image", args.image), ("--sparse", args.sparse),
                                        ("--intrinsics", args.intrinsics), ("--out", args.out)) if value is None]
    if missing:
        raise InputError(f"one-frame mode needs --image, --sparse, --intrinsics and --out; missing "
                         f"{', '.join(missing)}")
    stray = [flag for flag, value in (("--out-dir", args.out_dir), ("--out-std-dir", args.out_std_dir))
             if value is not None]
    if stray:
        raise InputError(f"{', '.join(stray)}: folder options need --input-dir; for one frame use --out / --out-std")
    out = _check_output_file(args.out, "--out")
    out_std = _check_output_file(args.out_std, "--out-std") if args.out_std is not None else None
    if out_std is not None and _same_file(out, out_std):
        raise InputError(f"--out-std: must differ from --out, got {out_std} for both")
    inputs = {"--image": Path(args.image), "--sparse": Path(args.sparse), "--intrinsics": Path(args.intrinsics)}
    for flag, path in ((f, p) for f, p in (("--out", out), ("--out-std", out_std)) if p is not None):
        for source, src_path in inputs.items():
            if _same_file(path, src_path):
                raise InputError(f"{flag}: {path} is the {source} input; refusing to overwrite it")
    rgb = read_rgb(args.image)
    sparse = read_depth_png(args.sparse)
    K = read_intrinsics(args.intrinsics)
    if rgb.shape[:2] != sparse.shape:
        raise InputError(f"image and sparse sizes differ: --image {args.image} is {rgb.shape[0]}x{rgb.shape[1]} "
                         f"(HxW) but --sparse {args.sparse} is {sparse.shape[0]}x{sparse.shape[1]}")
    if np.array_equal(rgb[..., 0], rgb[..., 1]) and np.array_equal(rgb[..., 1], rgb[..., 2]):
        logger.warning("--image %s is greyscale; the colour potential sees intensity only", args.image)
    _check_intrinsics(K, f"--intrinsics {args.intrinsics}")
    _check_sparse(sparse, f"--sparse {args.sparse}")
    model = build_model(args)
    vis_dir = None
    if args.vis is not None:  # created only once inputs and model are known to be good
        vis_dir = _make_output_dir(args.vis, "--vis") if args.vis else out.parent

    image_t = torch.from_numpy(np.ascontiguousarray(rgb.transpose(2, 0, 1))).float() / 255.0
    start = time.perf_counter()
    depth, std = _complete(model, image_t, torch.from_numpy(sparse)[None], torch.from_numpy(K),
                           with_std=out_std is not None or vis_dir is not None)
    _write_outputs(depth, std, out, out_std, vis_dir, out.stem)
    logger.info("completed %s in %.2f s -> %s", args.sparse, time.perf_counter() - start, out)
    return 0


def _open_dataset(input_dir: str):
    """KittiValSelection when ``input_dir`` has ``groundtruth_depth/``, else KittiTestCompletion."""
    root = Path(input_dir)
    if not root.exists():
        raise FileNotFoundError(f"--input-dir: no such folder: {root}")
    if (root / "groundtruth_depth").is_dir() or (root / KittiValSelection._folder / "groundtruth_depth").is_dir():
        return KittiValSelection(root)
    return KittiTestCompletion(root)


def _run_folder(args: argparse.Namespace) -> int:
    if args.out_dir is None:
        raise InputError("--input-dir needs --out-dir (the folder for the output PNGs)")
    stray = [flag for flag, value in (("--image", args.image), ("--sparse", args.sparse),
                                      ("--intrinsics", args.intrinsics), ("--points", args.points),
                                      ("--calib", args.calib), ("--out", args.out),
                                      ("--out-std", args.out_std)) if value is not None]
    if stray:
        raise InputError(f"{', '.join(stray)}: one-frame options cannot be combined with --input-dir")
    dataset = _open_dataset(args.input_dir)
    inputs = [dataset.root / sub for sub in ("image", "velodyne_raw", "intrinsics", "groundtruth_depth")]
    targets = [("--out-dir", args.out_dir), ("--out-std-dir", args.out_std_dir)]
    if args.vis is not None:
        targets.append(("--vis", args.vis or f"{Path(args.out_dir).resolve()}_vis"))
    for flag, value in targets:
        if value is not None and any(_same_file(value, p) for p in inputs):
            raise InputError(f"{flag}: {value} is an input folder of {dataset.root}; refusing to write there")
    resolved = [os.path.realpath(v) for _, v in targets if v is not None]
    if len(set(resolved)) != len(resolved):
        raise InputError("--out-dir, --out-std-dir and --vis: expected different folders")
    model = build_model(args)
    out_dir = _make_output_dir(args.out_dir, "--out-dir")
    std_dir = _make_output_dir(args.out_std_dir, "--out-std-dir") if args.out_std_dir is not None else None
    vis_dir = _make_output_dir(targets[-1][1], "--vis") if args.vis is not None else None
    progress = tqdm(total=len(dataset), unit="frame", desc="complete",
                    disable=args.quiet or not sys.stderr.isatty())
    written = 0
    start = time.perf_counter()
    try:
        for index in range(len(dataset)):
            name = dataset.names[index]
            where = f"frame {index + 1}/{len(dataset)} {name}"
            try:
                sample = dataset[index]
                _check_intrinsics(sample.K.double().numpy(), f"{where} (intrinsics/)")
                _check_sparse(sample.sparse.numpy(), f"{where} (velodyne_raw/{name}.png)")
                depth, std = _complete(model, sample.image, sample.sparse, sample.K,
                                       with_std=std_dir is not None or vis_dir is not None)
                _write_outputs(depth, std, out_dir / f"{name}.png",
                               std_dir / f"{name}.png" if std_dir is not None else None, vis_dir, name)
            except (InputError, FileNotFoundError, PermissionError, IsADirectoryError) as exc:
                raise type(exc)(f"{exc} [stopped at {where}; {written} of {len(dataset)} frame(s) written "
                                f"to {out_dir}]") from None
            written += 1
            progress.update(1)
    finally:
        progress.close()
    seconds = time.perf_counter() - start
    logger.info("completed %d frame(s) in %.1f s (%.2f s/frame) -> %s", written, seconds,
                seconds / max(written, 1), out_dir)
    return 0


def run(args: argparse.Namespace) -> int:
    """Complete one frame or a folder as ``args`` asks; returns 0.

    Bad input raises InputError / FileNotFoundError / PermissionError naming the file or
    option, which ``crfdepth.cli.main`` turns into exit status 2 and a one-line message.
    """
    if args.input_dir is not None:
        return _run_folder(args)
    return _run_one(args)
