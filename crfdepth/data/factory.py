"""Datasets by layout name: one entry point for the trainer, ``crfdepth evaluate`` and benchmarks."""

from __future__ import annotations

from pathlib import Path
from typing import Literal

from torch.utils.data import Dataset

from crfdepth.checks import check_choice
from crfdepth.errors import InputError

Layout = Literal["depth_completion", "annotated", "val_selection", "test_selection", "raw", "object", "synthetic",
                 "sequence"]
LAYOUTS = ("depth_completion", "annotated", "val_selection", "test_selection", "raw", "object", "synthetic", "sequence")


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
      ``beams``); ``root`` is ignored.
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
    if layout == "sequence":
        from crfdepth.data.sequences import SequenceFrames

        return SequenceFrames(root, **options)
    if layout == "test_selection":
        return kitti.KittiTestCompletion(root, **options)
    return kitti.KittiRawScans(root, layout=layout, **options)
