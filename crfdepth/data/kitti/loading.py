"""The one loading path of every KITTI dataset: arrays from a frame's files -> a :class:`Sample`.

:func:`load_sample` checks that RGB, sparse depth and ground truth agree in size, converts
them to tensors in the library convention (docs/design.md section 1) and applies the
dataset's transform. The folder checks shared by the layouts raise ``FileNotFoundError``
for a root that does not exist and :class:`~crfdepth.errors.InputError` for a root that
does not match the layout or holds no frame.
"""

from __future__ import annotations

import os
import re
from collections.abc import Callable, Sequence
from pathlib import Path

import numpy as np
import torch
from torch.utils.data import Dataset

from crfdepth.data.sample import Sample
from crfdepth.errors import InputError

__all__ = ["CAMERAS", "DRIVE_NAME", "FrameDataset", "check_cameras", "PathLike", "Transform", "load_sample", "no_frames", "require_dir", "require_root", "rgb_tensor"]

PathLike = str | os.PathLike
Transform = Callable[[Sample], Sample]

#: The colour cameras of KITTI's depth-completion trees, and a raw drive's folder name (its date in group 1).
CAMERAS = ("image_02", "image_03")
DRIVE_NAME = re.compile(r"^(\d{4}_\d{2}_\d{2})_drive_\d{4}_sync$")


def check_cameras(camera: str | Sequence[str]) -> tuple[str, ...]:
    """``camera`` ("image_02", "image_03" or both) as a tuple; InputError naming ``camera`` otherwise."""
    cameras = (camera,) if isinstance(camera, str) else tuple(camera)
    if not cameras or any(c not in CAMERAS for c in cameras):
        raise InputError(f"camera: expected 'image_02', 'image_03' or both, got {camera!r}")
    return cameras


class FrameDataset(Dataset):
    """A dataset of the frames its constructor lists in ``self._frames`` (each with a ``name``), in
    that order: their count and names."""

    _frames: list

    def __len__(self) -> int:
        return len(self._frames)

    @property
    def names(self) -> list[str]:
        """Sample names in dataset order."""
        return [f.name for f in self._frames]


def load_sample(
    rgb: np.ndarray,
    sparse: np.ndarray,
    target: np.ndarray | None,
    K: np.ndarray,
    name: str,
    files: dict[str, Path],
    transform: Transform | None = None,
) -> Sample:
    """Arrays from one frame's files -> a (transformed) :class:`Sample`.

    Args:
        rgb: (H, W, 3) uint8 RGB.
        sparse: (H, W) float32 LiDAR z-depth in metres, 0 = no return.
        target: (H, W) float32 ground truth in metres, 0 = none; None when the frame has no
            ground truth (gives an all-zero target and ``has_target=False``).
        K: (3, 3) intrinsics of ``rgb`` (pixels).
        name: the sample name.
        files: ``{"image": path, "sparse": path, "target": path}`` (those that exist),
            only used to name the files in error messages.
        transform: applied to the assembled sample; None = none.

    Raises:
        InputError: ``sparse`` or ``target`` is not the size of ``rgb`` (files and sizes
            named).
    """
    h, w = rgb.shape[:2]
    for key, array in (("sparse", sparse), ("target", target)):
        if array is not None and array.shape != (h, w):
            raise InputError(
                f"{name}: RGB and depth sizes differ: image {files.get('image')} is {h}x{w} (HxW) "
                f"but {key} {files.get(key)} is {array.shape[0]}x{array.shape[1]}"
            )
    image_t = rgb_tensor(rgb)
    sparse_t = torch.from_numpy(np.ascontiguousarray(sparse, dtype=np.float32))[None]
    if target is None:
        target_t = torch.zeros_like(sparse_t)
    else:
        target_t = torch.from_numpy(np.ascontiguousarray(target, dtype=np.float32))[None]
    sample = Sample(
        image=image_t,
        sparse=sparse_t,
        target=target_t,
        K=torch.as_tensor(np.asarray(K, dtype=np.float64)).to(torch.float32),
        name=name,
        has_target=target is not None,
    )
    return transform(sample) if transform is not None else sample


def rgb_tensor(rgb: np.ndarray) -> torch.Tensor:
    """(H, W, 3) uint8 RGB -> (3, H, W) float32 in [0, 1], the layout of :attr:`Sample.image`."""
    return torch.from_numpy(np.ascontiguousarray(rgb.transpose(2, 0, 1))).to(torch.float32) / 255.0


def require_root(root: PathLike, what: str = "root") -> Path:
    """``root`` as a Path to an existing folder (``what`` names the argument in messages)."""
    root = Path(root)
    if not root.exists():
        raise FileNotFoundError(f"{what}: dataset folder does not exist: {root}")
    if not root.is_dir():
        raise InputError(f"{what}: expected a directory, got a file: {root}")
    return root


def require_dir(path: Path, root: Path, layout: str) -> Path:
    """``path``, a folder the ``layout`` needs under ``root``; InputError naming it when missing."""
    if not path.is_dir():
        raise InputError(f"{layout}: expected {path} (root {root} does not match the {layout} layout)")
    return path


def no_frames(root: Path, layout: str, looked: str) -> InputError:
    """The error for a ``layout`` folder that holds no frame (``looked``: the pattern searched)."""
    return InputError(f"{layout}: found no frames under {root} (looked for {looked})")

