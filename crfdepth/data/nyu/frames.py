"""What the NYU v2 datasets share: the root check, frame names, and arrays -> :class:`~crfdepth.data.sample.Sample`.

Every NYU layout (:mod:`crfdepth.data.nyu`) lists its frames once, at construction, in sorted order,
and refuses a ``root`` that does not exist or holds no frame of its layout with an
:class:`~crfdepth.errors.InputError` naming ``root`` and what was looked for (docs/design.md
section 17).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

from crfdepth.data.kitti.loading import FrameDataset, PathLike, Transform, rgb_tensor
from crfdepth.data.nyu.camera import nyu_intrinsics
from crfdepth.data.sample import Sample
from crfdepth.errors import InputError
from crfdepth.io.depth_image import check_depth_matches_image, read_depth_image
from crfdepth.io.kitti import read_rgb

__all__ = ["FrameDataset", "PathLike", "Transform", "check_root", "frame_sample", "no_frames", "read_png_frame",
           "scene_name"]



def check_root(root: PathLike, layout: str, expected: str) -> Path:
    """``root`` as a Path to an existing folder; an InputError naming ``root``, the layout and what it holds
    (``expected``) otherwise."""
    path = Path(root)
    if not path.exists():
        raise InputError(f"root: expected a folder of the {layout} layout ({expected}), got {path}, which does not "
                         f"exist")
    if not path.is_dir():
        raise InputError(f"root: expected a folder of the {layout} layout ({expected}), got a file: {path}")
    return path


def no_frames(root: Path, layout: str, expected: str) -> InputError:
    """The error of a ``root`` that holds no frame of ``layout``."""
    return InputError(f"root: expected a folder of the {layout} layout ({expected}), got no frame in {root} or "
                      f"its sub-folders")


def scene_name(folder: Path, root: Path) -> str:
    """The scene a frame's ``folder`` under ``root`` stands for: its path from ``root`` joined by ``_``
    (``kitchen_0001``, ``a_kitchen``), or ``root``'s own name for a frame directly in ``root``."""
    parts = folder.relative_to(root).parts
    return "_".join(parts) if parts else (root.resolve().name or "nyu")


def frame_sample(rgb: np.ndarray, sparse: np.ndarray, target: np.ndarray, name: str, *, image_argument: str,
                 transform: Transform | None = None) -> Sample:
    """One NYU v2 frame's arrays -> a (transformed) :class:`Sample` with ``K`` from the image size
    (:func:`~crfdepth.data.nyu.camera.nyu_intrinsics`).

    Args:
        rgb: (H, W, 3) uint8 RGB.
        sparse, target: (H, W) float32 depth in metres, 0 = none, the size of ``rgb`` (checked by the caller).
        name: the sample name.
        image_argument: the image's name in messages (its file).
        transform: applied to the sample; None = none.
    """
    h, w = rgb.shape[:2]
    sample = Sample(
        image=rgb_tensor(rgb),
        sparse=torch.from_numpy(np.ascontiguousarray(sparse, dtype=np.float32))[None],
        target=torch.from_numpy(np.ascontiguousarray(target, dtype=np.float32))[None],
        K=nyu_intrinsics(w, h, argument=image_argument),
        name=name,
    )
    return transform(sample) if transform is not None else sample


def read_png_frame(image: Path, depths: tuple[Path, ...]) -> tuple[np.ndarray, list[np.ndarray]]:
    """The RGB image and the millimetre depth PNGs of one frame: (H, W, 3) uint8 and (H, W) float32 metres each.

    Raises:
        InputError: a depth file that cannot be read, is not 16-bit depth codes, has no valid pixel or does not
            look like millimetres (:func:`~crfdepth.io.depth_image.read_depth_image`, naming the file), or a
            depth image of another size than the RGB image (both files named).
    """
    rgb = read_rgb(image)
    arrays = []
    for depth in depths:
        array = read_depth_image(depth, "mm", argument=str(depth), units_argument=None)
        check_depth_matches_image(array.shape, rgb.shape, depth_argument=str(depth), image_argument=str(image))
        arrays.append(array)
    return rgb, arrays
