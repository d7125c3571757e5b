"""Data for crfdepth: KITTI datasets, the built-in synthetic scene, samples and transforms.

Every dataset returns a :class:`Sample` (docs/design.md section 1); :func:`build_dataset`
builds one by layout name. Sub-modules: :mod:`~crfdepth.data.kitti`, :mod:`~crfdepth.data.nyu`
(NYU Depth v2, docs/design.md section 17), :mod:`~crfdepth.data.synthetic`,
:mod:`~crfdepth.data.sample`, :mod:`~crfdepth.data.transforms`, :mod:`~crfdepth.data.sampling`
(resize, centre crop, sparse samples and the published protocols), :mod:`~crfdepth.data.factory`
and :mod:`~crfdepth.data.example` (the own-sensor example files).
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from crfdepth.lazy import lazy_names

if TYPE_CHECKING:
    from crfdepth.data.factory import LAYOUTS, build_dataset
    from crfdepth.data.kitti import (
        KittiDepthCompletion,
        KittiDrive,
        KittiRawScans,
        KittiTestCompletion,
        KittiValSelection,
        open_completion_folder,
    )
    from crfdepth.data.nyu import NYU_K, NyuH5, NyuRawFilled, NyuSync, nyu_intrinsics
    from crfdepth.data.sample import Batch, Sample, collate_samples
    from crfdepth.data.sampling import CenterCrop, Resize, SparseSamples, kitti_table4, nyu_protocol
    from crfdepth.data.synthetic import EVAL_MAX_DEPTH_M, SyntheticScene, SyntheticScenes, make_scene
    from crfdepth.data.transforms import (
        BottomCenterCrop,
        Compose,
        HorizontalFlip,
        RandomCrop,
        RandomThinning,
        SubsampleSparse,
    )

# Where each name lives, imported at its first use (PEP 562): a command that needs only the Sample record
# (crfdepth.data.sample) does not import every dataset, and with them kornia and SciPy.
_LAZY = {
    **dict.fromkeys(["LAYOUTS", "build_dataset"], "crfdepth.data.factory"),
    **dict.fromkeys(["KittiDepthCompletion", "KittiDrive", "KittiRawScans", "KittiTestCompletion", "KittiValSelection",
                     "open_completion_folder"], "crfdepth.data.kitti"),
    **dict.fromkeys(["NYU_K", "NyuH5", "NyuRawFilled", "NyuSync", "nyu_intrinsics"], "crfdepth.data.nyu"),
    **dict.fromkeys(["Batch", "Sample", "collate_samples"], "crfdepth.data.sample"),
    **dict.fromkeys(["CenterCrop", "Resize", "SparseSamples", "kitti_table4", "nyu_protocol"], "crfdepth.data.sampling"),
    **dict.fromkeys(["EVAL_MAX_DEPTH_M", "SyntheticScene", "SyntheticScenes", "make_scene"], "crfdepth.data.synthetic"),
    **dict.fromkeys(["BottomCenterCrop", "Compose", "HorizontalFlip", "RandomCrop", "RandomThinning", "SubsampleSparse"],
                    "crfdepth.data.transforms"),
}


__getattr__, __dir__ = lazy_names(__name__, _LAZY)


__all__ = [
    "EVAL_MAX_DEPTH_M",
    "LAYOUTS",
    "Batch",
    "BottomCenterCrop",
    "CenterCrop",
    "Compose",
    "HorizontalFlip",
    "KittiDepthCompletion",
    "KittiDrive",
    "KittiRawScans",
    "KittiTestCompletion",
    "KittiValSelection",
    "NYU_K",
    "NyuH5",
    "NyuRawFilled",
    "NyuSync",
    "RandomCrop",
    "RandomThinning",
    "Resize",
    "Sample",
    "SparseSamples",
    "SubsampleSparse",
    "SyntheticScene",
    "SyntheticScenes",
    "build_dataset",
    "collate_samples",
    "kitti_table4",
    "make_scene",
    "nyu_intrinsics",
    "nyu_protocol",
    "open_completion_folder",
]
