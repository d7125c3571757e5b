"""One frame of depth-completion data, and a batch of them (docs/design.md section 1).

Every dataset in :mod:`crfdepth.data.kitti` returns a :class:`Sample`; every transform in
:mod:`crfdepth.data.transforms` maps a :class:`Sample` to a new one; :func:`collate_samples`
stacks them into a :class:`Batch` for a ``torch.utils.data.DataLoader``.

Frames without ground truth (the KITTI test split) carry an all-zero ``target`` and
``has_target=False``, so that every sample has the same fields and a batch can always be
stacked; 0 already means "no ground truth at this pixel", so metrics computed over
``target > 0`` simply see no pixels.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import torch

from crfdepth.checks import describe
from crfdepth.errors import InputError


@dataclass(frozen=True)
class Sample:
    """One camera frame with its sparse LiDAR depth and (optional) ground truth.

    Attributes:
        image: (3, H, W) float32 RGB in [0, 1].
        sparse: (1, H, W) float32 camera z-depth in metres; 0 = no LiDAR return.
        target: (1, H, W) float32 ground-truth z-depth in metres; 0 = no ground truth at
            that pixel. All zeros when the frame has none (``has_target=False``).
        K: (3, 3) float32 pinhole intrinsics of ``image`` as it is now (after any crop or
            flip), pixels: ``[[fx, 0, cx], [0, fy, cy], [0, 0, 1]]`` with pixel ``(u, v)``
            centred at coordinate ``(u, v)``.
        name: file stem used to name outputs for this frame, e.g.
            ``2011_09_26_drive_0001_sync_velodyne_raw_0000000005_image_02`` (the
            ``velodyne_raw`` file name in ``val_selection_cropped``).
        has_target: False when the frame has no ground truth at all (test split).
        neighbours: optional (S, 3, H, W) float32 RGB of S neighbouring frames of the same
            camera (same size and ``K`` as ``image``), for the photometric term
            (:mod:`crfdepth.sequences.photometric`); None (the default) for single frames.
        poses: optional (S, 4, 4) float32 ``T_cam(s)<-cam(t)``: points of this frame's
            camera into neighbour ``s``'s camera, metres; given exactly when
            ``neighbours`` is (:class:`crfdepth.data.sequences.SequenceFrames`).

    A sample is immutable: transforms return a new one (``dataclasses.replace``) and never
    modify the tensors they receive. ``__post_init__`` checks shapes and dtypes and raises
    :class:`~crfdepth.errors.InputError` naming the field.
    """

    image: torch.Tensor
    sparse: torch.Tensor
    target: torch.Tensor
    K: torch.Tensor
    name: str
    has_target: bool = True
    neighbours: torch.Tensor | None = None
    poses: torch.Tensor | None = None

    def __post_init__(self) -> None:
        image = self.image
        if not isinstance(image, torch.Tensor) or image.ndim != 3 or image.shape[0] != 3:
            raise InputError(f"Sample.image: expected a (3, H, W) tensor, got {describe(image)}")
        hw = tuple(image.shape[1:])
        for field_name in ("sparse", "target"):
            value = getattr(self, field_name)
            if not isinstance(value, torch.Tensor) or tuple(value.shape) != (1, *hw):
                raise InputError(
                    f"Sample.{field_name}: expected a (1, {hw[0]}, {hw[1]}) tensor (the size of "
                    f"image), got {describe(value)} for {self.name!r}"
                )
        if not isinstance(self.K, torch.Tensor) or tuple(self.K.shape) != (3, 3):
            raise InputError(f"Sample.K: expected a (3, 3) tensor, got {describe(self.K)}")
        for field_name in ("image", "sparse", "target", "K"):
            value = getattr(self, field_name)
            if not value.is_floating_point():
                raise InputError(f"Sample.{field_name}: expected a floating-point tensor, got {value.dtype}")
        if (self.neighbours is None) != (self.poses is None):
            raise InputError(f"Sample.poses: expected poses exactly when neighbours are given, got neighbours "
                             f"{describe(self.neighbours)} and poses {describe(self.poses)} for {self.name!r}")
        if self.neighbours is not None:
            n = self.neighbours
            if (not isinstance(n, torch.Tensor) or n.ndim != 4 or tuple(n.shape[1:]) != (3, *hw)
                    or not n.is_floating_point()):
                raise InputError(f"Sample.neighbours: expected a floating-point (S, 3, {hw[0]}, {hw[1]}) tensor "
                                 f"(the size of image), got {describe(n)} for {self.name!r}")
            p = self.poses
            if not isinstance(p, torch.Tensor) or tuple(p.shape) != (n.shape[0], 4, 4) or not p.is_floating_point():
                raise InputError(f"Sample.poses: expected a floating-point ({n.shape[0]}, 4, 4) tensor (one "
                                 f"T_cam(s)<-cam(t) per neighbour), got {describe(p)} for {self.name!r}")

    @property
    def size(self) -> tuple[int, int]:
        """(height, width) of the frame in pixels."""
        return int(self.image.shape[1]), int(self.image.shape[2])


@dataclass
class Batch:
    """A stack of :class:`Sample` (all the same size), as returned by :func:`collate_samples`.

    Attributes:
        image: (B, 3, H, W) float32 RGB in [0, 1].
        sparse: (B, 1, H, W) float32 z-depth in metres; 0 = no LiDAR return.
        target: (B, 1, H, W) float32 ground-truth z-depth in metres; 0 = none.
        K: (B, 3, 3) float32 intrinsics of each image, pixels.
        has_target: (B,) bool, False for frames without any ground truth.
        names: the B sample names, in batch order.
        neighbours: (B, S, 3, H, W) float32 neighbouring frames, or None (samples without).
        poses: (B, S, 4, 4) float32 ``T_cam(s)<-cam(t)``, or None (with ``neighbours``).
    """

    image: torch.Tensor
    sparse: torch.Tensor
    target: torch.Tensor
    K: torch.Tensor
    has_target: torch.Tensor
    names: list[str] = field(default_factory=list)
    neighbours: torch.Tensor | None = None
    poses: torch.Tensor | None = None

    def __len__(self) -> int:
        return len(self.names)

    def to(self, *args, **kwargs) -> "Batch":
        """A copy with every tensor moved/cast by ``Tensor.to(*args, **kwargs)``.

        Only floating-point tensors are cast when a dtype is given; ``has_target`` stays
        bool.
        """
        def move(t: torch.Tensor) -> torch.Tensor:
            if t.is_floating_point():
                return t.to(*args, **kwargs)
            device_args = [a for a in args if not isinstance(a, torch.dtype)]
            device_kwargs = {k: v for k, v in kwargs.items() if k != "dtype"}
            return t.to(*device_args, **device_kwargs)

        return Batch(
            image=move(self.image), sparse=move(self.sparse), target=move(self.target),
            K=move(self.K), has_target=move(self.has_target), names=list(self.names),
            neighbours=None if self.neighbours is None else move(self.neighbours),
            poses=None if self.poses is None else move(self.poses),
        )

    def pin_memory(self) -> "Batch":
        """Page-locked copy, used by ``DataLoader(pin_memory=True)``."""
        return Batch(
            image=self.image.pin_memory(), sparse=self.sparse.pin_memory(),
            target=self.target.pin_memory(), K=self.K.pin_memory(),
            has_target=self.has_target.pin_memory(), names=list(self.names),
            neighbours=None if self.neighbours is None else self.neighbours.pin_memory(),
            poses=None if self.poses is None else self.poses.pin_memory(),
        )


def collate_samples(samples: list[Sample]) -> Batch:
    """Stack samples into a :class:`Batch`; use as ``DataLoader(collate_fn=collate_samples)``.

    Args:
        samples: non-empty list of :class:`Sample`, all of the same (H, W) (crop them to a
            common size first, e.g. with ``BottomCenterCrop``).

    Returns:
        A :class:`Batch` with tensors of leading size ``len(samples)``; ``K`` is float32.

    ``neighbours`` and ``poses`` are stacked when every sample has them (all with the same
    count S), and None when none has.

    Raises:
        InputError: empty list, samples of different sizes (names and sizes given), or
            samples with and without neighbours, or with different counts of them.
    """
    if len(samples) == 0:
        raise InputError("collate_samples: expected at least one Sample, got an empty list")
    first = samples[0]
    for s in samples[1:]:
        if s.size != first.size:
            raise InputError(
                f"collate_samples: all samples must have the same (H, W); {first.name!r} is "
                f"{first.size} but {s.name!r} is {s.size} (crop them first, e.g. BottomCenterCrop)"
            )
    with_neighbours = [s.neighbours is not None for s in samples]
    neighbours = poses = None
    if any(with_neighbours):
        counts = [(s.name, 0 if s.neighbours is None else int(s.neighbours.shape[0])) for s in samples]
        if len({c for _, c in counts}) > 1:
            shown = ", ".join(f"{n!r}: {c}" for n, c in counts[:4])
            raise InputError(f"collate_samples: expected the same number of neighbours in every sample, got {shown}")
        neighbours = torch.stack([s.neighbours for s in samples])
        poses = torch.stack([s.poses.to(torch.float32) for s in samples])
    return Batch(
        image=torch.stack([s.image for s in samples]),
        sparse=torch.stack([s.sparse for s in samples]),
        target=torch.stack([s.target for s in samples]),
        K=torch.stack([s.K.to(torch.float32) for s in samples]),
        has_target=torch.tensor([bool(s.has_target) for s in samples], dtype=torch.bool),
        names=[s.name for s in samples],
        neighbours=neighbours,
        poses=poses,
    )

