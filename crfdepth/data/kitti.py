"""Torch datasets for every KITTI layout crfdepth reads (DESIGN.md sections 1 and 7).

All four datasets return a :class:`~crfdepth.data.sample.Sample` built by one loading path
(:func:`load_sample`): read RGB, sparse depth, ground truth and ``K`` from files, check
that their sizes agree, convert to tensors, then apply the dataset's ``transform``.

- :class:`KittiDepthCompletion`: the official ``data_depth_velodyne`` /
  ``data_depth_annotated`` trees, RGB and calibration from the raw-data tree; target =
  KITTI's semi-dense annotation.
- :class:`KittiValSelection`: ``depth_selection/val_selection_cropped``; annotated target.
- :class:`KittiTestCompletion`: ``depth_selection/test_depth_completion_anonymous``; no
  target (all zeros, ``has_target=False``).
- :class:`KittiRawScans`: raw-data drives or the object benchmark with Velodyne scans,
  projected here; target = LiDAR points held out of the input.

Files are listed once, at construction, in sorted (deterministic) order; a layout that
does not match, or one that holds no frame, raises at construction rather than giving an
empty dataset.

Errors: a ``root`` that does not exist raises ``FileNotFoundError`` with the path; a root
without the expected sub-folders, zero frames, an input without its target/RGB file, or RGB
and depth of different sizes raise :class:`~crfdepth.errors.InputError` naming the folder,
file(s) and sizes.
"""

from __future__ import annotations

import os
import re
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import numpy as np
import torch
from torch.utils.data import Dataset

from crfdepth import projection
from crfdepth.data.sample import Sample
from crfdepth.data.transforms import BottomCenterCrop, frame_seed
from crfdepth.errors import InputError
from crfdepth.io.kitti import (
    Calibration,
    read_depth_png,
    read_intrinsics,
    read_object_calibration,
    read_raw_calibration,
    read_rgb,
    read_velodyne,
)

__all__ = [
    "KittiDepthCompletion",
    "KittiRawScans",
    "KittiTestCompletion",
    "KittiValSelection",
    "load_sample",
]

PathLike = str | os.PathLike
Transform = Callable[[Sample], Sample]

_CAMERAS = ("image_02", "image_03")
_DRIVE = re.compile(r"^(\d{4}_\d{2}_\d{2})_drive_\d{4}_sync$")


# --------------------------------------------------------------------------- shared loading


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
    image_t = torch.from_numpy(np.ascontiguousarray(rgb.transpose(2, 0, 1))).to(torch.float32) / 255.0
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


def _require_root(root: PathLike, what: str = "root") -> Path:
    root = Path(root)
    if not root.exists():
        raise FileNotFoundError(f"{what}: dataset folder does not exist: {root}")
    if not root.is_dir():
        raise InputError(f"{what}: expected a directory, got a file: {root}")
    return root


def _require_dir(path: Path, root: Path, layout: str) -> Path:
    if not path.is_dir():
        raise InputError(f"{layout}: expected {path} (root {root} does not match the {layout} layout)")
    return path


def _no_frames(root: Path, layout: str, looked: str) -> InputError:
    return InputError(f"{layout}: found no frames under {root} (looked for {looked})")


def _resolve_subfolder(root: Path, name: str, marker: str) -> Path:
    """Accept either ``.../<name>`` itself or its parent (``depth_selection``)."""
    if not (root / marker).is_dir() and (root / name / marker).is_dir():
        return root / name
    return root


def _check_cameras(camera: str | Sequence[str]) -> tuple[str, ...]:
    cameras = (camera,) if isinstance(camera, str) else tuple(camera)
    if not cameras or any(c not in _CAMERAS for c in cameras):
        raise InputError(f"camera: expected 'image_02', 'image_03' or both, got {camera!r}")
    return cameras


# --------------------------------------------------------------------------- official layout


@dataclass(frozen=True)
class _CompletionFrame:
    drive: str
    camera: str
    frame: str
    sparse: Path
    target: Path
    image: Path
    day_dir: Path

    @property
    def name(self) -> str:
        return f"{self.drive}_velodyne_raw_{self.frame}_{self.camera}"


