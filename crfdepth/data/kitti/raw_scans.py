"""KITTI frames with full Velodyne scans, the input and the target held-out parts of one scan.

Raw-data drives or the object benchmark; the scan is split into input and target points
(a random fraction, or whole laser rings) and both are projected into the image, with no
pixel in both (docs/design.md section 7). By default the target is then cleaned of
see-through points (:func:`remove_see_through`), as KITTI's annotation was.

Share of target pixels the cleaning removes (default mask of :mod:`crfdepth.potentials.occlusion`,
1216x352 crop, target pixels of all frames pooled, per-frame range in brackets):

| holdout | drive 0060 (13 frames) | object (11 frames) | drive 0001 frame 5 |
|---|---|---|---|
| ``"fraction"`` (20%) | 3.57% (2.55-4.80) | 2.44% (0.88-6.34) | 0.46% |
| ``"rings"`` (every 4th kept) | 3.63% (2.36-5.16) | 2.45% (0.71-6.01) | 0.64% |

Checked against KITTI's annotation (drive 0001 frame 5, uncropped 1242x375; reported
only, the defaults were fixed before): camera 2's raw-scan projection has 19,137 returns,
8,439 of them on annotated pixels; 194 of those disagree with the annotation by more than
1 m, 99 by more than 10%. The mask flags 119 returns, 32 of them annotated, 27 of which
disagree by more than 1 m and by more than 10%: precision 84%, recall 14% (> 1 m) and
27% (> 10%). 73% of the flagged returns have no annotation at all (KITTI dropped them),
against 56% of the others. Of the 99 returns off by more than 10%, 32 have no nearer
return in the window and 29 lead by less than 0.005 1/m: no threshold reaches them
(0.005 would add at most 11). Camera 3: 184 flagged, precision 98%, recall 24% / 45%.
For comparison the metric rule "more than 1.5 m behind the nearest in 5x5" flags 326:
precision 44% (> 1 m) / 36% (> 10%), recall 28% / 44%.

``stereo_check=True`` (drives with both colour cameras) further drops the target pixels that the
rectified stereo pair contradicts (:func:`crfdepth.sequences.stereo.stereo_consistent`,
docs/design.md section 16), as KITTI's annotation was checked against stereo. Measured by
``benchmarks/stereo_check.py`` on drive 0048 (3 frames, 20% hold-out, uncropped): it drops 2.6-3.9%
of the see-through-cleaned target pixels of camera 2 (81-128 of about 3,200 per frame), 3.5-4.9% of
camera 3's. On the synthetic street it drops 0.7% of held-out targets, and about 1% of true returns
(thin poles before a facade, slanted lane markings): the price of what it removes at depth edges.
"""

from __future__ import annotations

import re
from dataclasses import replace
from pathlib import Path
from typing import TYPE_CHECKING, Literal

import numpy as np
import torch

from crfdepth.data.kitti import loading
from crfdepth.data.kitti.drive import ScanFrame, check_scan_files, drive_scans
from crfdepth.data.kitti.loading import FrameDataset, PathLike, Transform
from crfdepth.data.sample import Sample
from crfdepth.data.transforms import BottomCenterCrop, frame_seed
from crfdepth.errors import InputError
from crfdepth.geometry import projection
from crfdepth.io.calibration import read_object_calibration, read_raw_calibration
from crfdepth.io.kitti import read_rgb, read_velodyne
from crfdepth.potentials.occlusion import see_through_mask
from crfdepth.sequences.stereo import baseline_from_projections, remove_stereo_contradicted

if TYPE_CHECKING:
    from crfdepth.io.calibration import Calibration

__all__ = ["KittiRawScans", "remove_see_through", "remove_stereo_contradicted"]


