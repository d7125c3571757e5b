"""``crfdepth demo``: the whole pipeline on a built-in scene (or real KITTI frames).

With no arguments it generates the built-in synthetic street scene (no download),
completes its simulated 64-beam LiDAR with the CRF, prints the metrics against the
scene's ground truth next to the nearest-neighbour baseline, and writes to a folder:

- ``<name>_input.png``: the camera image with the LiDAR points drawn on it;
- ``<name>_depth.png``: the dense depth, coloured (near = warm);
- ``<name>_std.png``: the posterior standard deviation, coloured;
- ``<name>_points.png``: the completed depth as a coloured 3D point cloud seen from
  above and behind the camera;
- ``<name>_depth16.png``: the depth as a KITTI uint16 PNG (metres * 256).

With ``--kitti DIR`` it does the same for the frames of a ``val_selection_cropped``
folder found under ``DIR`` (for instance ``../shared/data/kitti``).

Synthetic ground truth is dense up to the horizon; metrics use its pixels below the
first LiDAR scan line and up to 80 m, the part of the image KITTI's ground truth covers.
"""

from __future__ import annotations

import argparse
import logging
import time
from pathlib import Path

import cv2
import numpy as np
import torch

from crfdepth.errors import InputError
from crfdepth.fill import nearest_fill
from crfdepth.io.kitti import write_depth_png
from crfdepth.metrics import average_metrics, depth_metrics, format_metrics
from crfdepth.pretrained import DEFAULT_WEIGHTS, WEIGHTS, load_pretrained
from crfdepth.data.synthetic import EVAL_MAX_DEPTH_M
from crfdepth.visualize import colorize_depth, colorize_std, draw_points, render_point_cloud

logger = logging.getLogger(__name__)


def add_parser(subparsers: argparse._SubParsersAction) -> argparse.ArgumentParser:
    """Register the ``demo`` sub-command on ``subparsers`` (sets ``func=run``)."""
    parser = subparsers.add_parser(
        "demo",
        help="run the full pipeline on a built-in scene (no download) or on KITTI frames",
        description="Complete the LiDAR of the built-in synthetic street scene (or of real KITTI "
                    "frames with --kitti) and write pictures of the input, the dense depth, the "
                    "uncertainty and the 3D point cloud.",
    )
    parser.add_argument("--kitti", metavar="DIR", default=None,
                        help="a KITTI folder holding depth_selection/val_selection_cropped (or that folder)")
    parser.add_argument("--out-dir", default="crfdepth_demo", metavar="DIR",
                        help="folder for the pictures (created; default: ./crfdepth_demo)")
    parser.add_argument("--seed", type=int, default=0, help="seed of the synthetic scene (default 0)")
    parser.add_argument("--beams", type=int, default=64, help="beams of the simulated LiDAR (default 64)")
    parser.add_argument("--mode", choices=("superpixel", "pixel"), default="superpixel",
                        help="CRF graph (default: superpixel)")
    parser.add_argument("--weights", choices=WEIGHTS, default=DEFAULT_WEIGHTS,
                        help=f"shipped weight set: kitti (learned on KITTI) or paper (hand-set); "
                             f"default: {DEFAULT_WEIGHTS}")
    parser.add_argument("--max-frames", type=int, default=2, help="KITTI frames to run (default 2)")
    parser.set_defaults(func=run)
    return parser


def _frames(args):
    """Yield (name, image (1,3,H,W), sparse (1,1,H,W), K (1,3,3), target (1,1,H,W))."""
    if args.kitti is None:
        from crfdepth.data.synthetic import make_scene

        scene = make_scene(args.seed, beams=args.beams)
        t = scene.to_tensors()
        yield scene.name, t["image"][None], t["sparse"][None], t["K"][None], t["target"][None]
        return
    from crfdepth.data.kitti import KittiValSelection

    root = Path(args.kitti)
    candidates = [root, root / "val_selection_cropped", root / "depth_selection" / "val_selection_cropped"]
    folder = next((c for c in candidates if (c / "velodyne_raw").is_dir()), None)
    if folder is None:
        raise InputError(f"--kitti: expected a folder with depth_selection/val_selection_cropped/velodyne_raw "
                         f"under {root}, found none")
    dataset = KittiValSelection(folder)
    for i in range(min(len(dataset), args.max_frames)):
        s = dataset[i]
        yield s.name, s.image[None], s.sparse[None], s.K[None], s.target[None]


def run(args: argparse.Namespace) -> int:
    """Run the demo; returns 0. Prints one metrics line per method and frame."""
    out_dir = Path(args.out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    model = load_pretrained(args.weights, mode=args.mode)
    start = time.perf_counter()
    for name, image, sparse, K, target in _frames(args):
        t0 = time.perf_counter()
        with torch.no_grad():
            out = model(image, sparse, K, return_std=True)
        seconds = time.perf_counter() - t0
        crf = average_metrics(depth_metrics(out.depth, target))
        nn = average_metrics(depth_metrics(nearest_fill(sparse), target))
        print(f"{name}  ({crf['pixels']} ground-truth pixels, CRF {seconds:.2f} s)")
        print(f"  crfdepth         {format_metrics(crf)}")
        print(f"  nearest-neighbour {format_metrics(nn)}")
        rgb = (image[0].permute(1, 2, 0).numpy() * 255).round().astype(np.uint8)
        depth = out.depth[0, 0].numpy()
        vmax = float(np.percentile(depth, 98))
        pictures = {
            "input": draw_points(rgb, sparse[0, 0].numpy(), vmax=vmax),
            "depth": colorize_depth(depth, vmax=vmax),
            "std": colorize_std(out.std[0, 0].numpy()),
            "points": render_point_cloud(depth, rgb, K[0].numpy(), max_depth=min(vmax, EVAL_MAX_DEPTH_M)),
        }
        for kind, picture in pictures.items():
            path = out_dir / f"{name}_{kind}.png"
            if not cv2.imwrite(str(path), cv2.cvtColor(picture, cv2.COLOR_RGB2BGR)):
                raise PermissionError(f"--out-dir: could not write {path}")
        write_depth_png(out_dir / f"{name}_depth16.png", depth)
    print(f"wrote pictures to {out_dir.resolve()} ({time.perf_counter() - start:.1f} s in all)")
    return 0
