"""``crfdepth complete`` for one frame: ``--image`` with ``--sparse`` + ``--intrinsics``, or with ``--points``
+ ``--calib`` (see :mod:`crfdepth.cli.complete`)."""

from __future__ import annotations

import argparse
import logging
import time
from pathlib import Path

import numpy as np

from crfdepth import api
from crfdepth.cli.completion import frame_errors
from crfdepth.cli.model_options import build_model
from crfdepth.cli.outputs import make_output_dir, same_file, write_frame
from crfdepth.errors import InputError
from crfdepth.io.calibration import load_any_calibration
from crfdepth.io.files import check_output_file
from crfdepth.io.kitti import read_depth_png, read_intrinsics, read_rgb
from crfdepth.io.pointcloud import read_points
from crfdepth.memory import check_image_file, cli_advice

logger = logging.getLogger("crfdepth.cli.complete")  # the command's logger, whichever mode runs

__all__ = ["run_one"]


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


def run_one(args: argparse.Namespace) -> int:
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
        # an explicit --sparse-units overrules the guess about the rig (a camera more than 4 m up)
        inputs = dict(sparse=sparse, K=K, trust_units=args.sparse_units is not None)
        where = {"sparse": f"--sparse {args.sparse}", "K": f"--intrinsics {args.intrinsics}",
                 "image": f"--image {args.image}"}
    if np.array_equal(rgb[..., 0], rgb[..., 1]) and np.array_equal(rgb[..., 1], rgb[..., 2]):
        logger.warning("--image %s is greyscale; the colour potential sees intensity only", args.image)
    model = build_model(args)
    start = time.perf_counter()
    with frame_errors(args, model, rgb.shape[:2], where, None if points_mode else units):
        depth, std = api.complete_depth(rgb, model=model, device=args.device, trust_transform=args.trust_transform,
                                        return_std=out_std is not None or args.vis is not None, **inputs)
    vis_dir = None
    if args.vis is not None:  # created only once the frame is completed
        vis_dir = make_output_dir(args.vis, "--vis") if args.vis else out.parent
    written = write_frame(depth, std, out, out_std, vis_dir, out.stem, args.vis_range)
    if not args.quiet:
        print(f"wrote {', '.join(str(p) for p in written)}: {depth.shape[1]}x{depth.shape[0]} depth, "
              f"{float(depth.min()):.2f}-{float(depth.max()):.2f} m, in {time.perf_counter() - start:.1f} s")
    return 0
