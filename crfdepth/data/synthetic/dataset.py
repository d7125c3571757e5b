"""The synthetic street scenes as a torch Dataset of :class:`~crfdepth.data.sample.Sample`."""

from __future__ import annotations

import torch

from crfdepth.data.synthetic._checks import check_int
from crfdepth.data.synthetic.scene import make_scene

__all__ = ["SyntheticScenes"]


class SyntheticScenes(torch.utils.data.Dataset):
    """``count`` built-in street scenes as :class:`~crfdepth.data.sample.Sample` items.

    Item ``i`` is ``make_scene(seed + i, ...)``; its target is :meth:`SyntheticScene.target`
    (the ground truth KITTI would have). Scenes are generated on access (about 0.25 s at
    1216x352), so DataLoader workers parallelise them; nothing is cached.

    Args:
        count: number of scenes, >= 1.
        seed: seed of the first scene; use disjoint ranges for train and validation.
        height: image rows, as for :func:`make_scene`.
        width: image columns, as for :func:`make_scene`.
        beams: LiDAR beams, as for :func:`make_scene`.
    """

    def __init__(self, count: int = 8, seed: int = 0, height: int = 352, width: int = 1216, beams: int = 64):
        check_int("count", count, 1, None)
        check_int("seed", seed, 0, None)
        self.count, self.seed, self.height, self.width, self.beams = count, seed, height, width, beams

    def __len__(self) -> int:
        return self.count

    def __getitem__(self, index: int):
        from crfdepth.data.sample import Sample

        if not 0 <= index < self.count:
            raise IndexError(f"index {index} out of range for {self.count} scenes")
        scene = make_scene(self.seed + index, self.height, self.width, self.beams)
        t = scene.to_tensors()
        return Sample(image=t["image"], sparse=t["sparse"], target=t["target"], K=t["K"], name=scene.name)

    @property
    def names(self) -> list[str]:
        return [f"synthetic-seed{self.seed + i}" for i in range(self.count)]