class KittiDepthCompletion(Dataset):
    """KITTI depth completion, official layout (``data_depth_velodyne`` + ``data_depth_annotated``).

    Frames are the ``velodyne_raw`` PNGs
    ``root/data_depth_velodyne/<split>/<drive>/proj_depth/velodyne_raw/<camera>/<frame>.png``;
    each needs its ground truth
    ``root/data_depth_annotated/<split>/<drive>/proj_depth/groundtruth/<camera>/<frame>.png``,
    its RGB image ``raw_root/<date>/<drive>/<camera>/data/<frame>.png`` and the day's
    calibration ``raw_root/<date>/calib_cam_to_cam.txt`` (``K = P_rect_0X[:, :3]``, the
    intrinsics of the full 1242 x 375 frame; the transform moves them with the crop).

    Sample names follow ``val_selection_cropped``'s ``velodyne_raw`` file names,
    ``<drive>_velodyne_raw_<frame>_<camera>``, ordered by (drive, frame, camera).

    Args:
        root: folder holding ``data_depth_velodyne/`` and ``data_depth_annotated/``.
        split: "train" or "val".
        camera: "image_02", "image_03" or both (default both).
        raw_root: root of the KITTI raw data (holding ``<date>/``). None means
            ``<root>/../raw`` (the layout of the shared test data,
            ``kitti/{depth_completion,raw}``).
        transform: applied to every sample; default ``BottomCenterCrop(352, 1216)``;
            None for full-size frames.

    Raises:
        FileNotFoundError: ``root`` or ``raw_root`` does not exist.
        InputError: ``root/data_depth_velodyne/<split>`` or the annotated folder is missing;
            no frame found; a frame's ground truth, RGB image or calibration is missing
            (path named). On ``__getitem__``: RGB and depth sizes differ.
    """

    def __init__(
        self,
        root: PathLike,
        split: Literal["train", "val"] = "train",
        camera: str | Sequence[str] = _CAMERAS,
        raw_root: PathLike | None = None,
        transform: Transform | None = BottomCenterCrop(),
    ) -> None:
        layout = "KittiDepthCompletion"
        if split not in ("train", "val"):
            raise InputError(f"split: expected 'train' or 'val', got {split!r}")
        self.root = _require_root(root)
        self.split = split
        self.cameras = _check_cameras(camera)
        self.raw_root = _require_root(self.root.parent / "raw" if raw_root is None else raw_root, "raw_root")
        self.transform = transform

        velodyne_dir = _require_dir(self.root / "data_depth_velodyne" / split, self.root, layout)
        annotated_dir = _require_dir(self.root / "data_depth_annotated" / split, self.root, layout)

        frames: list[_CompletionFrame] = []
        for drive_dir in sorted(p for p in velodyne_dir.iterdir() if p.is_dir()):
            drive = drive_dir.name
            match = _DRIVE.match(drive)
            if match is None:
                raise InputError(
                    f"{layout}: expected drive folders named <date>_drive_<NNNN>_sync in "
                    f"{velodyne_dir}, got {drive_dir.name!r}"
                )
            day_dir = self.raw_root / match.group(1)
            for cam in self.cameras:
                sparse_dir = drive_dir / "proj_depth" / "velodyne_raw" / cam
                if not sparse_dir.is_dir():
                    continue
                target_dir = annotated_dir / drive / "proj_depth" / "groundtruth" / cam
                image_dir = self.raw_root / match.group(1) / drive / cam / "data"
                for sparse in sorted(sparse_dir.glob("*.png")):
                    frames.append(_CompletionFrame(
                        drive=drive, camera=cam, frame=sparse.stem, sparse=sparse,
                        target=target_dir / sparse.name, image=image_dir / sparse.name,
                        day_dir=day_dir,
                    ))
        if not frames:
            raise _no_frames(self.root, layout,
                             f"data_depth_velodyne/{split}/<drive>/proj_depth/velodyne_raw/"
                             f"{{{','.join(self.cameras)}}}/*.png")
        frames.sort(key=lambda f: f.name)
        # One listing per folder instead of one stat per file.
        listings: dict[Path, set[str]] = {}
        for f in frames:
            for path, what in ((f.target, "ground truth"), (f.image, "RGB image")):
                names = listings.get(path.parent)
                if names is None:
                    names = set(os.listdir(path.parent)) if path.parent.is_dir() else set()
                    listings[path.parent] = names
                if path.name not in names:
                    raise InputError(f"{layout}: missing {what} for {f.sparse}: expected {path}")
        self._frames = frames
        self._calibrations: dict[tuple[Path, int], Calibration] = {}
        for f in frames:
            self._calibration(f)  # read (and check) each day's calibration once, now

    def _calibration(self, f: _CompletionFrame) -> Calibration:
        key = (f.day_dir, int(f.camera[-1]))
        if key not in self._calibrations:
            if not f.day_dir.is_dir():
                raise InputError(f"KittiDepthCompletion: missing raw-data day folder for {f.sparse}: "
                                 f"expected {f.day_dir}")
            self._calibrations[key] = read_raw_calibration(f.day_dir, camera=key[1])
        return self._calibrations[key]

    def __len__(self) -> int:
        return len(self._frames)

    def __getitem__(self, index: int) -> Sample:
        f = self._frames[index]
        return load_sample(
            rgb=read_rgb(f.image),
            sparse=read_depth_png(f.sparse),
            target=read_depth_png(f.target),
            K=self._calibration(f).K,
            name=f.name,
            files={"image": f.image, "sparse": f.sparse, "target": f.target},
            transform=self.transform,
        )

    @property
    def names(self) -> list[str]:
        """Sample names in dataset order."""
        return [f.name for f in self._frames]


