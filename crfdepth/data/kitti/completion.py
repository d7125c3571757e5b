"""KITTI depth completion in its official layout (``data_depth_velodyne`` + ``data_depth_annotated``).

RGB images and calibration come from the raw-data tree; the target is KITTI's
semi-dense annotation (docs/design.md section 7).
"""

from __future__ import annotations

import os
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Literal

from crfdepth.data.kitti import loading
from crfdepth.data.kitti.loading import FrameDataset, PathLike, Transform
from crfdepth.data.sample import Sample
from crfdepth.data.transforms import BottomCenterCrop
from crfdepth.errors import InputError
from crfdepth.io.calibration import read_raw_calibration
from crfdepth.io.kitti import read_depth_png, read_rgb

if TYPE_CHECKING:
    from crfdepth.io.calibration import Calibration

__all__ = ["KittiDepthCompletion"]

from crfdepth.data.kitti.loading import CAMERAS, DRIVE_NAME, check_cameras


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


class KittiDepthCompletion(FrameDataset):
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
        camera: str | Sequence[str] = CAMERAS,
        raw_root: PathLike | None = None,
        transform: Transform | None = BottomCenterCrop(),
    ) -> None:
        layout = "KittiDepthCompletion"
        if split not in ("train", "val"):
            raise InputError(f"split: expected 'train' or 'val', got {split!r}")
        self.root = loading.require_root(root)
        self.split = split
        self.cameras = check_cameras(camera)
        self.raw_root = loading.require_root(self.root.parent / "raw" if raw_root is None else raw_root, "raw_root")
        self.transform = transform

        velodyne_dir = loading.require_dir(self.root / "data_depth_velodyne" / split, self.root, layout)
        annotated_dir = loading.require_dir(self.root / "data_depth_annotated" / split, self.root, layout)

        frames: list[_CompletionFrame] = []
        for drive_dir in sorted(p for p in velodyne_dir.iterdir() if p.is_dir()):
            drive = drive_dir.name
            match = DRIVE_NAME.match(drive)
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
            raise loading.no_frames(self.root, layout,
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

    def __getitem__(self, index: int) -> Sample:
        f = self._frames[index]
        return loading.load_sample(
            rgb=read_rgb(f.image),
            sparse=read_depth_png(f.sparse),
            target=read_depth_png(f.target),
            K=self._calibration(f).K,
            name=f.name,
            files={"image": f.image, "sparse": f.sparse, "target": f.target},
            transform=self.transform,
        )
