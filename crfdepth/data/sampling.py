"""Resampling and sparse-sample transforms: the NYU v2 and KITTI protocols of Ma & Karaman (docs/design.md section 17).

Like :mod:`crfdepth.data.transforms`, each transform is a callable ``Sample -> Sample`` that returns a
new sample, never modifies the one it receives, and moves ``K`` with the pixels:

- :class:`Resize`: the frame to another size (the image smoothly, depth by nearest neighbour, so that
  no depth is invented between two surfaces);
- :class:`CenterCrop`: the centre window;
- :class:`SparseSamples`: the sparse input replaced by ``count`` pixels drawn at random from the
  ground truth (or from the sparse map);
- :func:`nyu_protocol` and :func:`kitti_table4`: the evaluation protocols of Ma & Karaman,
  "Sparse-to-Dense: Depth Prediction from Sparse Depth Samples and a Single Image" (ICRA 2018), which
  CSPN, NLSPN, CompletionFormer and BP-Net report on: 500 samples from the ground truth of a 304 x 228
  frame (NYU v2) or a 912 x 228 bottom-centre crop (KITTI, their Table 4).

Pixel convention (:mod:`crfdepth.data.transforms`): pixel ``(u, v)`` is centred at ``(u, v)``, so a
resize by ``s`` maps ``u`` to ``(u + 0.5) s - 0.5``.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np
import torch
import torch.nn.functional as F

from crfdepth.data.sample import Sample
from crfdepth.data.transforms import BottomCenterCrop, Compose, _is_positive_int, _size_fitting, crop_sample, frame_seed
from crfdepth.errors import InputError

__all__ = ["KITTI_TABLE4_CROP", "NYU_CROP", "NYU_RESIZE", "SAMPLE_SOURCES", "CenterCrop", "Resize", "SparseSamples", "kitti_table4",
           "nyu_protocol", "resized_intrinsics"]

#: (height, width) of the NYU v2 protocol: 640 x 480 frames resized to 320 x 240, then centre-cropped to 304 x 228.
NYU_RESIZE = (240, 320)
NYU_CROP = (228, 304)
#: (height, width) of the KITTI crop of Ma & Karaman's Table 4 (bottom centre).
KITTI_TABLE4_CROP = (228, 912)
#: Where :class:`SparseSamples` draws from.
SAMPLE_SOURCES = ("target", "sparse")


def _check_size(name: str, height: object, width: object) -> tuple[int, int]:
    if not _is_positive_int(height) or not _is_positive_int(width):
        raise InputError(f"{name}: expected height and width integers > 0, got ({height!r}, {width!r})")
    return int(height), int(width)


def resized_intrinsics(K: torch.Tensor, scale_x: float, scale_y: float) -> torch.Tensor:
    """``K`` of an image resized by ``scale_x`` (new width / old width) and ``scale_y``.

    ``fx * sx``, ``fy * sy`` (and the skew ``* sx``), ``cx' = (cx + 0.5) sx - 0.5``,
    ``cy' = (cy + 0.5) sy - 0.5``: pixel centres map to pixel centres (the convention of
    ``torch.nn.functional.interpolate(align_corners=False)`` and ``cv2.resize``).

    Args:
        K: (3, 3) float intrinsics, pixels.
        scale_x: new width / old width (> 0).
        scale_y: new height / old height (> 0).

    Returns:
        (3, 3) tensor of ``K``'s dtype; ``K`` is not modified.
    """
    S = torch.tensor([[scale_x, 0.0, 0.5 * scale_x - 0.5], [0.0, scale_y, 0.5 * scale_y - 0.5], [0.0, 0.0, 1.0]],
                     dtype=torch.float64)
    return (S @ K.to(torch.float64)).to(K.dtype)


@dataclass(frozen=True)
class Resize:
    """Resize the frame to ``height x width``; ``K`` follows (:func:`resized_intrinsics`).

    The image (and any ``neighbours``) is resampled bilinearly with antialiasing: the triangle filter
    widened by the shrink factor, as PIL's bilinear resize (the one of the Sparse-to-Dense protocol),
    so shrinking averages rather than skips pixels; ``sparse`` and ``target`` by nearest neighbour (``nearest-exact``: the source
    pixel whose centre is nearest), so every depth of the output is a depth of the input and none
    is invented between a near and a far surface. Shrinking a sparse map therefore drops the
    returns that no output pixel picks. ``poses`` are unchanged.

    Args:
        height: the output height in pixels (> 0).
        width: the output width in pixels (> 0).
    """

    height: int
    width: int

    def __post_init__(self) -> None:
        _check_size("Resize", self.height, self.width)

    def __call__(self, sample: Sample) -> Sample:
        h, w = sample.size
        size = (int(self.height), int(self.width))
        if (h, w) == size:
            return sample

        def smooth(x: torch.Tensor) -> torch.Tensor:
            return F.interpolate(x, size=size, mode="bilinear", align_corners=False, antialias=True).clamp_(0.0, 1.0)

        def nearest(x: torch.Tensor) -> torch.Tensor:
            return F.interpolate(x[None], size=size, mode="nearest-exact")[0]

        return dataclasses.replace(
            sample,
            image=smooth(sample.image[None])[0],
            sparse=nearest(sample.sparse),
            target=nearest(sample.target),
            K=resized_intrinsics(sample.K, size[1] / w, size[0] / h),
            neighbours=None if sample.neighbours is None else smooth(sample.neighbours),
        )


@dataclass(frozen=True)
class CenterCrop:
    """Crop the centre ``height x width`` window; ``K`` follows (``cx -= left``, ``cy -= top``).

    The window starts at row ``top = (H - height) // 2`` and column ``left = (W - width) // 2``
    (a 320 x 240 frame cropped to 304 x 228: ``top = 6``, ``left = 8``).

    Args:
        height: the crop's height in pixels (> 0).
        width: the crop's width in pixels (> 0).

    Raises (on call):
        InputError: the sample is smaller than the crop (sizes and name given).
    """

    height: int
    width: int

    def __post_init__(self) -> None:
        _check_size("CenterCrop", self.height, self.width)

    def __call__(self, sample: Sample) -> Sample:
        h, w = _size_fitting(sample, int(self.height), int(self.width), "CenterCrop")
        top, left = (h - int(self.height)) // 2, (w - int(self.width)) // 2
        return crop_sample(sample, top, left, int(self.height), int(self.width))


@dataclass(frozen=True)
class SparseSamples:
    """Replace the sparse input by ``count`` valid pixels drawn uniformly at random, without replacement.

    With ``source="target"`` (the NYU v2 and KITTI protocol of Ma & Karaman) the pixels are drawn
    from the ground truth and the target is kept whole, so the metrics are computed over every
    ground-truth pixel, the 500 given ones included; with ``source="sparse"`` they are drawn from
    the sparse map (a sparser sensor). Each drawn pixel keeps its depth exactly; all others are 0.
    ``image``, ``target`` and ``K`` are unchanged.

    Args:
        count: the number of pixels (> 0); the user's name for it is ``samples``.
        seed: a non-negative integer: the draw is a function of ``seed`` and the frame's ``name``
            (:func:`~crfdepth.data.transforms.frame_seed`), whatever the loading order or worker; None
            draws from torch's global generator, which the trainer seeds per frame and epoch
            (``train/sampling.py``), so training frames get fresh samples each epoch.
        source: ``"target"`` or ``"sparse"``.

    Raises (on call):
        InputError: ``samples``: the source has fewer valid (> 0) pixels than ``count`` (both numbers
            and the frame's name given).
    """

    count: int
    seed: int | None = 0
    source: str = "target"

    def __post_init__(self) -> None:
        if not _is_positive_int(self.count):
            raise InputError(f"samples: expected an integer > 0 (pixels drawn per frame), got {self.count!r}")
        if self.seed is not None and (not isinstance(self.seed, (int, np.integer)) or isinstance(self.seed, bool)
                                      or int(self.seed) < 0):
            raise InputError(f"seed: expected an integer >= 0 or None, got {self.seed!r}")
        if self.source not in SAMPLE_SOURCES:
            raise InputError(f"source: expected one of {', '.join(map(repr, SAMPLE_SOURCES))}, got {self.source!r}")

    def __call__(self, sample: Sample) -> Sample:
        values = getattr(sample, self.source).reshape(-1)
        valid = torch.nonzero(values > 0).reshape(-1)
        count = int(self.count)
        if count > valid.numel():
            raise InputError(f"samples: expected at most the {valid.numel()} valid pixel(s) of the {self.source} of "
                             f"frame {sample.name!r} ({sample.size[0]}x{sample.size[1]}, HxW), got {count}")
        if self.seed is None:
            chosen = torch.randperm(valid.numel())[:count]
        else:
            rng = np.random.default_rng(frame_seed(int(self.seed), sample.name))
            chosen = torch.from_numpy(rng.choice(valid.numel(), size=count, replace=False))
        sparse = torch.zeros_like(values)
        picked = valid[chosen]
        sparse[picked] = values[picked]
        return dataclasses.replace(sample, sparse=sparse.reshape(sample.sparse.shape).to(sample.sparse.dtype))


def nyu_protocol(samples: int | None = 500, seed: int | None = 0) -> Compose:
    """The NYU v2 protocol of Ma & Karaman (2018): resize 640 x 480 to 320 x 240, centre-crop to 304 x 228,
    draw ``samples`` pixels of the ground truth as the sparse input (docs/design.md section 17).

    Args:
        samples: pixels drawn per frame (500 in every paper that reports on it); None keeps the sparse map
            as it is (resize and crop only).
        seed: the draw's seed (:class:`SparseSamples`; None = torch's global generator).

    Returns:
        ``Compose([Resize(240, 320), CenterCrop(228, 304), SparseSamples(samples, seed)])``.
    """
    steps = [Resize(*NYU_RESIZE), CenterCrop(*NYU_CROP)]
    return Compose(steps if samples is None else [*steps, SparseSamples(samples, seed)])


def kitti_table4(samples: int = 500, seed: int | None = 0) -> Compose:
    """The KITTI protocol of Ma & Karaman (2018, Table 4): the bottom-centre 912 x 228 crop of the frame,
    ``samples`` pixels of its ground truth (KITTI's annotation) as the sparse input.

    Returns:
        ``Compose([BottomCenterCrop(228, 912), SparseSamples(samples, seed)])``.
    """
    return Compose([BottomCenterCrop(*KITTI_TABLE4_CROP), SparseSamples(samples, seed)])