# --------------------------------------------------------------------------- depth_selection


@dataclass(frozen=True)
class _SelectionFrame:
    name: str
    sparse: Path
    image: Path
    target: Path | None
    intrinsics: Path


class _SelectionDataset(Dataset):
    """Shared code of the two ``depth_selection`` layouts (already cropped, K per file)."""

    _layout = ""
    _folder = ""
    _with_target = True

    def __init__(self, root: PathLike, transform: Transform | None = None) -> None:
        self.root = _resolve_subfolder(_require_root(root), self._folder, "velodyne_raw")
        self.transform = transform
        layout = self._layout
        sparse_dir = _require_dir(self.root / "velodyne_raw", self.root, layout)
        image_dir = _require_dir(self.root / "image", self.root, layout)
        intrinsics_dir = _require_dir(self.root / "intrinsics", self.root, layout)
        target_dir = (_require_dir(self.root / "groundtruth_depth", self.root, layout)
                      if self._with_target else None)

        frames = []
        for sparse in sorted(sparse_dir.glob("*.png")):
            frames.append(self._frame(sparse, image_dir, target_dir, intrinsics_dir))
        if not frames:
            raise _no_frames(self.root, layout, "velodyne_raw/*.png")
        for f in frames:
            for path, what in ((f.image, "RGB image"), (f.intrinsics, "intrinsics"), (f.target, "ground truth")):
                if path is not None and not path.is_file():
                    raise InputError(f"{layout}: missing {what} for {f.sparse}: expected {path}")
        self._frames = frames

    def _frame(self, sparse: Path, image_dir: Path, target_dir: Path | None, intrinsics_dir: Path) -> _SelectionFrame:
        raise NotImplementedError

    def __len__(self) -> int:
        return len(self._frames)

    def __getitem__(self, index: int) -> Sample:
        f = self._frames[index]
        return load_sample(
            rgb=read_rgb(f.image),
            sparse=read_depth_png(f.sparse),
            target=read_depth_png(f.target) if f.target is not None else None,
            K=read_intrinsics(f.intrinsics),
            name=f.name,
            files={"image": f.image, "sparse": f.sparse, "target": f.target},
            transform=self.transform,
        )

    @property
    def names(self) -> list[str]:
        """Sample names in dataset order."""
        return [f.name for f in self._frames]


