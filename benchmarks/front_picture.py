"""The front page's picture (``docs/own_sensors.jpg``), made from the own-sensor example of ``docs/example``.

Two 320 x 240 panels side by side: the 16-beam scan of ``docs/example/scan.pcd`` drawn on
``docs/example/image.png``, and the depth that ``crfdepth complete --weights paper`` makes of them (the
README's command-line example), each with its colour bar in metres; both share one depth range.

    python benchmarks/front_picture.py [--example docs/example] [--out docs/own_sensors.jpg]

The output is the same on every run up to the solver's floating point (one seed, no other randomness);
``tests/test_plots_benchmark.py`` regenerates it and compares it with the committed picture.
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence
from pathlib import Path

import cv2
import numpy as np

from crfdepth import CRFDepth, complete_depth
from crfdepth.inputs import points_to_sparse
from crfdepth.io.calibration import load_any_calibration
from crfdepth.io.files import atomic_write_bytes
from crfdepth.io.kitti import read_rgb
from crfdepth.io.pointcloud import read_points
from crfdepth.pictures.colour import depth_range, draw_points
from crfdepth.pictures.figures import depth_picture

ROOT = Path(__file__).resolve().parents[1]
PANEL = (320, 240)  # width, height of each panel's map, pixels
JPEG_QUALITY = 90


def front_picture(example: Path) -> np.ndarray:
    """(H, 2 * 320, 3) uint8 RGB: the scan on the image | the completed depth, with their colour bars."""
    rgb = read_rgb(example / "image.png")
    points = read_points(example / "scan.pcd")
    calibration = load_any_calibration(example / "rig.yaml")
    depth, _ = complete_depth(rgb, points=points, calibration=calibration, model=CRFDepth.from_pretrained("paper"),
                              return_std=False)
    sparse = points_to_sparse(points, calibration, rgb.shape[:2])
    lo, hi = depth_range(depth)
    small = [cv2.resize(a, PANEL, interpolation=cv2.INTER_AREA) for a in (rgb, depth)]
    # the scan at the panel's resolution: the nearest return of each 2 x 2 block
    h, w = sparse.shape
    blocks = np.where(sparse > 0, sparse, np.inf).reshape(h // 2, 2, w // 2, 2).min(axis=(1, 3))
    scan = np.where(np.isfinite(blocks), blocks, 0.0)
    bar = depth_picture(small[1], vis_range=(lo, hi))
    left = bar.copy()
    left[:PANEL[1], :PANEL[0]] = draw_points(small[0], scan, vmin=lo, vmax=hi, radius=1)
    return np.concatenate([left, np.full((bar.shape[0], 4, 3), 255, np.uint8), bar], axis=1)


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--example", type=Path, default=ROOT / "docs" / "example",
                        help="the folder of image.png, scan.pcd and rig.yaml (default: docs/example)")
    parser.add_argument("--out", type=Path, default=ROOT / "docs" / "own_sensors.jpg",
                        help="the JPEG to write (default: docs/own_sensors.jpg)")
    args = parser.parse_args(argv)
    if args.out.suffix.lower() not in (".jpg", ".jpeg"):
        parser.error(f"--out: expected a .jpg file, got {args.out}")
    picture = front_picture(args.example)
    ok, data = cv2.imencode(".jpg", cv2.cvtColor(picture, cv2.COLOR_RGB2BGR), [cv2.IMWRITE_JPEG_QUALITY, JPEG_QUALITY])
    if not ok:  # pragma: no cover - OpenCV encodes any uint8 RGB picture
        parser.error(f"--out: could not encode {args.out}")
    atomic_write_bytes(args.out, data.tobytes())
    print(f"wrote {args.out}: {picture.shape[1]}x{picture.shape[0]}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
