"""A KITTI raw drive as frames to complete: each Velodyne scan projected whole into one colour camera.

A raw drive folder is ``<day>/<day>_drive_<NNNN>_sync`` with ``velodyne_points/data/<frame>.bin``
and ``image_0X/data/<frame>.png``; the day folder above it holds the calibration
(``calib_cam_to_cam.txt``, ``calib_velo_to_cam.txt``; docs/design.md section 1). :class:`KittiDrive`
reads one drive for completion (``crfdepth complete --input-dir DRIVE``); the listing of a drive's
scans (:func:`drive_scans`, :func:`check_scan_files`) is shared with
:class:`~crfdepth.data.kitti.raw_scans.KittiRawScans`, which splits each scan into input and target.
:func:`is_raw_drive` and :func:`raw_drives` tell a drive folder, and the drives of a day folder.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from crfdepth.data.kitti import loading
from crfdepth.data.kitti.loading import FrameDataset, PathLike, Transform
from crfdepth.data.sample import Sample
from crfdepth.errors import InputError
from crfdepth.geometry import projection
from crfdepth.io.calibration import read_raw_calibration
from crfdepth.io.kitti import read_rgb, read_velodyne

__all__ = ["KittiDrive", "ScanFrame", "check_scan_files", "drive_scans", "is_raw_drive", "raw_drives", "shown_drives"]

SCANS = "velodyne_points"


@dataclass(frozen=True)
class ScanFrame:
    """One Velodyne scan and the files it needs."""

    name: str
    image: Path
    velodyne: Path
    calib: Path  # day folder (raw) or calibration file (object)


def is_raw_drive(path: PathLike) -> bool:
    """Whether ``path`` is laid out as a KITTI raw drive: a folder holding ``velodyne_points/`` or an
    ``image_0X/`` camera folder (what else a drive must hold, :class:`KittiDrive` checks and names)."""
    folder = Path(path)
    return (folder / SCANS).is_dir() or any((folder / f"image_0{camera}").is_dir() for camera in range(4))


def raw_drives(path: PathLike) -> list[Path]:
    """The raw drive folders directly inside ``path`` (a day folder such as ``2011_09_26``), sorted; [] when
    ``path`` is no folder or holds none."""
    folder = Path(path)
    if not folder.is_dir():
        return []
    return sorted(p for p in folder.iterdir() if p.is_dir() and is_raw_drive(p))


def shown_drives(drives: list[Path]) -> str:
    """The first three of ``drives`` by name, for messages: ``a, b, c, ...``."""
    return ", ".join(p.name for p in drives[:3]) + (", ..." if len(drives) > 3 else "")


def drive_scans(drive_dir: Path, camera: int) -> list[ScanFrame]:
    """The scans of one drive in frame order, each named by its frame number (the ``.bin`` stem), with its
    image ``image_0<camera>/data/<frame>.png`` and the day folder (``drive_dir``'s parent) as calibration.
    The files are listed, not checked (:func:`check_scan_files`)."""
    cam = f"image_0{camera}"
    return [ScanFrame(name=scan.stem, image=drive_dir / cam / "data" / f"{scan.stem}.png", velodyne=scan,
                      calib=drive_dir.parent)
            for scan in sorted((drive_dir / SCANS / "data").glob("*.bin"))]


def check_scan_files(frames: list[ScanFrame], layout: str) -> None:
    """InputError naming the first scan of ``frames`` without its image or calibration, and the path expected."""
    for f in frames:
        for path, what in ((f.image, "RGB image"), (f.calib, "calibration")):
            if not path.exists():
                raise InputError(f"{layout}: missing {what} for {f.velodyne}: expected {path}")


class KittiDrive(FrameDataset):
    """The frames of one KITTI raw drive for completion: sparse input = the frame's whole scan, no target.

    Frames are the scans ``root/velodyne_points/data/<frame>.bin`` in frame order; each needs its
    image ``root/image_0X/data/<frame>.png``. The calibration is the day folder's (``root``'s
    parent) ``calib_cam_to_cam.txt`` and ``calib_velo_to_cam.txt``, read once
    (:func:`crfdepth.io.calibration.read_raw_calibration`). Images without a scan are not frames.

    Each item projects the whole scan into the camera
    (:func:`crfdepth.geometry.projection.project_velodyne`: z-buffer, z-depth in metres, 0 = no
    return), as ``crfdepth complete --points SCAN --calib DAY`` does for one frame. The image is
    kept whole (1242 x 375 for KITTI; no crop, so an output covers the image it belongs to; the
    rows above the LiDAR's field of view get the model's extrapolation), ``K = P_rect_0X[:, :3]``,
    the name is the frame number (``0000000005``), and the target is all zeros
    (``has_target=False``).

    Args:
        root: the drive folder (``<day>/<day>_drive_<NNNN>_sync``).
        camera: KITTI colour camera, 2 (left, default) or 3 (right).
        transform: applied to every sample; default None (the whole image).

    Raises:
        FileNotFoundError: ``root`` does not exist.
        InputError: ``root`` is a day folder (its drives named), or has no
            ``velodyne_points/data``; no scan; a scan without its image, or the day folder
            without a calibration file (path named); a bad ``camera``. On ``__getitem__``: the
            image is not the calibration's size (``S_rect_0X``), or a file does not read.
    """

    def __init__(self, root: PathLike, camera: int = 2, transform: Transform | None = None) -> None:
        if camera not in (2, 3):
            raise InputError(f"camera: expected 2 or 3 (KITTI colour cameras), got {camera!r}")
        self.root = loading.require_root(root)
        self.camera = int(camera)
        self.transform = transform
        layout = "KittiDrive"
        if not is_raw_drive(self.root):
            drives = raw_drives(self.root)
            if drives:
                raise InputError(f"{layout}: expected one raw drive folder, got the day folder {self.root} holding "
                                 f"{len(drives)} drive(s) ({shown_drives(drives)}); give a drive folder, e.g. "
                                 f"{drives[0]}")
        loading.require_dir(self.root / SCANS / "data", self.root, layout)
        self._frames = drive_scans(self.root, self.camera)
        if not self._frames:
            raise loading.no_frames(self.root, layout, f"{SCANS}/data/*.bin")
        check_scan_files(self._frames, layout)
        try:
            self.calibration = read_raw_calibration(self.root.parent, camera=self.camera)
        except FileNotFoundError as exc:
            raise InputError(f"{layout}: missing calibration of {self.root}: {str(exc).removeprefix('calibration: ')} "
                             f"(the day folder above a drive holds calib_cam_to_cam.txt and "
                             f"calib_velo_to_cam.txt)") from None

    def image_path(self, index: int) -> Path:
        """The image of frame ``index`` (its PNG header gives the frame's size)."""
        return self._frames[index].image

    def __getitem__(self, index: int) -> Sample:
        f = self._frames[index]
        rgb = read_rgb(f.image)
        size = rgb.shape[:2]
        expected = self.calibration.image_size
        if expected is not None and size != expected:
            raise InputError(f"{f.name}: image {f.image} is {size[1]}x{size[0]} (WxH), expected the calibration's "
                             f"{expected[1]}x{expected[0]} (S_rect_0{self.camera} in "
                             f"{self.root.parent / 'calib_cam_to_cam.txt'})")
        sparse = projection.project_velodyne(read_velodyne(f.velodyne), self.calibration, size)
        return loading.load_sample(rgb=rgb, sparse=sparse, target=None, K=self.calibration.K, name=f.name,
                                   files={"image": f.image, "sparse": f.velodyne}, transform=self.transform)