def remove_see_through(target: np.ndarray, full: np.ndarray) -> np.ndarray:
    """The target without its see-through pixels, judged against the whole scan.

    A target pixel is dropped when :func:`crfdepth.potentials.occlusion.see_through_mask` (default
    window and threshold) flags it in ``full``: the projection of the whole scan, input
    and target together, is denser than either part, so every target point is compared
    with all the nearer returns around it, as KITTI compared its annotation with the
    accumulated scans.

    Args:
        target: (H, W) float32 held-out LiDAR z-depth in metres, 0 = no target.
        full: (H, W) float32 projection of the whole scan in metres, 0 = no return; must
            hold the target's value at every target pixel (the target is part of the scan
            and no input point shares its pixels).

    Returns:
        A new (H, W) float32 array: ``target`` with flagged pixels set to 0. ``target``
        is not modified.
    """
    flagged = see_through_mask(torch.from_numpy(np.ascontiguousarray(full, dtype=np.float32))[None, None])
    out = np.array(target, dtype=np.float32, copy=True)
    out[flagged[0, 0].numpy()] = 0.0
    return out


class KittiRawScans(FrameDataset):
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

    Each item projects the scan (:func:`crfdepth.geometry.projection.project_velodyne`, z-buffer,
    camera z-depth in metres) after splitting its points:

    - ``holdout="fraction"``: a random ``1 - holdout_fraction`` of the points is the input,
      the other ``holdout_fraction`` the target. The draw is deterministic per frame: its
      seed is derived from ``seed`` and the frame name (not the index, so a frame keeps its
      split when other frames are added or removed).
    - ``holdout="rings"``: the points of every ``keep_every_ring``-th laser ring (rings
      recovered from the scan order) are the input, all other rings the target: 16 beams
      out of 64 for ``keep_every_ring=4``, the paper's sparse-LiDAR scenario.
    - ``holdout="drop_rings"``: the other way round: every ``drop_every_ring``-th ring is
      the target, all other rings the input (48 of 64 beams in for ``drop_every_ring=4``).
      The targets then lie *between* input scan lines, as most of KITTI's annotated pixels
      do, with an input nearly as dense as the full scan; a random point hold-out puts its
      targets on the input's scan lines only.

    ``keep_fraction`` (< 1) then keeps only that random share of the *input* points (the
    sub-sampling study); the dropped points are not added to the target, and the target
    is the same for every ``keep_fraction`` (same seed), so densities are compared on the
    same pixels.

    No leakage: every target pixel onto which an input point projects (input before the
    ``keep_fraction`` thinning) is set to 0 in the target, so no pixel is both input and
    target. With ``keep_fraction == 1`` and ``clean_target=False``,
    ``(sparse > 0).sum() + (target > 0).sum()`` equals the pixel count of the whole
    scan's projection (with cleaning, that count less the dropped target pixels).

    ``clean_target=True`` (default) then drops every target pixel that
    :func:`remove_see_through` judges see-through against the projection of the whole
    scan (input before thinning plus target, denser than either): raw scans keep the
    background returns the LiDAR sees past foreground edges and the camera does not;
    KITTI's annotation does not (docs/design.md section 3b), and a model trained on them
    learns to blur edges. It removes 2.4-3.6% of the target pixels (module docstring).
    The input is never cleaned (that is the model's job). ``clean_target=False`` keeps
    the raw held-out points, the behaviour before the option existed; say which was
    used when reporting numbers (docs/design.md section 7).

    ``stereo_check=True`` then drops every target pixel the rectified stereo pair contradicts
    (:func:`remove_stereo_contradicted`: the other colour camera, 3 for ``camera=2`` and 2 for
    ``camera=3``, from ``image_0X`` beside the drive's camera folder, or ``image_X`` of the
    object layout; the baseline from the two cameras' ``P_rect``). Only returns stereo
    contradicts with confidence go; texture-less and occluded pixels stay (docs/design.md
    section 16). Off by default: the targets are then those before the option existed.

    The target is thus sparse LiDAR (not KITTI's semi-dense annotation): far fewer
    pixels, and raw-LiDAR noise.

    Args:
        root: the raw-data root (holding ``<date>/``) or the object ``training`` folder.
        layout: "raw" or "object".
        holdout: "fraction", "rings" or "drop_rings".
        holdout_fraction: share of points held out as target, in (0, 1) (``"fraction"``).
        keep_every_ring: k >= 2; rings ``r % k == 0`` are the input (``"rings"``).
        drop_every_ring: k >= 2; rings ``r % k == 0`` are the target (``"drop_rings"``).
        seed: non-negative integer seeding the per-frame random draws.
        keep_fraction: share of input points kept, in (0, 1]; 1 = all.
        camera: KITTI camera index, 2 (left colour, default) or 3.
        clean_target: drop see-through target pixels (:func:`remove_see_through`).
        stereo_check: drop target pixels the stereo pair contradicts (:func:`remove_stereo_contradicted`);
            needs the other colour camera's images.
        transform: applied to every sample; default ``BottomCenterCrop(352, 1216)``.

    Raises:
        FileNotFoundError: ``root`` does not exist.
        InputError: ``root`` does not match the layout (expected folder named); no frame;
            a scan without its image or calibration (path named); bad option values;
            ``stereo_check`` with a drive (or object folder) without the other camera's folder or
            a scan without the other camera's image (path named).
    """

    def __init__(self, root: PathLike, layout: Literal["raw", "object"] = "raw",
                 holdout: Literal["fraction", "rings", "drop_rings"] = "fraction", holdout_fraction: float = 0.2,
                 keep_every_ring: int = 4, drop_every_ring: int = 4, seed: int = 0, keep_fraction: float = 1.0,
                 camera: int = 2, transform: Transform | None = BottomCenterCrop(), clean_target: bool = True,
                 stereo_check: bool = False) -> None:
        if layout not in ("raw", "object"):
            raise InputError(f"layout: expected 'raw' or 'object', got {layout!r}")
        if holdout not in ("fraction", "rings", "drop_rings"):
            raise InputError(f"holdout: expected 'fraction', 'rings' or 'drop_rings', got {holdout!r}")
        if not 0.0 < float(holdout_fraction) < 1.0:
            raise InputError(f"holdout_fraction: expected a value in (0, 1), got {holdout_fraction}")
        if isinstance(keep_every_ring, bool) or int(keep_every_ring) != keep_every_ring or keep_every_ring < 2:
            raise InputError(f"keep_every_ring: expected an integer >= 2, got {keep_every_ring!r}")
        if isinstance(drop_every_ring, bool) or int(drop_every_ring) != drop_every_ring or drop_every_ring < 2:
            raise InputError(f"drop_every_ring: expected an integer >= 2, got {drop_every_ring!r}")
        if not 0.0 < float(keep_fraction) <= 1.0:
            raise InputError(f"keep_fraction: expected a value in (0, 1], got {keep_fraction}")
        if isinstance(seed, bool) or int(seed) != seed or seed < 0:
            raise InputError(f"seed: expected a non-negative integer, got {seed!r}")
        if camera not in (2, 3):
            raise InputError(f"camera: expected 2 or 3 (KITTI colour cameras), got {camera!r}")
        if not isinstance(clean_target, bool):
            raise InputError(f"clean_target: expected True or False, got {clean_target!r}")
        if not isinstance(stereo_check, bool):
            raise InputError(f"stereo_check: expected True or False, got {stereo_check!r}")
        self.root = loading.require_root(root)
        self.layout = layout
        self.holdout = holdout
        self.holdout_fraction = float(holdout_fraction)
        self.keep_every_ring = int(keep_every_ring)
        self.drop_every_ring = int(drop_every_ring)
        self.seed = int(seed)
        self.keep_fraction = float(keep_fraction)
        self.camera = int(camera)
        self.transform = transform
        self.clean_target = clean_target
        self.stereo_check = stereo_check
        self._frames = self._list_raw() if layout == "raw" else self._list_object()
        check_scan_files(self._frames, f"KittiRawScans({layout})")
        self._calibrations: dict[tuple[Path, int], Calibration] = {}
        self._other_images = self._list_other_images() if stereo_check else []
        if layout == "raw":
            for f in self._frames:
                self._calibration(f)  # one file pair per day: read (and check) now
                if stereo_check:
                    self._calibration(f, 5 - self.camera)

    def _list_raw(self) -> list[ScanFrame]:
        cam = f"image_0{self.camera}"
        dates = sorted(p for p in self.root.iterdir() if p.is_dir() and re.fullmatch(r"\d{4}_\d{2}_\d{2}", p.name))
        if not dates:
            raise InputError(f"KittiRawScans(raw): expected {self.root}/<date> folders (e.g. "
                             f"{self.root}/2011_09_26) holding <date>_drive_<NNNN>_sync/, found none")
        frames = []
        for day_dir in dates:
            for drive_dir in sorted(p for p in day_dir.iterdir() if p.is_dir()):
                frames += [replace(f, name=f"{drive_dir.name}_{f.name}_{cam}")
                           for f in drive_scans(drive_dir, self.camera)]
        if not frames:
            raise loading.no_frames(self.root, "KittiRawScans(raw)", "<date>/<drive>/velodyne_points/data/*.bin")
        return frames

    def _list_object(self) -> list[ScanFrame]:
        layout = "KittiRawScans(object)"
        velodyne_dir = loading.require_dir(self.root / "velodyne", self.root, layout)
        image_dir = loading.require_dir(self.root / f"image_{self.camera}", self.root, layout)
        calib_dir = loading.require_dir(self.root / "calib", self.root, layout)
        frames = [
            ScanFrame(name=scan.stem, image=image_dir / f"{scan.stem}.png", velodyne=scan,
                      calib=calib_dir / f"{scan.stem}.txt")
            for scan in sorted(velodyne_dir.glob("*.bin"))
        ]
        if not frames:
            raise loading.no_frames(self.root, layout, "velodyne/*.bin")
        return frames

    def _list_other_images(self) -> list[Path]:
        """The other colour camera's image of every frame (``stereo_check``), each checked to exist."""
        other = 5 - self.camera
        images = []
        for f in self._frames:
            camera_dir = f.image.parent.parent if self.layout == "raw" else f.image.parent
            other_dir = camera_dir.parent / (f"image_0{other}" if self.layout == "raw" else f"image_{other}")
            if not other_dir.is_dir():
                raise InputError(f"stereo_check: expected the other colour camera's folder {other_dir} beside "
                                 f"{camera_dir} (a stereo check needs both cameras), got no such folder")
            path = (other_dir / "data" if self.layout == "raw" else other_dir) / f.image.name
            if not path.is_file():
                raise InputError(f"stereo_check: expected camera {other}'s image {path} for {f.velodyne}, got no "
                                 f"such file")
            images.append(path)
        return images

    def _calibration(self, f: ScanFrame, camera: int | None = None) -> Calibration:
        camera = self.camera if camera is None else camera
        calib = self._calibrations.get((f.calib, camera))
        if calib is None:
            if self.layout == "raw":
                calib = read_raw_calibration(f.calib, camera=camera)
            else:
                calib = read_object_calibration(f.calib, camera=camera)
            self._calibrations[(f.calib, camera)] = calib
        return calib

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
        elif self.holdout == "drop_rings":
            inp = ~projection.ring_mask(points, self.drop_every_ring)
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

    def _stereo_cleaned(self, index: int, target: np.ndarray, rgb: np.ndarray, calib: Calibration) -> np.ndarray:
        other = read_rgb(self._other_images[index])
        if other.shape != rgb.shape:
            raise InputError(f"stereo_check: expected camera {5 - self.camera}'s image {self._other_images[index]} "
                             f"to be {rgb.shape[1]}x{rgb.shape[0]} like {self._frames[index].image}, got "
                             f"{other.shape[1]}x{other.shape[0]}")
        other_calib = self._calibration(self._frames[index], 5 - self.camera)
        return remove_stereo_contradicted(target, rgb, other, calib.K,
                                          baseline_from_projections(calib.P_rect, other_calib.P_rect))

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
        if self.clean_target:
            target = remove_see_through(target, projection.project_velodyne(points, calib, size))
        if self.stereo_check:
            target = self._stereo_cleaned(index, target, rgb, calib)
        return loading.load_sample(
            rgb=rgb, sparse=sparse, target=target, K=calib.K, name=f.name,
            files={"image": f.image, "sparse": f.velodyne, "target": f.velodyne},
            transform=self.transform,
        )
