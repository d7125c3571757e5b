"""Transforms on a :class:`~crfdepth.data.sample.Sample`, shared by every split and layout.

Each transform is a small callable ``Sample -> Sample`` that returns a new sample and never
modifies the one it receives; the intrinsics ``K`` always follow the pixels (a crop moves
the principal point, a flip mirrors it), so no dataset patches ``K`` by hand.
Compose them with :class:`Compose`.

Pixel convention: pixel ``(u, v)`` (column, row) is centred at image coordinate ``(u, v)``,
so ``K`` maps a camera point to ``u = fx x / z + cx``, ``v = fy y / z + cy``.
"""

from __future__ import annotations

import dataclasses
import zlib
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np
import torch

from crfdepth.data.sample import Sample
from crfdepth.errors import InputError

Transform = Callable[[Sample], Sample]

KITTI_CROP_HEIGHT = 352
KITTI_CROP_WIDTH = 1216


class Compose:
    """Apply transforms in order: ``Compose([a, b])(s) == b(a(s))``.

    Args:
        transforms: callables ``Sample -> Sample``.
    """

    def __init__(self, transforms: Sequence[Transform]) -> None:
        self.transforms = tuple(transforms)

    def __call__(self, sample: Sample) -> Sample:
        for t in self.transforms:
            sample = t(sample)
        return sample

    def __repr__(self) -> str:
        return f"Compose({list(self.transforms)!r})"


def crop_sample(sample: Sample, top: int, left: int, height: int, width: int) -> Sample:
    """The ``height x width`` window of ``sample`` from row ``top``, column ``left``; ``K``
    follows (``cx -= left``, ``cy -= top``). The window must lie inside the frame."""
    rows, cols = slice(top, top + height), slice(left, left + width)
    K = sample.K.clone()
    K[0, 2] -= left
    K[1, 2] -= top
    return dataclasses.replace(
        sample,
        image=sample.image[:, rows, cols].contiguous(),
        sparse=sample.sparse[:, rows, cols].contiguous(),
        target=sample.target[:, rows, cols].contiguous(),
        K=K,
        neighbours=None if sample.neighbours is None else sample.neighbours[:, :, rows, cols].contiguous(),
    )


def _size_fitting(sample: Sample, height: int, width: int, crop: str) -> tuple[int, int]:
    """``(H, W)`` of ``sample``; an InputError naming ``crop`` when a ``height x width`` window does not fit."""
    h, w = sample.size
    if h < height or w < width:
        raise InputError(f"{crop}: sample {sample.name!r} is {h}x{w} (HxW), smaller than the crop {height}x{width}")
    return h, w


@dataclass(frozen=True)
class BottomCenterCrop:
    """Crop the bottom-centre ``height x width`` window (KITTI's benchmark crop).

    The window starts at row ``top = H - height`` and column ``left = (W - width) // 2``;
    the KITTI default 352 x 1216 keeps the rows the LiDAR covers. ``K`` follows:
    ``cx -= left``, ``cy -= top``. On a 1242 x 375 raw KITTI frame this gives
    ``left = 13, top = 23``, exactly the intrinsics shipped with ``val_selection_cropped``.

    Args:
        height: crop height in pixels (> 0).
        width: crop width in pixels (> 0).

    Raises (on call):
        InputError: the sample is smaller than the crop (sizes and name given).
    """

    height: int = KITTI_CROP_HEIGHT
    width: int = KITTI_CROP_WIDTH

    def __post_init__(self) -> None:
        if int(self.height) <= 0 or int(self.width) <= 0:
            raise InputError(
                f"BottomCenterCrop: expected height and width > 0, got ({self.height}, {self.width})"
            )

    def offsets(self, size: tuple[int, int]) -> tuple[int, int]:
        """(top, left) of the crop window in a frame of ``size = (H, W)`` pixels."""
        h, w = size
        return h - self.height, (w - self.width) // 2

    def __call__(self, sample: Sample) -> Sample:
        top, left = self.offsets(_size_fitting(sample, self.height, self.width, "BottomCenterCrop"))
        return crop_sample(sample, top, left, self.height, self.width)


