"""Torch datasets of NYU Depth v2 (Silberman et al., ECCV 2012), indoor Kinect v1 frames (docs/design.md section 17).

Every dataset returns a :class:`~crfdepth.data.sample.Sample`: the colour image, the depth registered
to it in metres (0 = no depth), ``K`` of the frame's size (:mod:`~crfdepth.data.nyu.camera`) and a
name; depth files are checked to be millimetres (:func:`~crfdepth.io.depth_image.read_depth_image`).

- :class:`NyuSync` (:mod:`~crfdepth.data.nyu.sync`): the "sync" layout of the official test split,
  ``<scene>/rgb_XXXXX.jpg`` with ``sync_depth_XXXXX.png``; sparse = target = the depth with holes.
- :class:`NyuRawFilled` (:mod:`~crfdepth.data.nyu.raw_filled`): the labeled set's raw depth (holes)
  as input, its filled depth as target (``images.png``, ``rawdepth.png``, ``depth.png``).
- :class:`NyuH5` (:mod:`~crfdepth.data.nyu.h5`): the Sparse-to-Dense HDF5 release,
  ``nyudepthv2/{train,val}/<scene>/<n>.h5``; sparse = target = the filled depth (needs
  ``pip install "crfdepth[nyu]"``).

The published protocol (500 samples of the ground truth, 304 x 228) is a transform,
:func:`~crfdepth.data.sampling.nyu_protocol`; :func:`crfdepth.data.build_dataset` applies it to the
layouts ``nyu_sync``, ``nyu_raw`` and ``nyu_h5`` when given ``samples``
(:func:`~crfdepth.data.nyu.layouts.build_nyu_dataset`).
"""

from crfdepth.data.nyu.camera import NYU_K, nyu_intrinsics
from crfdepth.data.nyu.h5 import NyuH5
from crfdepth.data.nyu.layouts import NYU_LAYOUTS, build_nyu_dataset
from crfdepth.data.nyu.raw_filled import NyuRawFilled
from crfdepth.data.nyu.sync import NyuSync

__all__ = ["NYU_K", "NYU_LAYOUTS", "NyuH5", "NyuRawFilled", "NyuSync", "build_nyu_dataset", "nyu_intrinsics"]
