"""The own-sensor example shipped in ``docs/example/``: an image, a 16-beam scan and a rig file.

The README's "Your own sensors" commands run as printed on these files, so a new user can
try ``crfdepth complete --points ... --calib ...`` before pointing it at their own rig.
They are made from the built-in synthetic street (:func:`example_scene`, a
:func:`crfdepth.data.synthetic.make_scene` frame), which also gives the dense ground truth
to check the completed depth against:

- ``image.png``: 640 x 480 8-bit RGB, the scene's camera image (not a KITTI size),
  rendered without sensor noise so that the PNG stays small.
- ``scan.pcd``: the 16-beam LiDAR scan as a binary PCD (fields x y z intensity, float32),
  points in the LiDAR frame (x forward, y left, z up, metres). The scan is a full
  360-degree sweep; its horizontal resolution is 0.4 degrees (a 16-beam spinning LiDAR at
  20 Hz) to keep the file small.
- ``rig.yaml``: the rig calibration in the format of :mod:`crfdepth.io.calibration`
  (docs/design.md section 1): ``K`` of the image, ``T_cam_lidar`` (the LiDAR mounted like
  KITTI's: 0.27 m behind, 0.08 m above and 0.06 m to the right of the camera, axes
  aligned) and ``image_size``; no ``distortion`` (the image is a pinhole render).

Regenerate with ``python -m crfdepth.data.example docs/example``; the output is the same
on every run (one seed, no other randomness).
"""

from __future__ import annotations

import argparse
import logging
import os
import sys
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from crfdepth.data.synthetic import SyntheticScene, make_scene
from crfdepth.errors import InputError
from crfdepth.io.files import atomic_write_bytes
from crfdepth.io.pointcloud import write_pcd

__all__ = [
    "EXAMPLE_AZIMUTH_STEP_DEG",
    "EXAMPLE_BEAMS",
    "EXAMPLE_SEED",
    "EXAMPLE_SIZE",
    "ExampleFiles",
    "example_scene",
    "main",
    "write_example",
]

logger = logging.getLogger(__name__)

EXAMPLE_SEED = 3
"""Seed of the synthetic street the example is made from."""
EXAMPLE_SIZE = (480, 640)
"""(height, width) of the example image, pixels."""
EXAMPLE_BEAMS = 16
"""Beams of the example LiDAR."""
EXAMPLE_AZIMUTH_STEP_DEG = 0.4
"""Horizontal angle between two firings of a beam, degrees."""


@dataclass(frozen=True)
class ExampleFiles:
    """Paths of the three example files written by :func:`write_example`."""

    image: Path
    points: Path
    calibration: Path


def example_scene(seed: int = EXAMPLE_SEED) -> SyntheticScene:
    """The synthetic frame the example files are made from (with its dense ground truth).

    ``make_scene(seed, 480, 640, beams=16, azimuth_step_deg=0.4, image_noise_std=0)`` (no
    sensor noise: the PNG stays small); its ``depth`` /
    :meth:`~crfdepth.data.synthetic.SyntheticScene.target` is the ground truth of the
    example (metres, 0 = none).

    Raises:
        InputError: ``seed`` is not a non-negative integer.
    """
    height, width = EXAMPLE_SIZE
    return make_scene(seed, height, width, EXAMPLE_BEAMS, azimuth_step_deg=EXAMPLE_AZIMUTH_STEP_DEG,
                      image_noise_std=0.0)


def image_bytes(scene: SyntheticScene) -> bytes:
    """The scene's image as an 8-bit RGB PNG file's bytes (values rounded to 1/255)."""
    rgb = np.clip(np.rint(scene.image * 255.0), 0, 255).astype(np.uint8)
    ok, png = cv2.imencode(".png", np.ascontiguousarray(rgb[:, :, ::-1]), [cv2.IMWRITE_PNG_COMPRESSION, 9])
    if not ok:  # pragma: no cover - OpenCV encodes any uint8 image
        raise RuntimeError("OpenCV could not encode the example image as PNG")
    return png.tobytes()


