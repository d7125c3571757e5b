"""Torch datasets for every KITTI layout crfdepth reads (docs/design.md sections 1 and 7).

All six datasets return a :class:`~crfdepth.data.sample.Sample` built by one loading path
(:func:`~crfdepth.data.kitti.loading.load_sample`): read RGB, sparse depth, ground truth
and ``K`` from files, check that their sizes agree, convert to tensors, then apply the
dataset's ``transform``.

- :class:`KittiDepthCompletion` (:mod:`~crfdepth.data.kitti.completion`): the official
  ``data_depth_velodyne`` / ``data_depth_annotated`` trees, RGB and calibration from the
  raw-data tree; target = KITTI's semi-dense annotation.
- :class:`KittiAnnotated` (:mod:`~crfdepth.data.kitti.annotated`): frames with KITTI's
  annotation, the input drawn from it (a share of its pixels, or a ring pattern) or the scan.
- :class:`KittiValSelection` (:mod:`~crfdepth.data.kitti.selection`):
  ``depth_selection/val_selection_cropped``; annotated target.
- :class:`KittiTestCompletion` (:mod:`~crfdepth.data.kitti.selection`):
  ``depth_selection/test_depth_completion_anonymous``; no target (all zeros,
  ``has_target=False``). :func:`open_completion_folder` picks one of the two for a folder.
- :class:`KittiRawScans` (:mod:`~crfdepth.data.kitti.raw_scans`): raw-data drives or the
  object benchmark with Velodyne scans, projected here; target = LiDAR points held out of
  the input.
- :class:`KittiDrive` (:mod:`~crfdepth.data.kitti.drive`): one raw drive folder for
  completion: each scan projected whole into the uncropped image, no target
  (``has_target=False``); names are the frame numbers.

Files are listed once, at construction, in sorted (deterministic) order; a layout that
does not match, or one that holds no frame, raises at construction rather than giving an
empty dataset.

Errors: a ``root`` that does not exist raises ``FileNotFoundError`` with the path; a root
without the expected sub-folders, zero frames, an input without its target/RGB file, or RGB
and depth of different sizes raise :class:`~crfdepth.errors.InputError` naming the folder,
file(s) and sizes.
"""

from crfdepth.data.kitti.annotated import KittiAnnotated
from crfdepth.data.kitti.completion import KittiDepthCompletion
from crfdepth.data.kitti.drive import KittiDrive, is_raw_drive, raw_drives
from crfdepth.data.kitti.loading import load_sample
from crfdepth.data.kitti.raw_scans import KittiRawScans
from crfdepth.data.kitti.selection import KittiTestCompletion, KittiValSelection, open_completion_folder

__all__ = [
    "KittiAnnotated",
    "KittiDepthCompletion",
    "KittiDrive",
    "KittiRawScans",
    "KittiTestCompletion",
    "KittiValSelection",
    "is_raw_drive",
    "load_sample",
    "open_completion_folder",
    "raw_drives",
]
