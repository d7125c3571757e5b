"""``crfdepth demo``: the whole pipeline on a built-in scene (or real KITTI frames).

With no arguments it generates the built-in synthetic street scene (no download),
completes its simulated 64-beam LiDAR with the CRF through
:func:`crfdepth.api.complete_depth` (the ``--weights`` set, default kitti, in the structure
stored with it, kitti: pixel grid, log depth, occlusion gate; ``--mode`` overrides the
graph; the first line printed names the model run), prints the metrics against the scene's ground truth
next to the nearest-neighbour baseline, and writes to ``--out-dir`` (default
``./crfdepth_demo``):

- ``<name>_input.png``: the camera image with the LiDAR points drawn on it, coloured by
  depth like the depth picture, with its colour bar in metres;
- ``<name>_depth.png``: the dense depth (near = warm) with a colour bar in metres
  (:func:`crfdepth.pictures.figures.depth_picture`);
- ``<name>_std.png``: the standard deviation on a log scale with a colour bar in
  metres (:func:`crfdepth.pictures.figures.std_picture`, docs/design.md section 5);
- ``<name>_points.png``: the completed depth as a coloured 3D point cloud seen from
  above and behind the camera;
- ``data/<name>_depth16.png``: the depth as data, a KITTI uint16 PNG (metres * 256,
  docs/design.md section 1), in its own ``data/`` subfolder so that ``--out-dir`` itself
  holds only pictures.

The depth colours span the 2nd to 98th percentile of each frame's depth unless
``--vis-range MIN MAX`` fixes them (metres; the same colours for the same metres in every
frame). With ``--kitti DIR`` it does the same for the first ``--max-frames`` frames of a
``val_selection_cropped`` folder found under ``DIR`` (for instance ``../shared/data/kitti``).

Synthetic ground truth is dense up to the horizon; metrics use its pixels below the
first LiDAR scan line and up to 80 m, the part of the image KITTI's ground truth covers
(docs/design.md section 7).

With ``--rerun FILE.rrd`` it also writes a Rerun recording, one time step per frame: the camera, the image,
the LiDAR points in 3D and on the image, the depth and the std (:mod:`crfdepth.pictures.rerun_recording`); a
bare ``--rerun`` streams to a viewer.

Bad flags are refused when parsed; a ``--out-dir`` that is a file or not writable, a ``--rerun`` file not
ending in ``.rrd`` or in a folder that does not take new files, or a ``--kitti`` folder without frames, is
refused before any computation. Nothing is created before the inputs and the model are known to be good, and
every file appears atomically (the recording when the run ends, not at all when it fails).
"""

from __future__ import annotations

import argparse
import logging
import os
import time
from pathlib import Path

import numpy as np
import torch

from crfdepth.api import complete_depth
from crfdepth.checkpoints import load_pretrained, own_structure
from crfdepth.cli.arguments import MAX_SEED, VisRange, add_rerun_argument, int_at_least, seed_type, vis_range_type
from crfdepth.cli.model_options import model_line
from crfdepth.cli.outputs import rerun_recording
from crfdepth.data.synthetic import EVAL_MAX_DEPTH_M
from crfdepth.errors import InputError
from crfdepth.fill.nearest import nearest_fill
from crfdepth.io.kitti import write_depth_png
from crfdepth.metrics import average_metrics, depth_metrics, format_metrics
from crfdepth.pictures.colour import depth_range, draw_points, render_point_cloud
from crfdepth.pictures.figures import captioned, depth_picture, std_picture
from crfdepth.runs.outputs import is_inside, same_file, write_rgb_png
from crfdepth.weights import DEFAULT_WEIGHTS, WEIGHTS

logger = logging.getLogger(__name__)

DATA_FOLDER = "data"
"""Subfolder of ``--out-dir`` for the uint16 depth PNGs (data, not pictures)."""
PICTURES = ("input", "depth", "std", "points")
"""Kinds of picture written per frame, as ``<name>_<kind>.png``."""
MAX_BEAMS = 128
"""Most beams :func:`crfdepth.data.synthetic.make_scene` simulates (it accepts 1 to 128)."""


# --------------------------------------------------------------------------- flag parsing

# The defaults of the options that only one mode reads (None when parsed: not given, so that the other mode warns).
_DEFAULTS = {"seed": 0, "beams": 64, "max_frames": 2}


