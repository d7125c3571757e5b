"""NYU v2 raw Kinect depth with holes, paired with the in-painted (filled) depth of the same frame.

The labeled set of NYU v2 (1449 frames) gives, per frame, the colour image, the raw depth with
holes and the depth filled by colourisation; exported one frame per folder as ``images.png``,
``rawdepth.png`` and ``depth.png`` (uint16 millimetres), often cropped to the 560 x 425 that many
papers evaluate on (docs/design.md section 17). Completing the raw depth against the filled one
is NYU's own depth-completion task: real holes (edges, dark, shiny and far surfaces), not random
samples.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from crfdepth.data.nyu.frames import (
    FrameDataset,
    PathLike,
    Transform,
    check_root,
    frame_sample,
    no_frames,
    read_png_frame,
    scene_name,
)
from crfdepth.data.sample import Sample
from crfdepth.errors import InputError

__all__ = ["FILES", "NyuRawFilled"]

#: The files of one frame's folder: colour image, raw depth (holes), filled depth.
FILES = ("images.png", "rawdepth.png", "depth.png")
_EXPECTED = "folders of images.png, rawdepth.png and depth.png in millimetres"


@dataclass(frozen=True)
class _RawFrame:
    name: str
    image: Path
    raw: Path
    filled: Path


class NyuRawFilled(FrameDataset):
    """NYU v2 frames with the raw Kinect depth as input and the filled depth as target.

    Each folder holding ``images.png``, ``rawdepth.png`` and ``depth.png`` (``root`` itself, or any
    folder under it) is one frame: ``sparse`` = the raw depth (metres, 0 = hole), ``target`` = the
    filled depth, ``K`` from the image size: 640 x 480, a scale of it, or the 560 x 425 crop
    (``cx = 285.58``, ``cy = 209.74``; :func:`~crfdepth.data.nyu.camera.nyu_intrinsics`). The name is
    the folder's path under ``root`` joined by ``_`` (``root``'s own name when ``root`` is the frame).

    Args:
        root: one frame's folder or a folder of them.
        transform: applied to every sample; default None (the frame as stored).

    Raises:
        InputError: ``root`` does not exist or holds no frame; a folder with some of the three files but
            not all (the missing one named). On ``__getitem__``: a depth file that is not a 16-bit PNG of
            millimetres, or not the size of the image (both files named); an image size that is neither a
            scale of 640 x 480 nor the 560 x 425 crop.
    """

    def __init__(self, root: PathLike, transform: Transform | None = None) -> None:
        self.root = check_root(root, "NyuRawFilled", _EXPECTED)
        self.transform = transform
        folders = sorted({p.parent for name in FILES for p in self.root.rglob(name) if p.is_file()})
        frames = []
        for folder in folders:
            missing = [name for name in FILES if not (folder / name).is_file()]
            if missing:
                raise InputError(f"root: expected {', '.join(FILES)} together in {folder} (the NyuRawFilled layout), "
                                 f"got no {', '.join(missing)}")
            image, raw, filled = (folder / name for name in FILES)
            frames.append(_RawFrame(scene_name(folder, self.root), image, raw, filled))
        if not frames:
            raise no_frames(self.root, "NyuRawFilled", _EXPECTED)
        self._frames = frames

    def __getitem__(self, index: int) -> Sample:
        f = self._frames[index]
        rgb, (raw, filled) = read_png_frame(f.image, (f.raw, f.filled))
        return frame_sample(rgb, raw, filled, f.name, image_argument=str(f.image), transform=self.transform)
