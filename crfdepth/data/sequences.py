"""KITTI raw drives as sequences: camera-view targets plus the neighbouring frames and their poses.

:class:`SequenceFrames` (layout ``"sequence"`` of :func:`crfdepth.data.build_dataset`) reads
the frames of KITTI raw drives together with the camera-view targets that
``crfdepth targets`` wrote for them (docs/design.md sections 13, 14 and 15), and gives each
frame's neighbours (images and relative camera poses) for the photometric term
(:func:`crfdepth.sequences.photometric.photometric_loss`, ``CRFDepthModule(photometric_weight=...)``).

Make the targets first, once per drive::

    crfdepth targets --drive RAW/2011_09_26/2011_09_26_drive_0060_sync --out-dir TARGETS

Pose chain. ``crfdepth targets`` writes ``TARGETS/<drive>/poses.txt`` in KITTI odometry
format: line ``i`` is ``P(i) = T_rect0(first)<-rect0(i)``, the pose of the *rectified
camera 0* at the i-th scan it used, relative to the first (``Tr L(i) Tr^-1`` with the LiDAR
poses ``L`` and ``Tr = R_rect_00 T_velo_to_cam``). The colour camera X's rectified frame is
camera 0's, shifted: ``P_rect_0X = K [I | t]`` so ``T_camX<-rect0 = E = [I | K^-1 P_rect_0X[:, 3]]``
(KITTI's stereo baseline; the stored z-depth includes ``t_z``, crfdepth's depth
convention). The relative pose of a neighbour ``s`` of frame ``t`` is then::

    T_cam(s)<-cam(t) = E P(s)^-1 P(t) E^-1

Which frame line 0 is: the ``first_scan`` of the first row of ``index_image_0X.csv`` written
beside poses.txt (``crfdepth targets --frames A:B`` writes the poses of A-k .. B+k); without
that file, the drive's first scan. The line count must match the frames the index (or the
drive) spans.

Ends. A frame is used only when every neighbour ``t + offset`` is a frame of the drive
inside ``frames`` (the block) and has a pose: the first and last ``max |offset|`` frames of
each block are dropped (listed in :attr:`SequenceFrames.dropped`), so every sample has the
same S neighbours and no training frame looks at a frame of another block.

Input-density augmentation (docs/design.md section 15): ``beams`` (e.g. ``[16, 32, 64]``)
keeps, per item, the rings ``r % k == o`` of the 64-ring scan with ``k = 64 / beams`` and a
random offset ``o`` (rings recovered from the scan order,
:func:`crfdepth.geometry.projection.recover_rings`); ``keep_fraction`` ``[low, high]`` then keeps a
uniformly random share in that range of the remaining points
(:func:`crfdepth.geometry.projection.fraction_mask`). The target is never thinned.

Clean inputs (``target_input``): with probability ``p`` an item's input is not its scan but a
random share (``target_input_fraction``, default 10-40%) of its camera-view target pixels, and
those pixels leave its target. Such an input has no see-through returns and does not lie on
laser rings: the case of a LiDAR mounted next to the camera, an input cleaned upstream, or
KITTI's annotated maps subsampled. Without it, every input the weights see carries a LiDAR's
see-through returns at depth edges, and the weights learn to distrust the far side of every
edge, which is wrong for a clean input (docs/design.md section 15).
"""

from __future__ import annotations

import csv
import dataclasses
import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from crfdepth.data.kitti.loading import (
    FrameDataset,
    PathLike,
    Transform,
    load_sample,
    no_frames,
    require_root,
    rgb_tensor,
)
from crfdepth.data.sample import Sample
from crfdepth.data.transforms import BottomCenterCrop, frame_seed
from crfdepth.errors import InputError
from crfdepth.geometry import projection
from crfdepth.io.calibration import Calibration, read_raw_calibration
from crfdepth.io.kitti import read_depth_png, read_rgb, read_velodyne
from crfdepth.sequences.poses import read_kitti_poses

__all__ = ["FULL_BEAMS", "SequenceFrames", "colour_camera_poses"]