HELP = "run the full pipeline on a built-in scene (no download) or on KITTI frames"
DESCRIPTION = ("Complete the LiDAR of the built-in synthetic street scene (or of real KITTI "
               "frames with --kitti) and write pictures of the input, the dense depth, the "
               "uncertainty and the 3D point cloud (and the depth as uint16 PNG data in "
               f"OUT_DIR/{DATA_FOLDER}/).")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """The options of ``crfdepth demo``."""
    parser.add_argument("--kitti", metavar="DIR", default=None,
                        help="a KITTI folder holding depth_selection/val_selection_cropped (or that folder)")
    parser.add_argument("--out-dir", default="crfdepth_demo", metavar="DIR",
                        help=f"folder for the pictures, created if missing; the depth data go to "
                             f"DIR/{DATA_FOLDER}/ (default: ./crfdepth_demo)")
    parser.add_argument("--seed", type=seed_type(), default=None,
                        help=f"seed of the synthetic scene, 0 to {MAX_SEED} (default 0)")
    parser.add_argument("--beams", type=int_at_least(1, MAX_BEAMS), default=None,
                        help=f"beams of the simulated LiDAR, 1 to {MAX_BEAMS} (default 64)")
    own = ", ".join(f"{name}: {own_structure(name)['mode']}" for name in WEIGHTS)
    parser.add_argument("--mode", choices=("superpixel", "pixel"), default=None,
                        help=f"CRF graph (default: the weights' own structure ({own}))")
    parser.add_argument("--weights", choices=WEIGHTS, default=DEFAULT_WEIGHTS,
                        help=f"shipped weight set: kitti (learned on KITTI) or paper (hand-set); "
                             f"default: {DEFAULT_WEIGHTS}")
    parser.add_argument("--max-frames", type=int_at_least(1), default=None,
                        help="--kitti: frames to run, >= 1 (default 2)")
    parser.add_argument("--vis-range", nargs=2, type=vis_range_type, action=VisRange, default=None,
                        metavar=("MIN", "MAX"),
                        help="fixed depth colour range in metres, 0 < MIN < MAX, the same in every "
                             "frame (default: 2nd to 98th percentile of each frame's depth)")
    add_rerun_argument(parser, "the image, its LiDAR points, the depth and the std")


# --------------------------------------------------------------------------- checks and inputs


def _check_out_dir(path: str) -> Path:
    """``--out-dir`` as a Path: an existing writable folder, or one that can be created.

    Nothing is created. Raises InputError (a file in the way) or PermissionError.
    """
    directory = Path(path)
    for folder in (directory, directory / DATA_FOLDER):
        if folder.exists() and not folder.is_dir():
            raise InputError(f"--out-dir: expected a folder (existing or to create), got a file: {folder}")
    existing = directory.absolute()
    while not existing.exists():  # the nearest existing folder must let us create the rest
        existing = existing.parent
    if not existing.is_dir():
        raise InputError(f"--out-dir: expected a folder (existing or to create), got a path under the "
                         f"file {existing}")
    if not os.access(existing, os.W_OK | os.X_OK):
        raise PermissionError(f"--out-dir: expected a writable folder, got {existing} (not writable)")
    return directory


def _check_mode_options(args: argparse.Namespace) -> None:
    """A warning for each option given that the mode run does not read: ``--seed`` and ``--beams`` make the
    synthetic scene (ignored with ``--kitti``), ``--max-frames`` counts KITTI frames (ignored without it)."""
    if args.kitti is not None:
        for flag in (f for f in ("--seed", "--beams") if getattr(args, f[2:]) is not None):
            logger.warning("%s is ignored with --kitti (it sets the synthetic scene; the KITTI frames have their "
                           "own LiDAR)", flag)
    elif args.max_frames is not None:
        logger.warning("--max-frames is ignored without --kitti (the synthetic scene is one frame)")
    for name, default in _DEFAULTS.items():  # None: not given
        if getattr(args, name) is None:
            setattr(args, name, default)


def _make_dirs(directory: Path) -> Path:
    """Create ``directory`` and its data subfolder; returns the data subfolder."""
    data = directory / DATA_FOLDER
    try:
        data.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise PermissionError(f"--out-dir: expected a folder that can be created, got {directory} "
                              f"({exc.strerror})") from None
    return data


def _kitti_folder(root: Path) -> Path:
    candidates = [root, root / "val_selection_cropped", root / "depth_selection" / "val_selection_cropped"]
    folder = next((c for c in candidates if (c / "velodyne_raw").is_dir()), None)
    if folder is None:
        raise InputError(f"--kitti: expected a folder with depth_selection/val_selection_cropped/velodyne_raw "
                         f"under {root}, found none")
    return folder


def _frames(args: argparse.Namespace):
    """The frames to run, checked now, read lazily.

    Returns an iterator of (name, image (3, H, W) in [0, 1], sparse (H, W) metres,
    K (3, 3), target (H, W) metres, 0 = no ground truth) tensors.
    """
    if args.kitti is None:
        from crfdepth.data.synthetic import make_scene

        def synthetic():
            scene = make_scene(args.seed, beams=args.beams)
            t = scene.to_tensors()
            yield scene.name, t["image"], t["sparse"][0], t["K"], t["target"][0]

        return synthetic()
    from crfdepth.data.kitti import KittiValSelection

    dataset = KittiValSelection(_kitti_folder(Path(args.kitti)))

    def kitti():
        for i in range(min(len(dataset), args.max_frames)):
            s = dataset[i]
            yield s.name, s.image, s.sparse[0], s.K, s.target[0]

    return kitti()


