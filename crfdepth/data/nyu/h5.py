"""NYU v2 in the HDF5 release of Sparse-to-Dense (Ma & Karaman, ICRA 2018): ``nyudepthv2/{train,val}/<scene>/<n>.h5``.

The training data of every NYU v2 depth-completion paper since (CSPN, NLSPN, CompletionFormer,
BP-Net): 47584 training frames of 249 scenes and the 654 frames of the official test split as
``val`` (docs/design.md section 17). Each file holds ``rgb``, uint8 (3, 480, 640), and ``depth``,
float32 (480, 640) metres, in-painted (dense). Reading needs h5py, the optional extra
``pip install "crfdepth[nyu]"``.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from crfdepth.data.nyu.camera import NYU_HEIGHT, NYU_WIDTH
from crfdepth.data.nyu.frames import FrameDataset, PathLike, Transform, check_root, frame_sample, no_frames, scene_name
from crfdepth.data.sample import Sample
from crfdepth.errors import InputError
from crfdepth.io.depth_image import check_depth_units

__all__ = ["EXTRA_HINT", "SPLITS", "NyuH5"]

EXTRA_HINT = 'pip install "crfdepth[nyu]"'
#: The splits of the release, folders of the ``nyudepthv2`` folder.
SPLITS = ("train", "val")
_EXPECTED = "nyudepthv2/{train,val}/<scene>/<n>.h5"
_SHAPES = {"rgb": ((3, NYU_HEIGHT, NYU_WIDTH), "uint8 RGB"), "depth": ((NYU_HEIGHT, NYU_WIDTH), "float metres")}


def _h5py():
    try:
        import h5py
    except ImportError:
        raise InputError(f"NyuH5: expected the h5py package (to read HDF5 files), got it not installed; "
                         f"{EXTRA_HINT}") from None
    return h5py


@dataclass(frozen=True)
class _H5Frame:
    name: str
    file: Path


class NyuH5(FrameDataset):
    """NYU v2 frames of the Sparse-to-Dense HDF5 release.

    Each ``<scene>/<n>.h5`` is one frame: the 640 x 480 image, ``sparse`` = ``target`` = its depth
    (metres, 0 = none), ``K`` = :data:`~crfdepth.data.nyu.camera.NYU_K`, the name ``<scene>_<n>``.
    The protocol transform (:func:`~crfdepth.data.sampling.nyu_protocol`) then resizes, crops and
    draws the sparse samples from the target.

    Args:
        root: the ``nyudepthv2`` folder (holding ``train/`` and ``val/``) or one split's folder (its
            scene folders; searched at any depth).
        transform: applied to every sample; default None (the frame as stored).
        split: ``"train"``, ``"val"`` or None. With the ``nyudepthv2`` folder, the split read (None:
            both, train first); with a split's folder, None or that folder's own name.

    Raises:
        InputError: h5py is not installed (``pip install "crfdepth[nyu]"``); ``root`` does not exist or
            holds no ``.h5`` file; ``split`` is not one of the splits or has no folder under ``root``.
            On ``__getitem__``: a file without ``rgb`` or ``depth``, with another shape or dtype (file,
            key, expected and received shape named), or whose depth has no valid pixel or is not metres
            (:func:`~crfdepth.io.depth_image.check_depth_units`).
    """

    def __init__(self, root: PathLike, transform: Transform | None = None, split: str | None = None) -> None:
        _h5py()
        if split is not None and split not in SPLITS:
            raise InputError(f"split: expected one of {', '.join(map(repr, SPLITS))} or None, got {split!r}")
        self.root = check_root(root, "NyuH5", _EXPECTED)
        self.transform = transform
        self.split = split
        if any((self.root / s).is_dir() for s in SPLITS):
            wanted = SPLITS if split is None else (split,)
            folders = [self.root / s for s in wanted if (self.root / s).is_dir()]
            if not folders:
                raise InputError(f"split: expected a {split}/ folder in {self.root} (the {_EXPECTED} layout), got "
                                 f"none")
        elif split is not None and self.root.name in SPLITS and self.root.name != split:
            raise InputError(f"split: expected {self.root.name!r} or None for the {self.root.name}/ folder "
                             f"{self.root}, got {split!r}")
        else:
            folders = [self.root]
        frames = []
        for folder in folders:
            for file in sorted(folder.rglob("*.h5")):
                if file.is_file():
                    frames.append(_H5Frame(f"{scene_name(file.parent, folder)}_{file.stem}", file))
        if not frames:
            raise no_frames(self.root, "NyuH5", _EXPECTED)
        self._frames = frames

    def __getitem__(self, index: int) -> Sample:
        f = self._frames[index]
        rgb, depth = read_h5_frame(f.file)
        return frame_sample(rgb.transpose(1, 2, 0), depth, depth.copy(), f.name, image_argument=str(f.file),
                            transform=self.transform)


def read_h5_frame(file: Path) -> tuple[np.ndarray, np.ndarray]:
    """``rgb`` (3, 480, 640) uint8 and ``depth`` (480, 640) float32 metres of one HDF5 file, checked.

    Raises:
        InputError: the file cannot be read as HDF5; a key missing; another shape or dtype; a depth with no
            valid pixel or not in metres. Messages name the file and the key.
    """
    h5py = _h5py()
    try:
        with h5py.File(file, "r") as h5:
            arrays = {}
            for key, (shape, what) in _SHAPES.items():
                if key not in h5:
                    raise InputError(f"{file}: expected a dataset {key!r} of shape {shape} ({what}), got the keys "
                                     f"{sorted(h5.keys())}")
                value = h5[key]
                if not isinstance(value, h5py.Dataset) or tuple(value.shape) != shape or not _dtype_ok(key, value):
                    got = (f"shape {tuple(value.shape)} {value.dtype}" if isinstance(value, h5py.Dataset)
                           else "a group")
                    raise InputError(f"{file}: expected {key!r} of shape {shape} ({what}), got {got}")
                arrays[key] = value[()]
    except OSError as exc:
        raise InputError(f"{file}: expected an HDF5 file of the {_EXPECTED} layout, got one that does not open "
                         f"({exc})") from None
    depth = arrays["depth"].astype(np.float32)
    check_depth_units(depth, "m", f"{file}: 'depth'", units_argument=None)
    return arrays["rgb"], np.where(np.isfinite(depth) & (depth > 0), depth, np.float32(0))


def _dtype_ok(key: str, value) -> bool:
    return value.dtype == np.uint8 if key == "rgb" else value.dtype.kind == "f"