def _number(value: float) -> str:
    """A matrix entry for the YAML file: rounded to 4 decimals, shortest form (``1.0``, ``0.06``)."""
    return repr(round(float(value), 4) + 0.0)  # + 0.0: no "-0.0"


def rig_yaml(scene: SyntheticScene, seed: int = EXAMPLE_SEED) -> str:
    """The rig calibration of ``scene`` as YAML text (K, T_cam_lidar, image_size)."""
    K, T = scene.K, scene.T_cam_lidar
    height, width = scene.image.shape[:2]
    k_rows = ",\n    ".join(f"[{', '.join(_number(v) for v in row)}]" for row in K)
    t_rows = "\n".join(f"  - [{', '.join(_number(v).rjust(5) for v in row)}]" for row in T)
    return (
        f"# Rig calibration of the crfdepth own-sensor example (synthetic street, seed {seed}).\n"
        "# Written by: python -m crfdepth.data.example docs/example\n"
        "# LiDAR -> camera, metres and pixels; camera frame x right, y down, z forward;\n"
        "# LiDAR frame x forward, y left, z up. p_cam = T_cam_lidar @ [x, y, z, 1].\n"
        f"K: [{k_rows}]\n"
        "T_cam_lidar:\n"
        f"{t_rows}\n"
        f"image_size: [{height}, {width}]\n"
    )


def write_example(folder: str | os.PathLike, *, seed: int = EXAMPLE_SEED) -> ExampleFiles:
    """Write ``image.png``, ``scan.pcd`` and ``rig.yaml`` of the own-sensor example into ``folder``.

    Args:
        folder: output folder; created (with its parents) if missing. Existing files of
            the same names are replaced (each written atomically).
        seed: seed of the synthetic street (default :data:`EXAMPLE_SEED`, the committed
            ``docs/example/``).

    Returns:
        The three paths. The image is (480, 640) 8-bit RGB; the scan (N, 4) float32
        x y z intensity in the LiDAR frame, metres (``example_scene(seed).points``); the
        calibration maps it into the image (:func:`crfdepth.io.calibration.load_any_calibration`).

    Raises:
        InputError: ``folder`` is an existing file, or ``seed`` is not a non-negative integer.
    """
    out = Path(folder)
    if out.exists() and not out.is_dir():
        raise InputError(f"folder: expected a folder for the example files, got a file: {out}")
    scene = example_scene(seed)
    out.mkdir(parents=True, exist_ok=True)
    files = ExampleFiles(image=out / "image.png", points=out / "scan.pcd", calibration=out / "rig.yaml")
    atomic_write_bytes(files.image, image_bytes(scene))
    write_pcd(files.points, scene.points, binary=True)
    atomic_write_bytes(files.calibration, rig_yaml(scene, seed).encode("ascii"))
    logger.info("wrote %s, %s (%d points), %s", files.image, files.points, len(scene.points), files.calibration)
    return files


def main(argv: Sequence[str] | None = None) -> int:
    """``python -m crfdepth.data.example OUT_DIR [--seed N]``: write the example files; exit status."""
    parser = argparse.ArgumentParser(
        prog="python -m crfdepth.data.example",
        description="Write the own-sensor example (image.png, scan.pcd, rig.yaml) made from the "
                    "built-in synthetic street into OUT_DIR (docs/example in the repository).",
    )
    parser.add_argument("out_dir", metavar="OUT_DIR", help="output folder (created if missing)")
    parser.add_argument("--seed", type=int, default=EXAMPLE_SEED,
                        help=f"seed of the synthetic street (default {EXAMPLE_SEED}: the committed files)")
    args = parser.parse_args(argv)
    try:
        files = write_example(args.out_dir, seed=args.seed)
    except InputError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    for path in (files.image, files.points, files.calibration):
        print(f"{path}  {path.stat().st_size / 1024:.0f} KB")
    return 0


if __name__ == "__main__":
    sys.exit(main())
