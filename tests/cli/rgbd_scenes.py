"""Small synthetic RGB-D frames for the tests of ``crfdepth complete --depth`` and ``evaluate --layout nyu_*``.

:func:`scene` is a known answer: a slanted wall with a box in front of it, seen by NYU Depth v2's camera scaled to
160x120 (``--known-camera nyu``), the depth camera's holes cut where a Kinect has them (blocks on dark or shiny
surfaces, a ring at the box's depth edge, scattered pixels). :func:`write_pair` / :func:`write_sync_folder` write it
as the files the commands read: a JPEG or PNG image and a 16-bit depth PNG in a unit.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from crfdepth.io.depth_image import CODES_PER_METRE

HEIGHT, WIDTH = 120, 160  # a quarter of NYU's 640x480: --known-camera nyu scales its K
WALL_BLOCK = np.s_[60:76, 10:30]  # a hole inside the wall (rows, columns)
BOX_BLOCK = np.s_[45:60, 65:85]  # a hole inside the box


@dataclass(frozen=True)
class Scene:
    """``rgb`` (H, W, 3) uint8; ``depth`` (H, W) float32 metres, the true depth everywhere; ``measured`` the depth
    camera's image of it (0 = hole); ``holes`` the (H, W) bool mask of its holes; ``box`` the box's pixels."""

    rgb: np.ndarray
    depth: np.ndarray
    measured: np.ndarray
    holes: np.ndarray
    box: np.ndarray


def scene(seed: int = 0) -> Scene:
    """The wall (3.0 m, receding to the right and down) and the box (1.6 m) of frame ``seed`` (the scattered holes
    and the image noise depend on it)."""
    rng = np.random.default_rng(seed)
    v, u = np.mgrid[0:HEIGHT, 0:WIDTH].astype(np.float64)
    box = (u >= 50) & (u < 110) & (v >= 30) & (v < 90)
    depth = np.where(box, 1.6, 3.0 + 0.004 * u + 0.002 * v)
    rgb = np.empty((HEIGHT, WIDTH, 3), np.int64)
    rgb[...] = (170, 180, 200)
    rgb[box] = (220, 120, 40)
    rgb = np.clip(rgb + rng.integers(-6, 7, size=rgb.shape), 0, 255).astype(np.uint8)
    holes = np.zeros((HEIGHT, WIDTH), bool)
    holes[WALL_BLOCK] = True
    holes[BOX_BLOCK] = True
    mask = box.astype(np.uint8)
    kernel = np.ones((3, 3), np.uint8)
    holes |= (cv2.dilate(mask, kernel) > 0) & ~(cv2.erode(mask, kernel) > 0)  # the ring at the depth edge
    holes |= rng.random((HEIGHT, WIDTH)) < 0.1
    measured = np.where(holes, 0.0, depth)
    return Scene(rgb, depth.astype(np.float32), measured.astype(np.float32), holes, box)


def codes(metres: np.ndarray, units: str = "mm") -> np.ndarray:
    """(H, W) uint16 codes of ``metres`` in ``units`` (0 stays 0)."""
    return np.clip(np.rint(metres * CODES_PER_METRE[units]), 0, 65535).astype(np.uint16)


def write_pair(image: Path, depth: Path, frame: Scene, units: str = "mm") -> tuple[Path, Path]:
    """``frame``'s image (format by ``image``'s suffix) and depth PNG in ``units``; returns the two paths."""
    image.parent.mkdir(parents=True, exist_ok=True)
    depth.parent.mkdir(parents=True, exist_ok=True)
    assert cv2.imwrite(str(image), cv2.cvtColor(frame.rgb, cv2.COLOR_RGB2BGR))
    assert cv2.imwrite(str(depth), codes(frame.measured, units))
    return image, depth


def write_sync_folder(folder: Path, count: int = 3, suffix: str = ".jpg") -> list[Scene]:
    """``count`` frames in NYU's sync layout (``rgb_0000N.jpg`` + ``sync_depth_0000N.png``, millimetres)."""
    frames = [scene(seed) for seed in range(count)]
    for index, frame in enumerate(frames):
        write_pair(folder / f"rgb_{index:05d}{suffix}", folder / f"sync_depth_{index:05d}.png", frame)
    return frames


def read_codes(path: Path) -> np.ndarray:
    """A 16-bit PNG's codes, unchanged."""
    image = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    assert image is not None and image.dtype == np.uint16 and image.ndim == 2, path
    return image
