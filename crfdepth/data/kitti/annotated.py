"""KITTI's annotated frames as a training source: image + semi-dense annotation, the input drawn from it.

KITTI's annotation (``data_depth_annotated``) is the ground truth the benchmark scores; frames that
have it need not have a scan beside them (the shared ``annotated/`` frames have none). This dataset
reads the image, the annotation and the day's calibration and makes the input one of three ways
(docs/design.md section 16):

- ``input_from="share"``: a random ``input_share`` of the annotated pixels (the clean-input protocol
  a22 of ``benchmarks/accuracy.py`` uses 0.22);
- ``input_from="rings"``: the annotated pixels that lie on every ``keep_every_ring``-th laser ring of
  a 64-beam Velodyne HDL-64E, the pattern of one scan: each pixel is lifted to 3D with its
  annotated depth, moved into the Velodyne frame with the calibration, and kept when its
  elevation lies within half a pixel's angle of a kept ring's elevation;
- ``input_from="lidar"``: a Velodyne scan of the annotated scene, simulated from the calibration
  (:func:`crfdepth.data.kitti.lidar_view.simulate_scan`): every ``keep_every_ring``-th ring, the
  see-through returns a scan carries at depth edges included; the target is then the whole
  annotation, as with a real scan;
- ``input_from="scan"``: the frame's own LiDAR, the ``velodyne_raw`` map of the depth-completion
  layout when the root has one, else the raw scan ``.bin`` projected; the target is then the
  whole annotation.

With "share" and "rings" the input pixels leave the target (the model is scored on the pixels it was not
given). With ``seed=None`` the draw uses torch's generator as it stands (the trainer seeds it per
frame and epoch, so each epoch draws another input); with an integer the draw of frame ``i`` is
fixed (``seed + i``), for validation.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Literal

import numpy as np
import torch

from crfdepth.checks import check_choice
from crfdepth.data.kitti import loading
from crfdepth.data.kitti.lidar_view import HDL64_ELEVATIONS_DEG, lift_to_velodyne, simulate_scan
from crfdepth.data.kitti.loading import CAMERAS, DRIVE_NAME, FrameDataset, PathLike, Transform, check_cameras
from crfdepth.data.sample import Sample
from crfdepth.data.transforms import BottomCenterCrop
from crfdepth.errors import InputError
from crfdepth.geometry.projection import project_velodyne
from crfdepth.io.calibration import read_raw_calibration
from crfdepth.io.kitti import read_depth_png, read_rgb, read_velodyne

if TYPE_CHECKING:
    from crfdepth.io.calibration import Calibration

__all__ = ["HDL64_ELEVATIONS_DEG", "KittiAnnotated", "ring_pixels"]

INPUTS = ("share", "rings", "lidar", "scan")
DEFAULT_SHARE = 0.22  # input_from="share": the clean-input protocols' share (benchmarks/accuracy.py, a22)



def _check_share(value: object) -> float:
    ok = isinstance(value, (int, float)) and not isinstance(value, bool) and 0.0 < float(value) <= 1.0
    if not ok:
        raise InputError(f"input_share: expected a number in (0, 1] (the share of annotated pixels given as "
                         f"input), got {value!r}")
    return float(value)


def ring_pixels(target: np.ndarray, calib: Calibration, keep_every_ring: int, offset: int = 0) -> np.ndarray:
    """Pixels of ``target`` on every ``keep_every_ring``-th ring of a 64-beam scan (``ring % k == offset``).

    Args:
        target: (H, W) annotated depth in metres (the third row of ``P_rect R_rect T_velo_to_cam x``),
            0 = none.
        calib: the camera's calibration (:class:`~crfdepth.io.calibration.Calibration`).
        keep_every_ring: k >= 1; 1 keeps every ring, 4 a 16-beam pattern.
        offset: which ring of each group of k, ``0 <= offset < k``.

    Returns:
        (H, W) bool, True where an annotated pixel's point, seen from the Velodyne, lies within
        half a pixel's angle (``0.5 / fy`` radians) of a kept ring's elevation.
    """
    v, u = np.nonzero(target > 0)
    keep = np.zeros(target.shape, dtype=bool)
    if v.size == 0:
        return keep
    P = calib.P_rect
    velo = lift_to_velodyne(v, u, target[v, u].astype(np.float64), calib)
    elevation = np.degrees(np.arctan2(velo[2], np.hypot(velo[0], velo[1])))
    rings = HDL64_ELEVATIONS_DEG[offset::keep_every_ring]
    gap = np.abs(elevation[:, None] - rings[None, :]).min(axis=1)
    keep[v, u] = gap <= math.degrees(0.5 / P[1, 1])
    return keep


@dataclass(frozen=True)
class _AnnotatedFrame:
    drive: str
    camera: str
    frame: str
    target: Path
    image: Path
    day_dir: Path
    scan: Path | None

    @property
    def name(self) -> str:
        # The depth-completion name, so a frame here and in a validation set of that layout is caught.
        return f"{self.drive}_velodyne_raw_{self.frame}_{self.camera}"


class KittiAnnotated(FrameDataset):
    """Frames with KITTI's annotation, the input made from the annotation or the frame's scan.

    Frames are the annotation PNGs
    ``root/data_depth_annotated/<split>/<drive>/proj_depth/groundtruth/<camera>/<frame>.png``; each
    needs its image ``raw_root/<date>/<drive>/<camera>/data/<frame>.png`` and the day's calibration
    ``raw_root/<date>/calib_*.txt``. ``input_from="scan"`` also needs
    ``root/data_depth_velodyne/<split>/<drive>/proj_depth/velodyne_raw/<camera>/<frame>.png`` or
    ``raw_root/<date>/<drive>/velodyne_points/data/<frame>.bin``.

    Args:
        root: folder holding ``data_depth_annotated/`` (the shared ``annotated/`` folder, or a
            depth-completion root).
        split: "train" or "val".
        camera: "image_02", "image_03" or both (default both; a camera without annotation is skipped).
        raw_root: root of the raw data (holding ``<date>/``); None = ``root/raw`` if it exists, else
            ``root/../raw``.
        input_from: "share", "rings", "lidar" or "scan" (module docstring).
        input_share: share of the annotated pixels given as input ("share"; None = 0.22), or kept of
            the ring pixels ("rings"; None = all); in (0, 1]. Not used by "lidar" and "scan".
        keep_every_ring: "rings" and "lidar": one ring in k (1 = 64 beams, 4 = 16 beams).
        seed: None = draw from torch's generator (training); an int = a fixed draw per frame.
        transform: applied to every sample; default ``BottomCenterCrop(352, 1216)``.

    Raises:
        FileNotFoundError: ``root`` or ``raw_root`` does not exist.
        InputError: no frame; a frame's image, calibration or (for "scan") scan is missing; an
            annotation with no annotated pixel or of another size than its image (on
            ``__getitem__``, file named); a bad option (named).
    """

    def __init__(
        self,
        root: PathLike,
        split: Literal["train", "val"] = "train",
        camera: str | Sequence[str] = CAMERAS,
        raw_root: PathLike | None = None,
        input_from: Literal["share", "rings", "lidar", "scan"] = "share",
        input_share: float | None = None,
        keep_every_ring: int = 1,
        seed: int | None = None,
        transform: Transform | None = BottomCenterCrop(),
    ) -> None:
        layout = "KittiAnnotated"
        check_choice("split", split, ("train", "val"))
        check_choice("input_from", input_from, INPUTS)
        if input_from in ("lidar", "scan") and input_share is not None:
            raise InputError(f"input_share: not used with input_from {input_from!r} (the input is a whole scan), "
                             f"got {input_share!r}; leave it out")
        if input_share is None:
            input_share = DEFAULT_SHARE if input_from == "share" else 1.0
        self.input_share = _check_share(input_share)
        if input_from == "share" and self.input_share == 1.0:
            raise InputError("input_share: expected a number below 1 for input_from 'share' (the pixels given as input "
                             "leave the target), got 1.0")
        if isinstance(keep_every_ring, bool) or not isinstance(keep_every_ring, int) or not 1 <= keep_every_ring <= 64:
            raise InputError(f"keep_every_ring: expected an integer in [1, 64] (one ring in k), got {keep_every_ring!r}")
        if seed is not None and (isinstance(seed, bool) or not isinstance(seed, int)):
            raise InputError(f"seed: expected an integer or None, got {seed!r}")
        cameras = check_cameras(camera)
        self.root = loading.require_root(root)
        if raw_root is None:
            raw_root = self.root / "raw" if (self.root / "raw").is_dir() else self.root.parent / "raw"
        self.raw_root = loading.require_root(raw_root, "raw_root")
        self.split, self.cameras, self.input_from = split, cameras, input_from
        self.keep_every_ring, self.seed, self.transform = keep_every_ring, seed, transform

        annotated_dir = loading.require_dir(self.root / "data_depth_annotated" / split, self.root, layout)
        velodyne_dir = self.root / "data_depth_velodyne" / split
        frames: list[_AnnotatedFrame] = []
        for drive_dir in sorted(p for p in annotated_dir.iterdir() if p.is_dir()):
            match = DRIVE_NAME.match(drive_dir.name)
            if match is None:
                raise InputError(f"{layout}: expected drive folders named <date>_drive_<NNNN>_sync in "
                                 f"{annotated_dir}, got {drive_dir.name!r}")
            day_dir = self.raw_root / match.group(1)
            for cam in cameras:
                for target in sorted((drive_dir / "proj_depth" / "groundtruth" / cam).glob("*.png")):
                    image = day_dir / drive_dir.name / cam / "data" / target.name
                    if not image.is_file():
                        raise InputError(f"{layout}: missing RGB image for {target}: expected {image}")
                    scan = None
                    if input_from == "scan":
                        scan = self._scan_path(velodyne_dir, day_dir, drive_dir.name, cam, target.stem)
                    frames.append(_AnnotatedFrame(drive_dir.name, cam, target.stem, target, image, day_dir, scan))
        if not frames:
            raise loading.no_frames(self.root, layout, f"data_depth_annotated/{split}/<drive>/proj_depth/"
                                                       f"groundtruth/{{{','.join(cameras)}}}/*.png")
        frames.sort(key=lambda f: f.name)
        self._frames = frames
        self._calibrations: dict[tuple[Path, int], Calibration] = {}
        for f in frames:
            self._calibration(f)  # each day's calibration read (and checked) once, now

    @staticmethod
    def _scan_path(velodyne_dir: Path, day_dir: Path, drive: str, camera: str, frame: str) -> Path:
        png = velodyne_dir / drive / "proj_depth" / "velodyne_raw" / camera / f"{frame}.png"
        if png.is_file():
            return png
        scan = day_dir / drive / "velodyne_points" / "data" / f"{frame}.bin"
        if scan.is_file():
            return scan
        raise InputError(f"input_from: 'scan' needs the frame's LiDAR, expected {png} or {scan}; "
                         f"use input_from 'share' or 'rings' for frames without a scan")

    def _calibration(self, f: _AnnotatedFrame) -> Calibration:
        key = (f.day_dir, int(f.camera[-1]))
        if key not in self._calibrations:
            if not f.day_dir.is_dir():
                raise InputError(f"KittiAnnotated: missing raw-data day folder for {f.target}: expected {f.day_dir}")
            self._calibrations[key] = read_raw_calibration(f.day_dir, camera=key[1])
        return self._calibrations[key]

    def _draw(self, shape: tuple[int, int], index: int) -> np.ndarray:
        generator = None if self.seed is None else torch.Generator().manual_seed(self.seed + index)
        return torch.rand(shape, generator=generator).numpy()

    def _generator(self, index: int) -> np.random.Generator:
        """numpy's generator of frame ``index``'s simulated scan: seeded from torch's generator
        (training, ``seed=None``) or from ``seed + index``."""
        if self.seed is None:
            return np.random.default_rng(int(torch.randint(2**31 - 1, (1,))))
        return np.random.default_rng(self.seed + index)

    def __getitem__(self, index: int) -> Sample:
        f = self._frames[index]
        rgb = read_rgb(f.image)
        target = read_depth_png(f.target)
        if target.shape != rgb.shape[:2]:
            raise InputError(f"{f.name}: RGB and annotation sizes differ: image {f.image} is "
                             f"{rgb.shape[0]}x{rgb.shape[1]} (HxW) but annotation {f.target} is "
                             f"{target.shape[0]}x{target.shape[1]}")
        if not (target > 0).any():
            raise InputError(f"annotation: expected annotated pixels (depth > 0), got none in {f.target}")
        calib = self._calibration(f)
        if self.input_from == "scan":
            if f.scan.suffix == ".png":
                sparse = read_depth_png(f.scan)
            else:
                sparse = project_velodyne(read_velodyne(f.scan), calib, target.shape)
        elif self.input_from == "lidar":
            rng = self._generator(index)
            offset = int(rng.integers(self.keep_every_ring))
            sparse = simulate_scan(target, calib, keep_every_ring=self.keep_every_ring, ring_offset=offset,
                                   generator=rng)
        else:
            given = target > 0 if self.input_from == "share" else ring_pixels(target, calib, self.keep_every_ring)
            if self.input_share < 1.0:
                given &= self._draw(target.shape, index) < self.input_share
            sparse = np.where(given, target, 0.0).astype(np.float32)
            target = np.where(given, 0.0, target).astype(np.float32)
        return loading.load_sample(rgb=rgb, sparse=sparse, target=target, K=calib.K, name=f.name,
                                   files={"image": f.image, "sparse": f.scan or f.target, "target": f.target},
                                   transform=self.transform)
