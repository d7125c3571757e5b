"""``crfdepth complete --depth``: an RGB-D camera's depth image with holes (Kinect, RealSense) filled, its measured
pixels kept (docs/rgbd.md).

One frame::

    crfdepth complete --image RGB.png --depth DEPTH.png [--depth-units mm] (--intrinsics K.txt | --known-camera nyu) \\
        --out FILLED.png [--out-std STD.png] [--vis [DIR]]

A folder of RGB-D pairs (:mod:`crfdepth.cli.complete_rgbd_folder`)::

    crfdepth complete --input-dir DIR --known-camera nyu --out-dir OUT [--out-std-dir STD] [--depth-units mm]

``--depth`` is a 16-bit single-channel PNG registered to ``--image`` (same size, same camera), 0 = no depth, in
``--depth-units`` (:data:`~crfdepth.io.depth_image.DEPTH_UNITS`: ``mm`` millimetres, the default; ``m`` whole
metres; ``kitti`` metres * 256), read by :func:`crfdepth.io.depth_image.read_depth_image`, which refuses, naming
``--depth``, a file that is not such a PNG, an 8-bit visualisation stored in 16 bits, a map with no valid pixel and
a map whose values are not plausibly depth in the unit given (naming the likely unit). The intrinsics are those of
the colour camera: ``--intrinsics K.txt`` (9 numbers, row-major) or ``--known-camera`` (:data:`KNOWN_CAMERAS`:
``nyu`` = NYU Depth v2's Kinect colour camera, :func:`crfdepth.data.nyu.camera.nyu_intrinsics`, scaled to the
image's size).

The model: the shipped weights (``--weights``, default kitti) with the occlusion gate off, since registered depth
has no LiDAR return seen through a foreground edge (:func:`~crfdepth.cli.model_options.build_model` with
``registered_depth``); a ``--checkpoint`` runs as stored. The depth image is the model's sparse input (every valid
pixel a measurement); the depth of the completed frame replaces the holes only (:func:`fill_holes`): where the
input has depth the output holds it unchanged.

Outputs: 16-bit PNGs **in the input's unit** (``--depth-units``): ``round(depth * codes per metre)`` of the unit,
clipped to [1, 65535] so that no pixel reads as a hole (millimetres: at most 65.535 m); the measured pixels get
their own codes back. ``--out-std`` likewise (the model's std in the same unit, at least one code). ``--vis``
writes the pictures as for LiDAR (``<stem>_vis_depth.png``, ``<stem>_vis_std.png``, in metres). The files of a
frame are written together through temporary files and renames (:func:`crfdepth.runs.outputs.write_files`):
all or none. Every input is read and checked before the model is built and every output path before any input
is read (:func:`crfdepth.cli.complete_one.check_outputs`); each refusal is one line naming the flag, exit status 2.
"""

from __future__ import annotations

import argparse
import logging
import time
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import torch

from crfdepth import api
from crfdepth.cli.completion import cli_advice, frame_errors
from crfdepth.cli.decoder_noise import quiet_decoders
from crfdepth.cli.file_errors import flagged
from crfdepth.cli.model_options import build_model
from crfdepth.errors import InputError
from crfdepth.io.depth_image import CODES_PER_METRE, check_depth_matches_image, read_depth_image
from crfdepth.io.kitti import read_intrinsics, read_rgb
from crfdepth.memory import check_image_file
from crfdepth.pictures.figures import depth_picture, std_picture
from crfdepth.runs.outputs import write_files

logger = logging.getLogger("crfdepth.cli.complete")  # the command's logger, whichever mode runs

__all__ = ["KNOWN_CAMERAS", "RGBD_LAYOUTS", "Camera", "complete_holes", "complete_rgbd_frame", "depth_codes",
           "fill_holes", "frame_files", "rgbd_input", "rgbd_layout"]

KNOWN_CAMERAS = {"nyu": "NYU Depth v2's Kinect colour camera (640x480, or scaled: 320x240, 160x120 ...)"}
"""``--known-camera`` names and what each is; :meth:`Camera.K` gives the intrinsics for an image size."""

RGBD_LAYOUTS = {"nyu_sync": "rgb_XXXXX.jpg with sync_depth_XXXXX.png (NYU Depth v2, official test layout)",
                "image_depth": "image/<stem>.png|jpg with depth/<stem>.png"}
"""The folders of RGB-D pairs ``--input-dir`` takes, and their files."""

# --------------------------------------------------------------------------- which mode, which camera