class HorizontalFlip:
    """Mirror the frame left-right with probability ``p``; ``K`` follows.

    Flips ``image``, ``sparse``, ``target`` (and ``neighbours``, whose ``poses`` become
    those of the mirrored cameras, ``M T M`` with ``M = diag(-1, 1, 1, 1)``) along the width and sets
    ``cx' = W - 1 - cx`` (pixel ``u`` goes to ``W - 1 - u``); ``fx``, ``fy``, ``cy`` are
    unchanged, so the flipped frame is what a mirrored pinhole camera would see. Flipping
    twice returns the original sample exactly.

    Args:
        p: probability of flipping, in [0, 1]. ``p=1`` always flips, ``p=0`` never.
        generator: source of the coin flips. None uses torch's global RNG, which a
            ``DataLoader`` reseeds per worker and epoch (so workers do not repeat each
            other); a fixed ``torch.Generator`` gives a reproducible sequence in a
            single process (each ``DataLoader`` worker gets a copy of its state).
    """

    def __init__(self, p: float = 0.5, generator: torch.Generator | None = None) -> None:
        if not 0.0 <= float(p) <= 1.0:
            raise InputError(f"HorizontalFlip: p must be in [0, 1], got {p}")
        self.p = float(p)
        self.generator = generator

    def __call__(self, sample: Sample) -> Sample:
        if self.p <= 0.0:
            return sample
        if self.p < 1.0 and torch.rand((), generator=self.generator).item() >= self.p:
            return sample
        _, w = sample.size
        K = sample.K.clone()
        K[0, 2] = (w - 1) - K[0, 2]
        neighbours, poses = sample.neighbours, sample.poses
        if neighbours is not None:
            # the mirrored cameras: x -> -x in every camera frame, T' = M T M with M = diag(-1, 1, 1, 1)
            mirror = torch.diag(torch.tensor([-1.0, 1.0, 1.0, 1.0], dtype=poses.dtype))
            neighbours, poses = neighbours.flip(-1), mirror @ poses @ mirror
        return dataclasses.replace(
            sample,
            image=sample.image.flip(-1),
            sparse=sample.sparse.flip(-1),
            target=sample.target.flip(-1),
            K=K,
            neighbours=neighbours,
            poses=poses,
        )

    def __repr__(self) -> str:
        return f"HorizontalFlip(p={self.p})"


class RandomCrop:
    """Cut a random ``height x width`` window out of the frame; ``K`` follows.

    Training augmentation: a crop keeps the pixel scale (unlike a resize, so the CRF's
    pixel-graph weights mean the same) and costs proportionally less to solve. The window's
    top-left corner is uniform over the positions where it fits; ``cx -= left``,
    ``cy -= top``.

    Args:
        height: crop height in pixels (> 0).
        width: crop width in pixels (> 0).
        generator: source of the window positions; None = torch's global RNG (reseeded per
            ``DataLoader`` worker and epoch).

    Raises (on call):
        InputError: the sample is smaller than the crop (sizes and name given).
    """

    def __init__(self, height: int, width: int, generator: torch.Generator | None = None) -> None:
        if not _is_positive_int(height) or not _is_positive_int(width):
            raise InputError(f"RandomCrop: expected height and width integers > 0, got ({height!r}, {width!r})")
        self.height, self.width = int(height), int(width)
        self.generator = generator

    def __call__(self, sample: Sample) -> Sample:
        h, w = _size_fitting(sample, self.height, self.width, "RandomCrop")
        top = int(torch.randint(h - self.height + 1, (), generator=self.generator))
        left = int(torch.randint(w - self.width + 1, (), generator=self.generator))
        return crop_sample(sample, top, left, self.height, self.width)

    def __repr__(self) -> str:
        return f"RandomCrop(height={self.height}, width={self.width})"


