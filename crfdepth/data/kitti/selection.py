"""KITTI ``depth_selection`` folders: ``val_selection_cropped`` and ``test_depth_completion_anonymous``.

Both are already cropped to 1216 x 352 and give K per frame in ``intrinsics/``; the
validation selection has ground truth, the test selection none (docs/design.md
section 7). :func:`open_completion_folder` picks the layout of a folder.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from crfdepth.data.kitti import loading
from crfdepth.data.kitti.loading import FrameDataset, PathLike, Transform
from crfdepth.data.sample import Sample
from crfdepth.errors import InputError
from crfdepth.io.kitti import read_depth_png, read_intrinsics, read_rgb

__all__ = ["KittiTestCompletion", "KittiValSelection", "open_completion_folder"]


def _resolve_subfolder(root: Path, name: str, marker: str) -> Path:
    """Accept either ``.../<name>`` itself or its parent (``depth_selection``)."""
    if not (root / marker).is_dir() and (root / name / marker).is_dir():
        return root / name
    return root


@dataclass(frozen=True)
class _SelectionFrame:
    name: str
    sparse: Path
    image: Path
    target: Path | None
    intrinsics: Path


class _SelectionDataset(FrameDataset):
    """Shared code of the two ``depth_selection`` layouts (already cropped, K per file)."""

    _layout = ""
    _folder = ""
    _with_target = True

    def __init__(self, root: PathLike, transform: Transform | None = None) -> None:
        self.root = _resolve_subfolder(loading.require_root(root), self._folder, "velodyne_raw")
        self.transform = transform
        layout = self._layout
        sparse_dir = loading.require_dir(self.root / "velodyne_raw", self.root, layout)
        image_dir = loading.require_dir(self.root / "image", self.root, layout)
        intrinsics_dir = loading.require_dir(self.root / "intrinsics", self.root, layout)
        target_dir = (loading.require_dir(self.root / "groundtruth_depth", self.root, layout)
                      if self._with_target else None)

        frames = []
        for sparse in sorted(sparse_dir.glob("*.png")):
            frames.append(self._frame(sparse, image_dir, target_dir, intrinsics_dir))
        if not frames:
            raise loading.no_frames(self.root, layout, "velodyne_raw/*.png")
        for f in frames:
            for path, what in ((f.image, "RGB image"), (f.intrinsics, "intrinsics"), (f.target, "ground truth")):
                if path is not None and not path.is_file():
                    raise InputError(f"{layout}: missing {what} for {f.sparse}: expected {path}")
        self._frames = frames

    def _frame(self, sparse: Path, image_dir: Path, target_dir: Path | None, intrinsics_dir: Path) -> _SelectionFrame:
        raise NotImplementedError

    def sparse_path(self, index: int) -> Path:
        """The ``velodyne_raw`` PNG of frame ``index`` (it names the frame and gives its size)."""
        return self._frames[index].sparse

    def __getitem__(self, index: int) -> Sample:
        f = self._frames[index]
        return loading.load_sample(
            rgb=read_rgb(f.image),
            sparse=read_depth_png(f.sparse),
            target=read_depth_png(f.target) if f.target is not None else None,
            K=read_intrinsics(f.intrinsics),
            name=f.name,
            files={"image": f.image, "sparse": f.sparse, "target": f.target},
            transform=self.transform,
        )


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


def open_completion_folder(
    root: PathLike, transform: Transform | None = None
) -> KittiValSelection | KittiTestCompletion:
    """The ``depth_selection`` dataset in ``root``, whichever of the two layouts it holds.

    A :class:`KittiValSelection` when ``root`` or its ``val_selection_cropped`` sub-folder
    holds ``groundtruth_depth/``; otherwise a :class:`KittiTestCompletion` (``root`` itself
    or its ``test_depth_completion_anonymous`` sub-folder, no target).

    Args:
        root: a ``val_selection_cropped`` or ``test_depth_completion_anonymous`` folder (with
            ``image/``, ``velodyne_raw/``, ``intrinsics/``), or their parent
            ``depth_selection``.
        transform: applied to every sample; default None (frames are already cropped).

    Raises:
        FileNotFoundError: ``root`` does not exist.
        InputError: ``root`` matches neither layout, or holds no frame (as the datasets).
    """
    folder = loading.require_root(root)
    val_folder = KittiValSelection._folder
    if (folder / "groundtruth_depth").is_dir() or (folder / val_folder / "groundtruth_depth").is_dir():
        return KittiValSelection(folder, transform=transform)
    return KittiTestCompletion(folder, transform=transform)