def rgbd_layout(folder: Path) -> str | None:
    """The RGB-D layout of ``folder`` (a key of :data:`RGBD_LAYOUTS`), or None when it holds neither. A folder
    of scene folders in the NYU layout (``official_test/`` holding ``basement/`` ...) is refused, naming them:
    each scene is an ``--input-dir`` of its own."""
    if any(folder.glob("sync_depth_*.png")):
        return "nyu_sync"
    if (folder / "image").is_dir() and (folder / "depth").is_dir():
        return "image_depth"
    scenes = sorted(sub.name for sub in folder.iterdir() if sub.is_dir() and any(sub.glob("sync_depth_*.png")))
    if scenes:
        shown = ", ".join(scenes[:5]) + (f" and {len(scenes) - 5} more" if len(scenes) > 5 else "")
        raise InputError(f"--input-dir: expected one folder of RGB-D pairs, got {folder}, a folder of {len(scenes)} "
                         f"scene folder(s) ({shown}); give each scene as --input-dir")
    return None


def rgbd_input(args: argparse.Namespace) -> str | None:
    """Which RGB-D mode ``args`` asks for: ``"frame"`` (``--depth``), the :data:`RGBD_LAYOUTS` key of an
    ``--input-dir`` of RGB-D pairs (detected from its files, or required by ``--depth-units``), or None (LiDAR).
    Options of the other kind of input are refused naming both flags; so is a missing camera."""
    depth_units = args.depth_units is not None
    layout = None
    if args.depth is not None:
        other = [flag for flag, value in (("--sparse", args.sparse), ("--points", args.points),
                                          ("--calib", args.calib)) if value is not None]
        if other:
            raise InputError(f"--depth / {other[0]}: give one of them: --depth is a depth camera's image registered "
                             f"to --image (its holes filled, its pixels kept), {other[0]} a LiDAR's "
                             f"{'sparse depth map' if other[0] == '--sparse' else 'point cloud'}")
        many = [flag for flag, value in (("--input-dir", args.input_dir), ("--input-list", args.input_list),
                                         ("--bag", args.bag)) if value is not None]
        if many:
            raise InputError(f"--depth / {many[0]}: --depth is one frame's depth image; a folder of RGB-D pairs is "
                             f"given as --input-dir alone")
        layout = "frame"
    elif args.input_dir is not None and (args.input_list is None and args.bag is None):
        folder = Path(args.input_dir)
        with flagged("--input-dir", args.input_dir):
            if folder.is_dir():
                layout = rgbd_layout(folder)
            elif depth_units and not folder.exists():
                raise FileNotFoundError(f"--input-dir: no such folder: {args.input_dir}")
        if layout is None and depth_units:
            raise InputError(f"--depth-units {args.depth_units}: applies to RGB-D pairs, and --input-dir "
                             f"{args.input_dir} holds none: expected {RGBD_LAYOUTS['nyu_sync']}, or "
                             f"{RGBD_LAYOUTS['image_depth']}")
    if layout is None:
        if depth_units:
            raise InputError(f"--depth-units {args.depth_units}: applies to an RGB-D depth image (--depth, or an "
                             f"--input-dir of RGB-D pairs)" + ("; the --sparse map's unit is --sparse-units"
                                                               if args.sparse is not None else ""))
        if args.known_camera is not None:
            raise InputError(f"--known-camera {args.known_camera}: applies to an RGB-D depth image (--depth, or an "
                             f"--input-dir of RGB-D pairs); a LiDAR frame gives --intrinsics K.txt or --calib")
        return None
    stray = [flag for flag, value in (("--sparse-units", args.sparse_units), ("--camera", args.camera),
                                      ("--trust-transform", args.trust_transform or None)) if value is not None]
    if stray:
        raise InputError(f"{', '.join(stray)}: appl{'ies' if len(stray) == 1 else 'y'} to LiDAR input; an RGB-D "
                         f"depth image's unit is --depth-units and its camera --intrinsics or --known-camera")
    if args.intrinsics is None and args.known_camera is None:
        raise InputError("--intrinsics / --known-camera: an RGB-D frame needs its colour camera's intrinsics: "
                         f"--intrinsics K.txt (9 numbers, row-major) or --known-camera "
                         f"{' / '.join(KNOWN_CAMERAS)}; missing both")
    if args.intrinsics is not None and args.known_camera is not None:
        raise InputError(f"--intrinsics / --known-camera: give one of them, got --intrinsics {args.intrinsics} and "
                         f"--known-camera {args.known_camera}")
    return layout