FULL_BEAMS = 64
"""Rings of a full scan (KITTI's HDL-64E); ``beams`` keeps ``FULL_BEAMS / beams``-th rings."""

_STEM = re.compile(r"\d+")


def colour_camera_poses(rect0_poses: np.ndarray, calib: Calibration) -> np.ndarray:
    """World<-camera poses of the colour camera from those of the rectified camera 0.

    Args:
        rect0_poses: (n, 4, 4) ``P(i) = T_w<-rect0(i)`` (a ``poses.txt``).
        calib: the day's calibration of the colour camera (its ``P_rect``).

    Returns:
        (n, 4, 4) float64 ``P(i) E^-1`` with ``E = [I | K^-1 P_rect[:, 3]]``, so that
        ``C(s)^-1 C(t) = E P(s)^-1 P(t) E^-1 = T_cam(s)<-cam(t)``.
    """
    E = np.eye(4)
    E[:3, 3] = np.linalg.solve(calib.K, calib.P_rect[:, 3])
    return np.asarray(rect0_poses, dtype=np.float64) @ np.linalg.inv(E)


@dataclass(frozen=True)
class _Frame:
    name: str
    drive: str
    image: Path
    velodyne: Path
    target: Path
    day: Path
    neighbours: tuple[Path, ...]
    poses: np.ndarray  # (S, 4, 4) T_cam(s)<-cam(t)


