"""NYU v2 in the "sync" layout of depth-estimation repositories: ``rgb_XXXXX.jpg`` with ``sync_depth_XXXXX.png``.

The layout of the official test split as BTS and its successors ship it (docs/design.md section 17):
one folder per scene, each frame a JPEG colour image and the Kinect depth projected into it, a
uint16 PNG of millimetres with holes (0 = no depth; 67-75 % of the pixels valid on the test scenes).
"""

from __future__ import annotations

import re
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

__all__ = ["NyuSync"]

_RGB = re.compile(r"^rgb_(\d+)\.jpg$")
_DEPTH = re.compile(r"^sync_depth_(\d+)\.png$")
_EXPECTED = "rgb_XXXXX.jpg with sync_depth_XXXXX.png in millimetres, in scene folders"


@dataclass(frozen=True)
class _SyncFrame:
    name: str
    image: Path
    depth: Path


class NyuSync(FrameDataset):
    """NYU v2 frames of the "sync" layout: ``<scene>/rgb_XXXXX.jpg`` and ``<scene>/sync_depth_XXXXX.png``.

    Each frame's sample has the 640 x 480 image, ``sparse`` = the Kinect depth with its holes and
    ``target`` = the same depth (metres, 0 = no depth), ``K`` from the image size
    (:func:`~crfdepth.data.nyu.camera.nyu_intrinsics`) and the name ``<scene>_<XXXXX>``. A protocol
    transform (:func:`~crfdepth.data.sampling.nyu_protocol`) then draws the sparse samples from the
    target.

    Args:
        root: a folder of frames, or of scene folders of frames (searched at any depth); the scene is
            the frame's folder under ``root`` (``root``'s own name for frames directly in it).
        transform: applied to every sample; default None (the frame as stored).

    Raises:
        InputError: ``root`` does not exist or holds no frame; an image without its depth file or a depth
            file without its image (both named); names that repeat. On ``__getitem__``: a depth file that is
            not a 16-bit PNG of millimetres, or not the size of its image (both files named).
    """

    def __init__(self, root: PathLike, transform: Transform | None = None) -> None:
        self.root = check_root(root, "NyuSync", _EXPECTED)
        self.transform = transform
        frames, depths = [], set()
        for path in sorted(self.root.rglob("*")):
            if _DEPTH.match(path.name) and path.is_file():
                depths.add(path)
            match = _RGB.match(path.name)
            if match is None or not path.is_file():
                continue
            depth = path.with_name(f"sync_depth_{match.group(1)}.png")
            if not depth.is_file():
                raise InputError(f"root: expected {depth.name} beside {path} (the {_EXPECTED} layout), got no such "
                                 f"file")
            frames.append(_SyncFrame(f"{scene_name(path.parent, self.root)}_{match.group(1)}", path, depth))
        orphans = sorted(depths - {f.depth for f in frames})
        if orphans:
            raise InputError(f"root: expected rgb_{_DEPTH.match(orphans[0].name).group(1)}.jpg beside {orphans[0]} "
                             f"(the {_EXPECTED} layout), got no such file ({len(orphans)} depth file(s) without "
                             f"their image)")
        if not frames:
            raise no_frames(self.root, "NyuSync", _EXPECTED)
        names = [f.name for f in frames]
        if len(set(names)) != len(names):
            twice = sorted({n for n in names if names.count(n) > 1})
            raise InputError(f"root: expected one frame per name <scene>_<XXXXX> under {self.root}, got {twice[:3]} "
                             f"more than once")
        self._frames = frames

    def __getitem__(self, index: int) -> Sample:
        f = self._frames[index]
        rgb, (depth,) = read_png_frame(f.image, (f.depth,))
        return frame_sample(rgb, depth, depth.copy(), f.name, image_argument=str(f.image), transform=self.transform)