@dataclass(frozen=True)
class Camera:
    """The colour camera of an RGB-D input: ``matrix``, the 3x3 intrinsics of ``--intrinsics`` (pixels), or
    ``known``, a :data:`KNOWN_CAMERAS` name; ``flag`` names it in messages."""

    flag: str
    matrix: np.ndarray | None = None
    known: str | None = None

    @classmethod
    def from_args(cls, args: argparse.Namespace) -> "Camera":
        """The camera :func:`rgbd_input` accepted; ``--intrinsics`` read here (errors name the flag)."""
        if args.known_camera is not None:
            return cls(f"--known-camera {args.known_camera}", known=args.known_camera)
        with flagged("--intrinsics", args.intrinsics, labels=("intrinsics",)):
            return cls(f"--intrinsics {args.intrinsics}", matrix=read_intrinsics(args.intrinsics))

    def K(self, width: int, height: int) -> np.ndarray:
        """(3, 3) float64 intrinsics of an image of ``width`` x ``height`` pixels; a known camera is scaled to the
        size (an InputError naming the flag for a size it does not come in)."""
        if self.matrix is not None:
            return np.asarray(self.matrix, dtype=np.float64)
        from crfdepth.data.nyu.camera import nyu_intrinsics

        K = nyu_intrinsics(width, height, argument=f"{self.flag} (the image's size)")
        return np.asarray(K.detach().cpu() if isinstance(K, torch.Tensor) else K, dtype=np.float64)


# --------------------------------------------------------------------------- filling and files


def fill_holes(depth: np.ndarray, completed: np.ndarray) -> np.ndarray:
    """The depth image ``depth`` ((H, W) metres, 0 = hole) with its holes taken from ``completed`` ((H, W) metres,
    > 0): equal to ``depth`` wherever it is > 0. Returns a new float32 array; neither input is modified."""
    return np.where(depth > 0, depth, completed).astype(np.float32)


def depth_codes(metres: np.ndarray, units: str) -> np.ndarray:
    """(H, W) uint16 PNG codes of ``metres`` in ``units`` (``mm``: 1000 per metre, ``m``: 1, ``kitti``: 256),
    rounded and clipped to [1, 65535]: no pixel reads as 0 ("no depth")."""
    codes = np.rint(np.asarray(metres, dtype=np.float64) * CODES_PER_METRE[units])
    return np.clip(np.nan_to_num(codes, nan=1.0), 1, 65535).astype(np.uint16)


def _png(codes: np.ndarray, flag: str, path: Path) -> bytes:
    ok, encoded = cv2.imencode(".png", codes)
    if not ok:  # pragma: no cover - cv2 encodes any uint8 / uint16 array of 1 or 3 channels
        raise InputError(f"{flag}: could not encode an array of shape {codes.shape} {codes.dtype} as PNG for {path}")
    return encoded.tobytes()


def frame_files(filled: np.ndarray, std: np.ndarray | None, units: str, out: Path, out_std: Path | None,
                vis_dir: Path | None, stem: str, vis_range, flags: tuple[str, str, str]) -> list[tuple[str, Path, bytes]]:
    """The encoded files of one filled frame, ``(flag, path, bytes)`` for :func:`crfdepth.runs.outputs.write_files`:
    the depth PNG (and std PNG) in ``units``, and with ``vis_dir`` the pictures ``<stem>_vis_depth.png`` (and
    ``<stem>_vis_std.png``). ``flags`` name the depth's, the std's and the pictures' outputs in errors."""
    if not np.all(np.isfinite(filled)):
        raise InputError(f"{flags[0]} {out}: the model returned {int(np.sum(~np.isfinite(filled)))} non-finite "
                         f"depth value(s); nothing written")
    files = [(flags[0], out, _png(depth_codes(filled, units), flags[0], out))]
    if out_std is not None:
        files.append((flags[1], out_std, _png(depth_codes(std, units), flags[1], out_std)))
    if vis_dir is not None:
        pictures = [(vis_dir / f"{stem}_vis_depth.png", depth_picture(filled, vis_range=vis_range))]
        if std is not None:
            pictures.append((vis_dir / f"{stem}_vis_std.png", std_picture(std)))
        files += [(flags[2], path, _png(cv2.cvtColor(picture, cv2.COLOR_RGB2BGR), flags[2], path))
                  for path, picture in pictures]
    return files