class KittiValSelection(_SelectionDataset):
    """KITTI ``depth_selection/val_selection_cropped`` (1000 frames, already 1216 x 352).

    For each ``velodyne_raw/<drive>_velodyne_raw_<frame>_image_0X.png`` the frame uses
    ``image/<drive>_image_<frame>_image_0X.png``,
    ``groundtruth_depth/<drive>_groundtruth_depth_<frame>_image_0X.png`` and
    ``intrinsics/<drive>_image_<frame>_image_0X.txt`` (K of the cropped image: the raw K
    with ``cx - 13``, ``cy - 23``). The sample name is the ``velodyne_raw`` file stem, the
    name the benchmark expects for the output PNG.

    Args:
        root: the ``val_selection_cropped`` folder (its parent ``depth_selection`` is
            accepted too).
        transform: applied to every sample; default None (frames are already cropped).

    Raises:
        FileNotFoundError: ``root`` does not exist.
        InputError: ``root/velodyne_raw`` (or ``image``, ``groundtruth_depth``,
            ``intrinsics``) missing; no frame; a frame's image, ground truth or intrinsics
            file missing (path named); on ``__getitem__``, RGB and depth sizes differ.
    """

    _layout = "KittiValSelection"
    _folder = "val_selection_cropped"
    _with_target = True

    def _frame(self, sparse, image_dir, target_dir, intrinsics_dir):
        stem = sparse.stem
        if "_velodyne_raw_" not in stem:
            raise InputError(f"{self._layout}: expected velodyne_raw files named "
                             f"<drive>_velodyne_raw_<frame>_image_0X.png, got {sparse}")
        image_stem = stem.replace("_velodyne_raw_", "_image_", 1)
        return _SelectionFrame(
            name=stem,
            sparse=sparse,
            image=image_dir / f"{image_stem}.png",
            target=target_dir / f"{stem.replace('_velodyne_raw_', '_groundtruth_depth_', 1)}.png",
            intrinsics=intrinsics_dir / f"{image_stem}.txt",
        )


class KittiTestCompletion(_SelectionDataset):
    """KITTI ``depth_selection/test_depth_completion_anonymous`` (no ground truth).

    Files ``velodyne_raw/<n>.png``, ``image/<n>.png``, ``intrinsics/<n>.txt`` with
    anonymous names ``0000000000`` ...; the sample name is ``<n>``, the file name the
    test server expects. Every sample has an all-zero ``target`` and ``has_target=False``.

    Args:
        root: the ``test_depth_completion_anonymous`` folder (its parent
            ``depth_selection`` is accepted too).
        transform: applied to every sample; default None (frames are already cropped).

    Raises:
        FileNotFoundError: ``root`` does not exist.
        InputError: ``root/velodyne_raw`` (or ``image``, ``intrinsics``) missing; no frame;
            a frame's image or intrinsics missing; on ``__getitem__``, sizes differ.
    """

    _layout = "KittiTestCompletion"
    _folder = "test_depth_completion_anonymous"
    _with_target = False

    def _frame(self, sparse, image_dir, target_dir, intrinsics_dir):
        return _SelectionFrame(
            name=sparse.stem,
            sparse=sparse,
            image=image_dir / sparse.name,
            target=None,
            intrinsics=intrinsics_dir / f"{sparse.stem}.txt",
        )


# --------------------------------------------------------------------------- Velodyne scans


@dataclass(frozen=True)
class _ScanFrame:
    name: str
    image: Path
    velodyne: Path
    calib: Path  # day folder (raw) or calibration file (object)