# --------------------------------------------------------------------------- outputs


# Where the points picture's virtual camera stands, above and behind the real one (metres), and how far it looks
# down (degrees): 6 centres the street of a KITTI-like frame (12 left the picture's bottom third black).
_VIEW_LIFT_M, _VIEW_BACK_M, _VIEW_PITCH_DEG = 4.0, 10.0, 6.0


def _pictures(image: torch.Tensor, sparse: torch.Tensor, K: torch.Tensor, depth: np.ndarray,
              std: np.ndarray, vis_range: tuple[float, float]) -> dict[str, np.ndarray]:
    """The demo's pictures of one frame, keyed by :data:`PICTURES`."""
    rgb = (image.permute(1, 2, 0).numpy() * 255).round().astype(np.uint8)
    lidar = sparse.numpy()
    lo, hi = vis_range
    depth_rgb = depth_picture(depth, vis_range)
    # The input picture shares the depth picture's colours and bar: same range, same layout.
    input_rgb = depth_rgb.copy()
    h, w = depth.shape
    input_rgb[:h, :w] = draw_points(rgb, lidar, vmin=lo, vmax=hi)
    return {
        "input": input_rgb,
        "depth": depth_rgb,
        "std": std_picture(std),
        "points": captioned(render_point_cloud(depth, rgb, K.numpy(), max_depth=min(hi, EVAL_MAX_DEPTH_M),
                                               lift_m=_VIEW_LIFT_M, back_m=_VIEW_BACK_M, pitch_deg=_VIEW_PITCH_DEG),
                            f"the depth in 3D, coloured by the image, seen from {_VIEW_LIFT_M:g} m above and "
                            f"{_VIEW_BACK_M:g} m behind the camera (black: out of its view)"),
    }


def run(args: argparse.Namespace) -> int:
    """Run the demo; returns 0.

    Prints the model line (``model: kitti weights, pixel grid, log depth, occlusion gate``:
    the weights in their own structure unless ``--mode`` overrides it), then per frame one
    metrics line per method and one line per written file group, then a last line saying
    what was written where.
    """
    _check_mode_options(args)
    out_dir = _check_out_dir(args.out_dir)
    if args.kitti is not None:  # the pictures and data/ would be written among the frames read
        frames = _kitti_folder(Path(args.kitti))
        for folder in (out_dir, out_dir / DATA_FOLDER):
            if same_file(folder, frames) or is_inside(folder, frames):
                raise InputError(f"--out-dir: {folder} is or lies inside the --kitti frames {frames}; refusing to "
                                 f"write among the inputs, choose a folder outside it")
    with rerun_recording(args) as recorder:  # checked now, written when the run ends
        return _demo(args, out_dir, recorder)


def _demo(args: argparse.Namespace, out_dir: Path, recorder) -> int:
    """:func:`run` once ``--out-dir`` and ``--rerun`` are checked; the frames logged into ``recorder`` (or None)."""
    frames = _frames(args)
    overrides = {} if args.mode is None else {"mode": args.mode}
    model = load_pretrained(args.weights, **overrides)
    data_dir = _make_dirs(out_dir)
    print(model_line(model, f"{args.weights} weights", overrides, own_structure(args.weights) if overrides else None))
    start = time.perf_counter()
    count = 0
    for name, image, sparse, K, target in frames:
        t0 = time.perf_counter()
        depth, std = complete_depth(image, sparse=sparse, K=K, model=model, return_std=True)
        seconds = time.perf_counter() - t0
        crf = average_metrics(depth_metrics(depth, target))
        nn = average_metrics(depth_metrics(nearest_fill(sparse), target))
        print(f"{name}  ({crf['pixels']} ground-truth pixels, CRF {seconds:.2f} s)")
        print(f"  crfdepth          {format_metrics(crf)}")
        print(f"  nearest-neighbour {format_metrics(nn)}")
        depth_np, std_np = depth.cpu().numpy(), std.cpu().numpy()
        vis_range = args.vis_range if args.vis_range is not None else depth_range(depth_np)
        for kind, picture in _pictures(image, sparse, K, depth_np, std_np, vis_range).items():
            write_rgb_png(out_dir / f"{name}_{kind}.png", picture, "--out-dir")
        print(f"  pictures: {out_dir / name}_{{{','.join(PICTURES)}}}.png (depth colours "
              f"{vis_range[0]:.3g}-{vis_range[1]:.3g} m)")
        write_depth_png(data_dir / f"{name}_depth16.png", depth_np)
        print(f"  data:     {data_dir / name}_depth16.png (uint16 KITTI PNG, metres * 256)")
        if recorder is not None:
            recorder.complete_frame(image, depth_np, std_np, sparse=sparse, K=K)
        count += 1
    print(f"wrote {len(PICTURES)} pictures per frame for {count} frame(s) to {out_dir.resolve()} and the "
          f"depth data to {data_dir.resolve()} ({time.perf_counter() - start:.1f} s in all)")
    return 0