def complete_holes(model, rgb: np.ndarray, depth: np.ndarray, K: np.ndarray, *, device: str, return_std: bool
                   ) -> tuple[np.ndarray, np.ndarray | None]:
    """``depth`` ((H, W) float32 metres, 0 = hole) of the (H, W, 3) uint8 image ``rgb`` with its holes filled by
    ``model`` (every valid pixel a measurement; ``K`` (3, 3) pixels): the filled depth (:func:`fill_holes`) and
    the model's std (metres; None without ``return_std``). Through :func:`crfdepth.api.complete_batch`, whose
    checks name ``image``, ``sparse`` and ``K`` (the LiDAR plausibility rules of ``complete_depth`` do not apply
    to a depth camera: its unit was checked as it was read)."""
    image = torch.from_numpy(np.ascontiguousarray(rgb.transpose(2, 0, 1)))[None].float().div_(255.0)
    sparse = torch.from_numpy(np.ascontiguousarray(depth, dtype=np.float32))[None, None]
    completed, std = api.complete_batch(image, sparse, torch.as_tensor(K, dtype=torch.float64), model=model,
                                        device=device, return_std=return_std)
    std = std[0].float().cpu().numpy() if std is not None else None
    return fill_holes(depth, completed[0].float().cpu().numpy()), std


# --------------------------------------------------------------------------- one frame


def complete_rgbd_frame(args: argparse.Namespace) -> int:
    """One RGB-D frame (module docstring): outputs checked, inputs read and checked, the model built, the holes
    filled and the files written together; returns 0."""
    from crfdepth.cli.complete_one import check_outputs, vis_folder

    needed = {"--image": args.image, "--depth": args.depth, "--out": args.out}
    missing = [flag for flag, value in needed.items() if value is None]
    if missing:
        raise InputError(f"an RGB-D frame needs --image, --depth, --out and --intrinsics or --known-camera; missing "
                         f"{', '.join(missing)}")
    stray = [flag for flag, value in (("--out-dir", args.out_dir), ("--out-std-dir", args.out_std_dir),
                                      ("--batch-size", None if args.batch_size == 1 else args.batch_size),
                                      ("--workers", None if args.workers == 0 else args.workers)) if value is not None]
    if stray:
        raise InputError(f"{', '.join(stray)}: folder options need --input-dir; for one frame use --out / --out-std")
    units = args.depth_units or "mm"
    inputs = {"--image": Path(args.image), "--depth": Path(args.depth)}
    if args.intrinsics is not None:
        inputs["--intrinsics"] = Path(args.intrinsics)
    out, out_std = check_outputs(args, inputs)
    return_std = out_std is not None or args.vis is not None
    with flagged("--image", args.image, labels=("image",)), quiet_decoders():
        check_image_file(args.image, f"--image {args.image}", device=args.device, dtype=args.dtype, mode=args.mode,
                         return_std=return_std, advice=cli_advice(args.device))
        rgb = read_rgb(args.image)
    with flagged("--depth", args.depth), quiet_decoders():
        depth = read_depth_image(args.depth, units, argument="--depth")
    check_depth_matches_image(depth.shape, rgb.shape[:2], depth_argument=f"--depth {args.depth}",
                              image_argument=f"--image {args.image}")
    camera = Camera.from_args(args)
    K = camera.K(rgb.shape[1], rgb.shape[0])
    model = build_model(args, registered_depth=True)
    start = time.perf_counter()
    where = {"image": f"--image {args.image}", "sparse": f"--depth {args.depth}", "K": camera.flag}
    with frame_errors(args, model, rgb.shape[:2], where):
        filled, std = complete_holes(model, rgb, depth, K, device=args.device, return_std=return_std)
    with vis_folder(args, out) as vis_dir:
        files = frame_files(filled, std, units, out, out_std, vis_dir, out.stem, args.vis_range,
                            ("--out", "--out-std", "--vis"))
        write_files(files)  # all of them, or none
    if args.recorder is not None:  # --rerun
        args.recorder.complete_frame(rgb, filled, std, sparse=depth, K=K)
    if not args.quiet:
        holes = int(np.sum(depth <= 0))
        print(f"wrote {', '.join(str(path) for _, path, _ in files)}: {depth.shape[1]}x{depth.shape[0]} depth in "
              f"{units}, {holes} hole pixel(s) filled ({100.0 * holes / depth.size:.0f}%), the {depth.size - holes} "
              f"measured kept, {float(filled.min()):.2f}-{float(filled.max()):.2f} m, in "
              f"{time.perf_counter() - start:.1f} s")
    return 0