class KittiRawScans(Dataset):
    """Frames with full Velodyne scans; input and target are disjoint parts of one scan.

    Layouts:
        ``"raw"``: ``root/<date>/<drive>/image_0X/data/<frame>.png`` and
        ``root/<date>/<drive>/velodyne_points/data/<frame>.bin`` with the day calibration
        ``root/<date>/calib_{cam_to_cam,velo_to_cam}.txt``; every drive of every date under
        ``root``. Names ``<drive>_<frame>_image_0X``.
        ``"object"``: ``root/image_X/<id>.png``, ``root/velodyne/<id>.bin``,
        ``root/calib/<id>.txt`` with ``root`` the object benchmark's ``training`` (or
        ``testing``) folder. Names ``<id>``.
        Frames are the scans (``.bin``); each must have its image and calibration.

    Each item projects the scan (:func:`crfdepth.projection.project_velodyne`, z-buffer,
    camera z-depth in metres) after splitting its points:

    - ``holdout="fraction"``: a random ``1 - holdout_fraction`` of the points is the input,
      the other ``holdout_fraction`` the target. The draw is deterministic per frame: its
      seed is derived from ``seed`` and the frame name (not the index, so a frame keeps its
      split when other frames are added or removed).
    - ``holdout="rings"``: the points of every ``keep_every_ring``-th laser ring (rings
      recovered from the scan order) are the input, all other rings the target: 16 beams
      out of 64 for ``keep_every_ring=4``, the paper's sparse-LiDAR scenario.

    ``keep_fraction`` (< 1) then keeps only that random share of the *input* points (the
    sub-sampling study); the dropped points are not added to the target, and the target
    is the same for every ``keep_fraction`` (same seed), so densities are compared on the
    same pixels.

    No leakage: every target pixel onto which an input point projects (input before the
    ``keep_fraction`` thinning) is set to 0 in the target, so no pixel is both input and
    target. With ``keep_fraction == 1``, ``(sparse > 0).sum() + (target > 0).sum()``
    equals the pixel count of the whole scan's projection. The target is thus sparse LiDAR (not KITTI's semi-dense
    annotation): far fewer pixels, and raw-LiDAR noise.

    Args:
        root: the raw-data root (holding ``<date>/``) or the object ``training`` folder.
        layout: "raw" or "object".
        holdout: "fraction" or "rings".
        holdout_fraction: share of points held out as target, in (0, 1) (``"fraction"``).
        keep_every_ring: k >= 2; rings ``r % k == 0`` are the input (``"rings"``).
        seed: non-negative integer seeding the per-frame random draws.
        keep_fraction: share of input points kept, in (0, 1]; 1 = all.
        camera: KITTI camera index, 2 (left colour, default) or 3.
        transform: applied to every sample; default ``BottomCenterCrop(352, 1216)``.

    Raises:
        FileNotFoundError: ``root`` does not exist.
        InputError: ``root`` does not match the layout (expected folder named); no frame;
            a scan without its image or calibration (path named); bad option values.
    """

    def __init__(
        self,
        root: PathLike,
        layout: Literal["raw", "object"] = "raw",
        holdout: Literal["fraction", "rings"] = "fraction",
        holdout_fraction: float = 0.2,
        keep_every_ring: int = 4,
        seed: int = 0,
        keep_fraction: float = 1.0,
        camera: int = 2,
        transform: Transform | None = BottomCenterCrop(),
    ) -> None:
        if layout not in ("raw", "object"):
            raise InputError(f"layout: expected 'raw' or 'object', got {layout!r}")
        if holdout not in ("fraction", "rings"):
            raise InputError(f"holdout: expected 'fraction' or 'rings', got {holdout!r}")
        if not 0.0 < float(holdout_fraction) < 1.0:
            raise InputError(f"holdout_fraction: expected a value in (0, 1), got {holdout_fraction}")
        if isinstance(keep_every_ring, bool) or int(keep_every_ring) != keep_every_ring or keep_every_ring < 2:
            raise InputError(f"keep_every_ring: expected an integer >= 2, got {keep_every_ring!r}")
        if not 0.0 < float(keep_fraction) <= 1.0:
            raise InputError(f"keep_fraction: expected a value in (0, 1], got {keep_fraction}")
        if isinstance(seed, bool) or int(seed) != seed or seed < 0:
            raise InputError(f"seed: expected a non-negative integer, got {seed!r}")
        if camera not in (2, 3):
            raise InputError(f"camera: expected 2 or 3 (KITTI colour cameras), got {camera!r}")
        self.root = _require_root(root)
        self.layout = layout
        self.holdout = holdout
        self.holdout_fraction = float(holdout_fraction)
        self.keep_every_ring = int(keep_every_ring)
        self.seed = int(seed)
        self.keep_fraction = float(keep_fraction)
        self.camera = int(camera)
        self.transform = transform
        self._frames = self._list_raw() if layout == "raw" else self._list_object()
        for f in self._frames:
            for path, what in ((f.image, "RGB image"), (f.calib, "calibration")):
                if not path.exists():
                    raise InputError(f"KittiRawScans({layout}): missing {what} for {f.velodyne}: expected {path}")
        self._calibrations: dict[Path, Calibration] = {}
        if layout == "raw":
            for f in self._frames:
                self._calibration(f)  # one file pair per day: read (and check) now

    def _list_raw(self) -> list[_ScanFrame]:
        cam = f"image_0{self.camera}"
        dates = sorted(p for p in self.root.iterdir() if p.is_dir() and re.fullmatch(r"\d{4}_\d{2}_\d{2}", p.name))
        if not dates:
            raise InputError(f"KittiRawScans(raw): expected {self.root}/<date> folders (e.g. "
                             f"{self.root}/2011_09_26) holding <date>_drive_<NNNN>_sync/, found none")
        frames = []
        for day_dir in dates:
            for drive_dir in sorted(p for p in day_dir.iterdir() if p.is_dir()):
                for scan in sorted((drive_dir / "velodyne_points" / "data").glob("*.bin")):
                    frames.append(_ScanFrame(
                        name=f"{drive_dir.name}_{scan.stem}_{cam}",
                        image=drive_dir / cam / "data" / f"{scan.stem}.png",
                        velodyne=scan,
                        calib=day_dir,
                    ))
        if not frames:
            raise _no_frames(self.root, "KittiRawScans(raw)", "<date>/<drive>/velodyne_points/data/*.bin")
        return frames

    def _list_object(self) -> list[_ScanFrame]:
        layout = "KittiRawScans(object)"
        velodyne_dir = _require_dir(self.root / "velodyne", self.root, layout)
        image_dir = _require_dir(self.root / f"image_{self.camera}", self.root, layout)
        calib_dir = _require_dir(self.root / "calib", self.root, layout)
        frames = [
            _ScanFrame(name=scan.stem, image=image_dir / f"{scan.stem}.png", velodyne=scan,
                       calib=calib_dir / f"{scan.stem}.txt")
            for scan in sorted(velodyne_dir.glob("*.bin"))
        ]
        if not frames:
            raise _no_frames(self.root, layout, "velodyne/*.bin")
        return frames

    def _calibration(self, f: _ScanFrame) -> Calibration:
        calib = self._calibrations.get(f.calib)
        if calib is None:
            if self.layout == "raw":
                calib = read_raw_calibration(f.calib, camera=self.camera)
            else:
                calib = read_object_calibration(f.calib, camera=self.camera)
            self._calibrations[f.calib] = calib
        return calib

    def __len__(self) -> int:
        return len(self._frames)

    def split_points(self, points: np.ndarray, name: str) -> tuple[np.ndarray, np.ndarray]:
        """Split one scan into (input, target) boolean point masks, per this dataset's options.

        Args:
            points: (N, 4) float32 Velodyne scan, in scan order.
            name: the frame name (seeds the random draws).

        Returns:
            Two (N,) bool masks, disjoint; ``input`` already reflects ``keep_fraction``.
        """
        rng = np.random.default_rng(frame_seed(self.seed, name))
        if self.holdout == "rings":
            inp = projection.ring_mask(points, self.keep_every_ring)
        else:
            inp = projection.fraction_mask(points, 1.0 - self.holdout_fraction, seed=rng)
        target = ~inp
        if self.keep_fraction < 1.0:
            kept = np.zeros_like(inp)
            idx = np.flatnonzero(inp)
            sub = projection.fraction_mask(idx, self.keep_fraction, seed=rng)
            kept[idx[sub]] = True
            inp = kept
        return inp, target

    def __getitem__(self, index: int) -> Sample:
        f = self._frames[index]
        rgb = read_rgb(f.image)
        calib = self._calibration(f)
        points = read_velodyne(f.velodyne)
        size = rgb.shape[:2]
        inp, held = self.split_points(points, f.name)
        sparse = projection.project_velodyne(points[inp], calib, size)
        target = projection.project_velodyne(points[held], calib, size)
        # No leakage: a pixel is input or target, never both. The target is cleared where
        # any input point (before keep_fraction thinning) lands, so it is the same set of
        # pixels for every keep_fraction.
        blocked = sparse if self.keep_fraction == 1.0 else projection.project_velodyne(points[~held], calib, size)
        target[blocked > 0] = 0.0
        return load_sample(
            rgb=rgb, sparse=sparse, target=target, K=calib.K, name=f.name,
            files={"image": f.image, "sparse": f.velodyne, "target": f.velodyne},
            transform=self.transform,
        )

    @property
    def names(self) -> list[str]:
        """Sample names in dataset order."""
        return [f.name for f in self._frames]