class RandomThinning:
    """Drop a random share of the LiDAR pixels: a fresh keep fraction every call.

    Training augmentation for sparser sensors: the keep fraction is drawn uniformly from
    ``[low, high]`` each call, then each valid ``sparse`` pixel is kept with that
    probability. ``image``, ``target`` and ``K`` are unchanged (the dropped points are not
    added to the target: the target stays the held-out set). For a fixed, reproducible
    sub-sample use :class:`SubsampleSparse`.

    Args:
        low, high: range of the keep fraction, ``0 < low <= high <= 1``.
        generator: random source; None = torch's global RNG.
    """

    def __init__(self, low: float, high: float = 1.0, generator: torch.Generator | None = None) -> None:
        if not 0.0 < float(low) <= float(high) <= 1.0:
            raise InputError(f"RandomThinning: expected 0 < low <= high <= 1, got low={low!r}, high={high!r}")
        self.low, self.high = float(low), float(high)
        self.generator = generator

    def __call__(self, sample: Sample) -> Sample:
        keep = self.low + (self.high - self.low) * float(torch.rand((), generator=self.generator))
        if keep >= 1.0:
            return sample
        drawn = torch.rand(sample.sparse.shape, generator=self.generator)
        sparse = torch.where(drawn < keep, sample.sparse, torch.zeros((), dtype=sample.sparse.dtype))
        return dataclasses.replace(sample, sparse=sparse)

    def __repr__(self) -> str:
        return f"RandomThinning(low={self.low}, high={self.high})"


def _is_positive_int(value: object) -> bool:
    return isinstance(value, (int, np.integer)) and not isinstance(value, bool) and int(value) > 0


@dataclass(frozen=True)
class SubsampleSparse:
    """Keep a fraction of the valid (> 0) pixels of ``sparse``; the rest become 0.

    For the paper's 40..100% LiDAR-density study when only a projected depth map is
    available (with a point cloud, sub-sample points instead: ``KittiRawScans``'s
    ``keep_fraction``). Exactly ``round(fraction * n_valid)`` pixels are kept, chosen
    uniformly at random. The choice is deterministic per frame: the random stream is
    seeded from ``seed`` and the sample's ``name``, so it does not depend on the order in
    which frames are loaded or on the ``DataLoader`` worker. ``image``, ``target`` and
    ``K`` are unchanged.

    Args:
        fraction: share of valid pixels to keep, in [0, 1].
        seed: non-negative integer.
    """

    fraction: float
    seed: int = 0

    def __post_init__(self) -> None:
        if not 0.0 <= float(self.fraction) <= 1.0:
            raise InputError(f"SubsampleSparse: fraction must be in [0, 1], got {self.fraction}")
        if int(self.seed) < 0:
            raise InputError(f"SubsampleSparse: seed must be >= 0, got {self.seed}")

    def __call__(self, sample: Sample) -> Sample:
        flat = sample.sparse.reshape(-1)
        valid = torch.nonzero(flat > 0).reshape(-1)
        n_keep = int(round(float(self.fraction) * valid.numel()))
        if n_keep == valid.numel():
            return sample
        rng = np.random.default_rng(frame_seed(self.seed, sample.name))
        chosen = rng.choice(valid.numel(), size=n_keep, replace=False)
        keep = torch.zeros_like(flat, dtype=torch.bool)
        keep[valid[torch.from_numpy(chosen)]] = True
        sparse = torch.where(keep, flat, torch.zeros((), dtype=flat.dtype)).reshape(sample.sparse.shape)
        return dataclasses.replace(sample, sparse=sparse)


def frame_seed(seed: int, name: str) -> int:
    """A 64-bit seed for one frame, derived from a global ``seed`` and the frame ``name``.

    Stable across runs, platforms and processes (CRC32 of the name, mixed with
    ``numpy.random.SeedSequence``), so per-frame randomness does not depend on load order.
    """
    state = np.random.SeedSequence([int(seed), zlib.crc32(name.encode("utf-8"))]).generate_state(2)
    return int(state[0]) << 32 | int(state[1])