class SequenceFrames(FrameDataset):
    """Frames of KITTI raw drives with camera-view targets, neighbouring images and poses.

    Layout: ``root/<date>/<drive>/image_0X/data/<frame>.png``,
    ``root/<date>/<drive>/velodyne_points/data/<frame>.bin``, the day calibration
    ``root/<date>/calib_{cam_to_cam,velo_to_cam}.txt`` (as the ``raw`` layout), and the
    output of ``crfdepth targets --drive root/<date>/<drive> --out-dir targets_root``:
    ``targets_root/<drive>/proj_depth/groundtruth/image_0X/<frame>.png`` and
    ``targets_root/<drive>/poses.txt``. Every drive under ``root`` needs its targets.

    Each item is a :class:`~crfdepth.data.sample.Sample` named ``<drive>_<frame>_image_0X``:
    image; sparse = the frame's own scan projected
    (:func:`crfdepth.geometry.projection.project_velodyne`, as :class:`~crfdepth.data.kitti.KittiRawScans`),
    after the density augmentation; target = the camera-view target; ``neighbours``
    (S, 3, H, W) the images of frames ``t + offset``; ``poses`` (S, 4, 4) float32
    ``T_cam(s)<-cam(t)`` (module docstring: the chain and the dropped ends). The
    transform (default the KITTI bottom-centre crop 352 x 1216) applies to all of them.

    Args:
        root: the raw-data root holding ``<date>/`` folders.
        targets_root: the ``--out-dir`` of ``crfdepth targets`` (required; a keyword so
            that ``build_dataset("sequence", root, targets_root=...)`` reads like the others).
        offsets: neighbour offsets in frames, non-zero integers (default ``(-1, 1)``).
        frames: ``[first, last]`` frame numbers (inclusive) to use from every drive, e.g.
            ``[0, 51]`` to train on a block and ``[52, 77]`` to validate; None = all.
        camera: 2 (left colour, default) or 3.
        beams: ring counts to draw from per item, each dividing 64 (e.g. ``[16, 32, 64]``);
            None = every ring.
        keep_fraction: ``[low, high]`` with ``0 < low <= high <= 1``: keep a random share
            in that range of the (ring-selected) points; None = all.
        target_input: probability that an item's input is a random share of its
            camera-view target instead of its scan (the module docstring); 0 (default): never.
        target_input_fraction: ``[low, high]``, ``0 < low <= high < 1``: the share of target
            pixels given as input in such an item (default ``[0.1, 0.4]``).
        seed: None: the augmentation draws from torch's global RNG (new draws every epoch,
            reseeded per ``DataLoader`` worker); an integer: fixed draws per frame name.
        transform: applied to every sample; default ``BottomCenterCrop(352, 1216)``.

    Raises:
        FileNotFoundError: ``root`` or ``targets_root`` does not exist.
        InputError: no drive or frame; a drive without ``poses.txt`` or a used frame
            without its target (the frame and the command that makes them named); a
            ``poses.txt`` whose line count does not match; no frame left with all its
            neighbours; bad option values.
    """

    def __init__(
        self,
        root: PathLike,
        targets_root: PathLike | None = None,
        offsets: tuple[int, ...] | list[int] = (-1, 1),
        frames: list[int] | tuple[int, int] | None = None,
        camera: int = 2,
        beams: list[int] | None = None,
        keep_fraction: list[float] | tuple[float, float] | None = None,
        target_input: float = 0.0,
        target_input_fraction: list[float] | tuple[float, float] = (0.1, 0.4),
        seed: int | None = None,
        transform: Transform | None = BottomCenterCrop(),
    ) -> None:
        offsets = list(offsets) if isinstance(offsets, (list, tuple)) else offsets
        if (not isinstance(offsets, list) or not offsets
                or not all(isinstance(o, int) and not isinstance(o, bool) and o != 0 for o in offsets)
                or len(set(offsets)) != len(offsets)):
            raise InputError(f"offsets: expected distinct non-zero integers (frames from t), got {offsets!r}")
        if frames is not None and (not isinstance(frames, (list, tuple)) or len(frames) != 2
                                   or not all(isinstance(f, int) and not isinstance(f, bool) for f in frames)
                                   or not 0 <= frames[0] <= frames[1]):
            raise InputError(f"frames: expected [first, last] frame numbers with 0 <= first <= last, got {frames!r}")
        if camera not in (2, 3):
            raise InputError(f"camera: expected 2 or 3 (KITTI colour cameras), got {camera!r}")
        if beams is not None and (not isinstance(beams, (list, tuple)) or not beams or not all(
                isinstance(b, int) and not isinstance(b, bool) and b >= 1 and FULL_BEAMS % b == 0 for b in beams)):
            raise InputError(f"beams: expected a list of ring counts dividing {FULL_BEAMS} (e.g. [16, 32, 64]), "
                             f"got {beams!r}")
        if keep_fraction is not None and (
                not isinstance(keep_fraction, (list, tuple)) or len(keep_fraction) != 2
                or not all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in keep_fraction)
                or not 0.0 < float(keep_fraction[0]) <= float(keep_fraction[1]) <= 1.0):
            raise InputError(f"keep_fraction: expected [low, high] with 0 < low <= high <= 1, got {keep_fraction!r}")
        if isinstance(target_input, bool) or not isinstance(target_input, (int, float)) \
                or not 0.0 <= float(target_input) <= 1.0:
            raise InputError(f"target_input: expected a probability in [0, 1], got {target_input!r}")
        if (not isinstance(target_input_fraction, (list, tuple)) or len(target_input_fraction) != 2
                or not all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in target_input_fraction)
                or not 0.0 < float(target_input_fraction[0]) <= float(target_input_fraction[1]) < 1.0):
            raise InputError(f"target_input_fraction: expected [low, high] with 0 < low <= high < 1, "
                             f"got {target_input_fraction!r}")
        if seed is not None and (isinstance(seed, bool) or not isinstance(seed, int) or seed < 0):
            raise InputError(f"seed: expected a non-negative integer or None, got {seed!r}")
        if targets_root is None:
            raise InputError("targets_root: expected the --out-dir folder of `crfdepth targets` (camera-view "
                             "targets of the drives under root), got none")
        self.root = require_root(root)
        self.targets_root = require_root(targets_root, "targets_root")
        self.offsets = tuple(offsets)
        self.frame_range = None if frames is None else (int(frames[0]), int(frames[1]))
        self.camera = int(camera)
        self.beams = None if beams is None else tuple(int(b) for b in beams)
        self.keep_fraction = None if keep_fraction is None else (float(keep_fraction[0]), float(keep_fraction[1]))
        self.target_input = float(target_input)
        self.target_input_fraction = (float(target_input_fraction[0]), float(target_input_fraction[1]))
        self.seed = seed
        self.transform = transform
        self._calibrations: dict[Path, Calibration] = {}
        self.dropped: list[str] = []
        self._frames: list[_Frame] = []
        for day, drive in self._drives():
            self._frames.extend(self._drive_frames(day, drive))
        if not self._frames:
            raise InputError(f"offsets: no frame under {self.root} has all its neighbours {list(self.offsets)} "
                             f"within frames {self.frame_range} ({len(self.dropped)} frame(s) dropped at the ends)")

    # -- listing ---------------------------------------------------------------------------
    def _drives(self) -> list[tuple[Path, Path]]:
        dates = sorted(p for p in self.root.iterdir() if p.is_dir() and re.fullmatch(r"\d{4}_\d{2}_\d{2}", p.name))
        if not dates:
            raise InputError(f"SequenceFrames: expected {self.root}/<date> folders (e.g. {self.root}/2011_09_26) "
                             f"holding <date>_drive_<NNNN>_sync/, found none")
        drives = [(day, d) for day in dates for d in sorted(p for p in day.iterdir() if p.is_dir())
                  if (d / "velodyne_points" / "data").is_dir()]
        if not drives:
            raise no_frames(self.root, "SequenceFrames", "<date>/<drive>/velodyne_points/data/*.bin")
        return drives

    def _command(self, drive: Path) -> str:
        return f"crfdepth targets --drive {drive} --out-dir {self.targets_root}"

    def _drive_frames(self, day: Path, drive: Path) -> list[_Frame]:
        cam = f"image_0{self.camera}"
        scans = {int(p.stem): p for p in sorted((drive / "velodyne_points" / "data").glob("*.bin"))
                 if _STEM.fullmatch(p.stem)}
        if not scans:
            raise no_frames(drive, "SequenceFrames", "velodyne_points/data/*.bin")
        width = len(next(iter(scans.values())).stem)
        out = self.targets_root / drive.name
        poses_path = out / "poses.txt"
        if not poses_path.is_file():
            raise InputError(f"targets_root: expected the camera-view targets of {drive.name} in {out} (with "
                             f"poses.txt), got no {poses_path}; make them with `{self._command(drive)}`")
        first, last = self._pose_span(out, cam, sorted(scans), drive)
        rect0 = read_kitti_poses(poses_path)
        if len(rect0) != last - first + 1:
            raise InputError(f"targets_root: expected {last - first + 1} poses in {poses_path} (frames {first} to "
                             f"{last}, one per line), got {len(rect0)}; rerun `{self._command(drive)}`")
        cams = colour_camera_poses(rect0, self._calibration(day))
        pose_of = {first + i: cams[i] for i in range(len(cams))}
        lo, hi = self.frame_range if self.frame_range is not None else (min(scans), max(scans))
        block = [f for f in sorted(scans) if lo <= f <= hi]
        frames = []
        for t in block:
            name = f"{drive.name}_{t:0{width}d}_{cam}"
            wanted = [t + o for o in self.offsets]
            if not all(s in scans and lo <= s <= hi and s in pose_of for s in wanted + [t]):
                self.dropped.append(name)
                continue
            target = out / "proj_depth" / "groundtruth" / cam / f"{t:0{width}d}.png"
            if not target.is_file():
                raise InputError(f"targets_root: expected the camera-view target of frame {t:0{width}d} of "
                                 f"{drive.name}, got no {target}; make it with `{self._command(drive)}`")
            images = [drive / cam / "data" / f"{s:0{width}d}.png" for s in [t] + wanted]
            for path in images:
                if not path.is_file():
                    raise InputError(f"SequenceFrames: missing RGB image for {scans[int(path.stem)]}: expected {path}")
            rel = np.stack([np.linalg.inv(pose_of[s]) @ pose_of[t] for s in wanted])
            frames.append(_Frame(name=name, drive=drive.name, image=images[0], velodyne=scans[t], target=target,
                                 day=day, neighbours=tuple(images[1:]), poses=rel))
        return frames

    def _pose_span(self, out: Path, cam: str, scans: list[int], drive: Path) -> tuple[int, int]:
        """The frame numbers of the first and last line of poses.txt (module docstring)."""
        index = out / f"index_{cam}.csv"
        if not index.is_file():
            return scans[0], scans[-1]
        with index.open(newline="") as handle:
            rows = list(csv.DictReader(handle))
        try:
            return int(rows[0]["first_scan"]), int(rows[-1]["last_scan"])
        except (IndexError, KeyError, ValueError):
            raise InputError(f"targets_root: expected the index crfdepth targets writes (columns first_scan, "
                             f"last_scan) in {index}, got a file without them; rerun `{self._command(drive)}`") from None

    def _calibration(self, day: Path) -> Calibration:
        calib = self._calibrations.get(day)
        if calib is None:
            calib = self._calibrations[day] = read_raw_calibration(day, camera=self.camera)
        return calib

    # -- items -----------------------------------------------------------------------------
    def _rng(self, name: str) -> np.random.Generator:
        if self.seed is None:
            return np.random.default_rng(int(torch.randint(0, 2**62, ()).item()))
        return np.random.default_rng(frame_seed(self.seed, name))

    def input_mask(self, points: np.ndarray, name: str, rng: np.random.Generator | None = None) -> np.ndarray:
        """(N,) bool: the points of one scan kept as input by the density augmentation."""
        keep = np.ones(len(points), dtype=bool)
        if self.beams is None and self.keep_fraction is None:
            return keep
        rng = self._rng(name) if rng is None else rng
        if self.beams is not None:
            k = FULL_BEAMS // int(rng.choice(self.beams))
            if k > 1:
                keep = projection.ring_mask(points, k, offset=int(rng.integers(k)))
        if self.keep_fraction is not None:
            share = float(rng.uniform(*self.keep_fraction))
            idx = np.flatnonzero(keep)
            if share < 1.0 and len(idx):
                kept = np.zeros_like(keep)
                kept[idx[projection.fraction_mask(idx, share, seed=rng)]] = True
                keep = kept
        return keep

    def __getitem__(self, index: int) -> Sample:
        f = self._frames[index]
        rgb = read_rgb(f.image)
        calib = self._calibration(f.day)
        target = read_depth_png(f.target)
        rng = self._rng(f.name) if self.target_input > 0 or self.beams or self.keep_fraction else None
        if self.target_input > 0 and rng.random() < self.target_input:
            pixels = np.flatnonzero(target > 0)
            chosen = pixels[projection.fraction_mask(pixels, float(rng.uniform(*self.target_input_fraction)), seed=rng)]
            sparse = np.zeros_like(target)
            sparse.flat[chosen] = target.flat[chosen]
            target = target.copy()
            target.flat[chosen] = 0.0
        else:
            points = read_velodyne(f.velodyne)
            sparse = projection.project_velodyne(points[self.input_mask(points, f.name, rng)], calib, rgb.shape[:2])
        sample = load_sample(rgb=rgb, sparse=sparse, target=target, K=calib.K, name=f.name,
                             files={"image": f.image, "sparse": f.velodyne, "target": f.target})
        neighbours = []
        for path in f.neighbours:
            image = read_rgb(path)
            if image.shape != rgb.shape:
                raise InputError(f"{f.name}: neighbouring image {path} is {image.shape[0]}x{image.shape[1]} (HxW), "
                                 f"the frame's {f.image} is {rgb.shape[0]}x{rgb.shape[1]}")
            neighbours.append(rgb_tensor(image))
        sample = dataclasses.replace(sample, neighbours=torch.stack(neighbours),
                                     poses=torch.from_numpy(f.poses).to(torch.float32))
        return self.transform(sample) if self.transform is not None else sample
