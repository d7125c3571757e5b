"""The NYU v2 layouts of :func:`crfdepth.data.build_dataset`, with the protocol transform when samples are asked for.

``build_dataset("nyu_h5", root, samples=500, seed=0)`` gives the frames of the Sparse-to-Dense
protocol (docs/design.md section 17): resized to 320 x 240, centre-cropped to 304 x 228, with 500
pixels of the ground truth as the sparse input (:func:`~crfdepth.data.sampling.nyu_protocol`).
"""

from __future__ import annotations

from typing import Any

from crfdepth.data.nyu.h5 import NyuH5
from crfdepth.data.nyu.raw_filled import NyuRawFilled
from crfdepth.data.nyu.sync import NyuSync
from crfdepth.data.sampling import SparseSamples, nyu_protocol
from crfdepth.data.transforms import Compose
from crfdepth.errors import InputError

__all__ = ["NYU_LAYOUTS", "build_nyu_dataset"]

#: Layout name -> dataset class.
NYU_LAYOUTS = {"nyu_sync": NyuSync, "nyu_raw": NyuRawFilled, "nyu_h5": NyuH5}


def build_nyu_dataset(layout: str, root: Any, *, samples: int | None = None, seed: Any = ...,
                      protocol: bool | None = None, transform: Any = None, **options: Any):
    """The NYU v2 dataset of ``layout`` (a key of :data:`NYU_LAYOUTS`) under ``root``.

    Args:
        layout: ``"nyu_sync"`` (:class:`~crfdepth.data.nyu.NyuSync`), ``"nyu_raw"``
            (:class:`~crfdepth.data.nyu.NyuRawFilled`) or ``"nyu_h5"`` (:class:`~crfdepth.data.nyu.NyuH5`).
        root: the dataset's folder.
        samples: pixels of the ground truth drawn per frame as the sparse input
            (:class:`~crfdepth.data.sampling.SparseSamples`); None: the sparse map as stored (the Kinect
            depth with holes, or the raw depth of ``nyu_raw``).
        seed: the draw's seed (default 0; None: torch's global generator, fresh draws per epoch under the
            trainer); only with ``samples``.
        protocol: resize to 320 x 240 and centre-crop to 304 x 228 first (Ma & Karaman 2018). None (the
            default): exactly when ``samples`` is given, so ``samples=500`` gives the published protocol and
            no options give the frame as stored, full size.
        transform: applied after the protocol; default None.
        options: further keyword options of the dataset (``split`` for ``nyu_h5``).

    Raises:
        InputError: ``seed`` without ``samples``; a bad ``samples`` or ``seed``; the dataset's own refusals.
    """
    if seed is not ... and samples is None:
        raise InputError(f"seed: expected together with samples (it seeds their draw), got seed={seed!r} without "
                         f"samples")
    seed = 0 if seed is ... else seed
    protocol = samples is not None if protocol is None else bool(protocol)
    steps = []
    if protocol:
        steps.append(nyu_protocol(samples, seed))
    elif samples is not None:
        steps.append(SparseSamples(samples, seed))
    if transform is not None:
        steps.append(transform)
    composed = None if not steps else steps[0] if len(steps) == 1 else Compose(steps)
    return NYU_LAYOUTS[layout](root, transform=composed, **options)
