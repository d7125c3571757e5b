"""Datasets by layout name: one entry point for the trainer, ``crfdepth evaluate`` and benchmarks."""

from __future__ import annotations

from pathlib import Path
from typing import Literal

from torch.utils.data import Dataset

from crfdepth.checks import check_choice
from crfdepth.errors import InputError

Layout = Literal["depth_completion", "annotated", "val_selection", "test_selection", "raw", "object", "synthetic",
                 "sequence", "nyu_sync", "nyu_raw", "nyu_h5"]
LAYOUTS = ("depth_completion", "annotated", "val_selection", "test_selection", "raw", "object", "synthetic", "sequence",
           "nyu_sync", "nyu_raw", "nyu_h5")


def build_dataset(layout: Layout, root: str | Path | None = None, **options) -> Dataset:
    """The dataset of ``layout`` under ``root``; ``options`` go to its constructor.

    ``layout``:

    - ``"depth_completion"``: :class:`~crfdepth.data.kitti.KittiDepthCompletion` (``split``, ``raw_root``, ...);
    - ``"annotated"``: :class:`~crfdepth.data.kitti.KittiAnnotated` (KITTI's annotation with the input
      drawn from it or from the frame's scan: ``input``, ``input_share``, ``keep_every_ring``, ``seed``);
    - ``"val_selection"``: :class:`~crfdepth.data.kitti.KittiValSelection` (``depth_selection/val_selection_cropped``);
    - ``"test_selection"``: :class:`~crfdepth.data.kitti.KittiTestCompletion` (no target);
    - ``"raw"`` / ``"object"``: :class:`~crfdepth.data.kitti.KittiRawScans` with held-out LiDAR
      targets (``holdout``, ``holdout_fraction``, ``keep_every_ring``, ``keep_fraction``, ``seed``);
    - ``"synthetic"``: :class:`~crfdepth.data.synthetic.SyntheticScenes` (``count``, ``seed``,
      ``beams``); ``root`` is ignored;
    - ``"nyu_sync"`` / ``"nyu_raw"`` / ``"nyu_h5"``: NYU Depth v2 (docs/design.md section 17):
      :class:`~crfdepth.data.nyu.NyuSync`, :class:`~crfdepth.data.nyu.NyuRawFilled`,
      :class:`~crfdepth.data.nyu.NyuH5` (``split``), through
      :func:`~crfdepth.data.nyu.layouts.build_nyu_dataset`: with ``samples`` (and ``seed``) the
      published protocol (320 x 240, centre 304 x 228, ``samples`` pixels of the ground truth as the
      input: :func:`~crfdepth.data.sampling.nyu_protocol`; ``protocol=False`` keeps the full size),
      without them the frames as stored.
    """
    from crfdepth.data import kitti, synthetic

    if layout == "synthetic":
        return synthetic.SyntheticScenes(**options)
    check_choice("layout", layout, LAYOUTS)
    if root is None:
        raise InputError(f"root: a data folder is needed for layout {layout!r}")
    if layout == "depth_completion":
        return kitti.KittiDepthCompletion(root, **options)
    if layout == "annotated":
        return kitti.KittiAnnotated(root, **options)
    if layout == "val_selection":
        return kitti.KittiValSelection(root, **options)
    if layout.startswith("nyu_"):
        from crfdepth.data.nyu.layouts import build_nyu_dataset

        return build_nyu_dataset(layout, root, **options)
    if layout == "sequence":
        from crfdepth.data.sequences import SequenceFrames

        return SequenceFrames(root, **options)
    if layout == "test_selection":
        return kitti.KittiTestCompletion(root, **options)
    return kitti.KittiRawScans(root, layout=layout, **options)
