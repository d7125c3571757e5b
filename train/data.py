"""The Lightning data module: training and validation frames of any crfdepth layout.

Datasets come from :func:`crfdepth.data.build_dataset` (one entry point for the trainer,
``crfdepth evaluate`` and the benchmarks), so validation sees exactly the frames and the
preprocessing that ``crfdepth evaluate --layout <layout> --data <root>`` sees: each
dataset's own default transform (the KITTI bottom-centre crop where it has one), nothing
else. Training adds the augmentation after that transform: a random horizontal flip, and
optionally a random crop and LiDAR thinning (``K`` follows the pixels).

Train / validation split, per layout:

- ``synthetic``: two sets of built-in scenes with disjoint seeds (by default training
  scenes ``seed 0 .. count-1`` and validation scenes from seed 1000).
- ``depth_completion``: ``train_options: {split: train}`` and ``val_options: {split: val}``
  (the defaults for this layout), or validate on another layout with ``val_layout`` /
  ``val_root`` (e.g. ``val_selection``).
- ``sequence``: blocks of frames (``train_options: {frames: [0, 46]}``, ``val_options:
  {frames: [52, 77]}``) or, for a folder of several drives or bags, whole drives by name
  (``val_names_contain``, as below).
- ``raw`` / ``object`` (LiDAR held out of each scan as the target): one folder, split by
  frame name: ``val_names_contain`` (a substring or a list; e.g. a drive name, so whole
  drives are held out) or ``val_fraction`` (the last fraction of the frames in name order,
  which also keeps drives together as far as possible).

Whatever the split, a frame never appears in both sets: frames whose names are in both
raise an error.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable
from typing import Any

import lightning.pytorch as pl
import torch
from lightning.pytorch.trainer.states import TrainerFn
from torch.utils.data import ConcatDataset, DataLoader, Dataset, Subset

from crfdepth.checks import check_choice
from crfdepth.data import Compose, HorizontalFlip, RandomCrop, RandomThinning, build_dataset, collate_samples
from crfdepth.data.factory import LAYOUTS
from crfdepth.data.sample import Sample
from crfdepth.errors import InputError
from train.sampling import Draw, EpochOrder, ResumableLoader, check_same_run, frames_digest, seeded_draws
from train.sources import check_source, check_weight, option_message, weighted

log = logging.getLogger(__name__)

#: Layouts whose one folder can be split by frame name (``val_names_contain`` / ``val_fraction``).
NAME_SPLIT_LAYOUTS = ("raw", "object", "sequence")

#: Default validation options of the synthetic layout: scenes from seed 1000 on.
SYNTHETIC_VAL_SEED = 1000

#: Largest ``batch_size`` / ``val_batch_size``: more frames than any machine's memory holds at KITTI's size
#: (``crfdepth complete --batch-size`` has the same cap).
MAX_BATCH = 1024
#: Largest ``num_workers``: more loader processes cannot keep up better; a typo (400) is refused, not started.
MAX_WORKERS = 64
#: Largest ``seed``: the training order adds the epoch to it in a 64-bit torch generator seed.
MAX_SEED = 2**62
#: Largest side of ``crop`` (pixels): no camera frame is larger; a typo is refused before any frame is read.
MAX_CROP = 2**16


def _integer(value: Any) -> bool:
    return isinstance(value, int) and not isinstance(value, bool)


def _number(value: Any) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool)


class TransformedDataset(Dataset):
    """``dataset`` with ``transform`` applied to every sample (after the dataset's own).

    An item asked for as a :class:`~train.sampling.Draw` (what the training loader's order yields) is
    read and transformed under torch's CPU generator seeded with the draw's seed, so its random
    draws are a function of the seed, the epoch and the frame (:mod:`train.sampling`); a plain index
    draws from the generator as it stands.

    Args:
        dataset: a map-style dataset of :class:`~crfdepth.data.sample.Sample`.
        transform: callable ``Sample -> Sample`` (e.g. ``HorizontalFlip``), or None for none.
    """

    def __init__(self, dataset: Dataset, transform: Callable[[Sample], Sample] | None = None) -> None:
        self.dataset = dataset
        self.transform = transform

    def __len__(self) -> int:
        return len(self.dataset)

    def __getitem__(self, index: int | Draw) -> Sample:
        if isinstance(index, Draw):
            with seeded_draws(index.seed):
                return self[index.index]
        sample = self.dataset[index]
        return sample if self.transform is None else self.transform(sample)

    @property
    def names(self) -> list[str]:
        return dataset_names(self.dataset)


def dataset_names(dataset: Dataset) -> list[str]:
    """Sample names of a crfdepth dataset (or a ``Subset`` / ``ConcatDataset`` of them), in order."""
    if isinstance(dataset, ConcatDataset):
        return [n for d in dataset.datasets for n in dataset_names(d)]
    if isinstance(dataset, Subset):
        names = dataset_names(dataset.dataset)
        return [names[i] for i in dataset.indices]
    names = getattr(dataset, "names", None)
    if names is None:
        return [dataset[i].name for i in range(len(dataset))]
    return list(names)


class CRFDataModule(pl.LightningDataModule):
    """Training and validation frames for :class:`~train.module.CRFDepthModule`.

    Args:
        layout: dataset layout of :func:`crfdepth.data.build_dataset`: "synthetic",
            "raw", "object", "depth_completion", "val_selection" (or "test_selection",
            which has no target and cannot be trained on).
        root: data folder of ``layout`` (ignored for "synthetic"); relative paths are
            relative to the working directory.
        train_options: keyword options of the training dataset's constructor (e.g.
            ``{count: 16, seed: 0}`` for synthetic, ``{holdout_fraction: 0.2}`` for raw).
            None = the dataset defaults (depth_completion: ``{split: train}``).
        val_options: options of the validation dataset. None = ``train_options`` for the
            same layout and root, except synthetic (``seed: 1000``) and depth_completion
            (``split: val``); the dataset defaults for another ``val_layout`` /
            ``val_root``.
        val_layout: layout of the validation data; None = ``layout``.
        val_root: folder of the validation data; None = ``root``.
        val_names_contain: raw/object/sequence split: validation frames are those whose
            name contains this string (or any string of a list), e.g. ``drive_0001`` or a
            bag's name; the others are the training frames.
        val_fraction: raw/object/sequence split: the last ``val_fraction`` of the frames (in name
            order, at least one) are the validation frames. At most one of
            ``val_names_contain`` and ``val_fraction``.
        flip: probability of the horizontal-flip augmentation of training frames
            (``crfdepth.data.HorizontalFlip``); 0 = none.
        crop: ``[height, width]`` of a random crop of each training frame
            (``crfdepth.data.RandomCrop``, after the flip); None = whole frames. A crop
            keeps the pixel scale and makes a step cheaper in proportion to its area.
        thin: ``[low, high]`` range of the share of LiDAR pixels kept in each training
            frame (``crfdepth.data.RandomThinning``, drawn afresh per frame); None = all.
        batch_size: frames per batch (all frames of a dataset must share one size: the
            KITTI layouts crop to 1216 x 352).
        val_batch_size: frames per validation batch; None = ``batch_size``.
        num_workers: ``DataLoader`` worker processes (0 = load in the main process).
        shuffle: shuffle the training frames each epoch.
        extra_train: more training sources, concatenated to the first: a list of
            ``{layout, root, options, names_contain, weight}`` mappings (all but ``layout`` and
            ``root`` optional; ``names_contain``, a string or list, keeps only the frames whose
            name contains one of them; ``weight`` (default 1) scales the source's frames per
            epoch, :func:`train.sources.weighted`). Frames matching
            ``val_names_contain`` are left out of every source, so a held-out drive stays
            held out. E.g. the same scans with another hold-out (``{layout: raw, root:
            ..., options: {holdout: rings}}``) or another folder (``object``).
        train_weight: the weight of the first source (``layout`` / ``root``), as ``extra_train``'s.
        seed: seed of the training order and of each frame's random draws, which are
            functions of (seed, epoch, frame) (:mod:`train.sampling`); None = the run's seed
            (``--seed_everything``, 0 by default) as torch holds it when the loader is made.

    Raises:
        InputError: unknown layout, a split option that does not apply, a split that
            leaves no training or no validation frame, or frames in both sets. Raised in
            :meth:`setup` (like a dataset that finds no frame under ``root``, whose error
            names the root and the layout).
    """

    def __init__(
        self,
        layout: str = "synthetic",
        root: str | None = None,
        train_options: dict[str, Any] | None = None,
        val_options: dict[str, Any] | None = None,
        val_layout: str | None = None,
        val_root: str | None = None,
        val_names_contain: str | list[str] | None = None,
        val_fraction: float | None = None,
        flip: float = 0.5,
        crop: list[int] | None = None,
        thin: list[float] | None = None,
        batch_size: int = 1,
        val_batch_size: int | None = None,
        num_workers: int = 0,
        shuffle: bool = True,
        extra_train: list[dict[str, Any]] | None = None,
        train_weight: float = 1.0,
        seed: int | None = None,
    ) -> None:
        super().__init__()
        for name, value in (("layout", layout), ("val_layout", val_layout)):
            if value is not None:
                check_choice(name, value, LAYOUTS)
        if val_names_contain is not None and val_fraction is not None:
            raise InputError("val_names_contain, val_fraction: give at most one of the two split options")
        if val_fraction is not None and (not _number(val_fraction) or not 0.0 < float(val_fraction) < 1.0):
            raise InputError(f"val_fraction: expected a value in (0, 1), got {val_fraction!r}")
        if not _number(flip) or not 0.0 <= float(flip) <= 1.0:  # nan fails both comparisons
            raise InputError(f"flip: expected a probability in [0, 1], got {flip!r}")
        if crop is not None and (not isinstance(crop, (list, tuple)) or len(crop) != 2
                                 or not all(_integer(v) and v > 0 for v in crop)):
            raise InputError(f"crop: expected [height, width], two integers > 0, got {crop!r}")
        if crop is not None and max(crop) > MAX_CROP:
            raise InputError(f"crop: expected [height, width] of at most {MAX_CROP} pixels each, got {list(crop)!r}")
        if thin is not None and (not isinstance(thin, (list, tuple)) or len(thin) != 2
                                 or not all(_number(v) for v in thin)
                                 or not 0.0 < float(thin[0]) <= float(thin[1]) <= 1.0):
            raise InputError(f"thin: expected [low, high] with 0 < low <= high <= 1, got {thin!r}")
        for name, value in (("batch_size", batch_size), ("val_batch_size", val_batch_size)):
            if value is not None and (not _integer(value) or not 1 <= value <= MAX_BATCH):
                raise InputError(f"{name}: expected an integer in [1, {MAX_BATCH}], got {value!r}")
        if not _integer(num_workers) or not 0 <= num_workers <= MAX_WORKERS:
            raise InputError(f"num_workers: expected an integer in [0, {MAX_WORKERS}] (DataLoader worker processes; "
                             f"0 = the main process), got {num_workers!r}")
        if seed is not None and (not _integer(seed) or not 0 <= seed <= MAX_SEED):
            raise InputError(f"seed: expected an integer in [0, {MAX_SEED}] or null, got {seed!r}")
        self.extra_train = [check_source(i, source) for i, source in enumerate(extra_train or [])]
        self.train_weight = check_weight("train_weight", train_weight)
        self.save_hyperparameters()
        self.layout = layout
        self.root = root
        self.train_options = dict(train_options or {})
        self.val_options = None if val_options is None else dict(val_options)
        self.val_layout = val_layout or layout
        self.val_root = root if val_root is None else val_root
        if isinstance(val_names_contain, str):
            val_names_contain = [val_names_contain]
        self.val_names_contain = None if val_names_contain is None else list(val_names_contain)
        self.val_fraction = val_fraction
        self.flip = float(flip)
        self.crop = None if crop is None else (int(crop[0]), int(crop[1]))
        self.thin = None if thin is None else (float(thin[0]), float(thin[1]))
        self.batch_size = batch_size
        self.val_batch_size = val_batch_size or batch_size
        self.num_workers = num_workers
        self.shuffle = shuffle
        self.seed = seed
        self.train_set: Dataset | None = None
        self.val_set: Dataset | None = None
        self._frames_sha256: str | None = None
        self._order_seed: int | None = None  # the training order's seed, once the loader is made
        self._restored_seed: int | None = None  # the seed of the run a checkpoint resumes

    # -- datasets -------------------------------------------------------------------------
    def _split_by_name(self) -> bool:
        return self.val_names_contain is not None or self.val_fraction is not None

    def _resolved_val_options(self) -> dict[str, Any]:
        if self.val_options is not None:
            return dict(self.val_options)
        options = dict(self.train_options)
        if self.val_layout != self.layout or self.val_root != self.root:
            return {}
        if self.layout == "synthetic" and not self._split_by_name():
            options["seed"] = SYNTHETIC_VAL_SEED
        elif self.layout == "depth_completion" and not self._split_by_name():
            options["split"] = "val"
        return options

    def _build(self, layout: str, root: str | None, options: dict[str, Any], role: str) -> Dataset:
        try:
            return build_dataset(layout, root, **options)
        except FileNotFoundError as exc:
            raise InputError(f"{role} data (layout {layout!r}, root {root}): {exc}") from exc
        except InputError as exc:
            raise InputError(f"{role} data (layout {layout!r}, root {root}): {exc}") from exc
        except TypeError as exc:  # an option the dataset does not take
            raise InputError(option_message(role, layout, options, exc)) from None

    def build_datasets(self) -> tuple[Dataset, Dataset]:
        """(train, validation) datasets, before the training augmentation."""
        train_options = dict(self.train_options)
        if self.layout == "depth_completion" and "split" not in train_options:
            train_options["split"] = "train"
        train = self._build(self.layout, self.root, train_options, "train")
        val = self._build(self.val_layout, self.val_root, self._resolved_val_options(), "val")
        if self._split_by_name():
            if (self.layout not in NAME_SPLIT_LAYOUTS or self.val_layout != self.layout
                    or self.val_root != self.root):
                raise InputError("val_names_contain / val_fraction: the split by frame name applies to one "
                                 f"raw, object or sequence folder (layout {self.layout!r}, val_layout "
                                 f"{self.val_layout!r})")
            # each side's indices from its own names: a sequence's val_options may pick other frames
            train_names, val_names = dataset_names(train), dataset_names(val)
            if self.val_names_contain is not None:
                def is_val(name: str) -> bool:
                    return any(s in name for s in self.val_names_contain)
                what = f"val_names_contain={self.val_names_contain!r}"
            else:
                ordered = sorted(set(train_names) | set(val_names))
                held = set(ordered[len(ordered) - max(1, math.ceil(float(self.val_fraction) * len(ordered))):])
                def is_val(name: str) -> bool:
                    return name in held
                what = f"val_fraction={self.val_fraction}"
            train_idx = [i for i, n in enumerate(train_names) if not is_val(n)]
            val_idx = [i for i, n in enumerate(val_names) if is_val(n)]
            if not val_idx or not train_idx:
                raise InputError(f"{what}: the split of the {len(train_names)} frames under {self.root} leaves "
                                 f"{len(train_idx)} training and {len(val_idx)} validation frames; both need one")
            train, val = Subset(train, train_idx), Subset(val, val_idx)
        train = weighted(train, self.train_weight)
        if self.extra_train:
            train = ConcatDataset([train, *(self._extra(i, source) for i, source in enumerate(self.extra_train))])
        both = set(dataset_names(train)) & set(dataset_names(val))
        if both:
            shown = ", ".join(sorted(both)[:3])
            raise InputError(f"data: {len(both)} frame(s) are in both the training and the validation set "
                             f"(e.g. {shown}); use val_names_contain / val_fraction (raw, object), disjoint "
                             f"synthetic seeds, or another val_layout / val_root")
        return train, val

    def _extra(self, index: int, source: dict[str, Any]) -> Dataset:
        """Extra training source ``index``: its frames minus the held-out names."""
        dataset = self._build(source["layout"], source.get("root"), dict(source.get("options") or {}),
                              f"extra_train[{index}]")
        keep, drop = source.get("names_contain"), self.val_names_contain or []
        names = dataset_names(dataset)
        idx = [i for i, n in enumerate(names)
               if (keep is None or any(k in n for k in keep)) and not any(d in n for d in drop)]
        if not idx:
            raise InputError(f"extra_train[{index}]: none of the {len(names)} frames of {source.get('root')} "
                             f"is left (names_contain={keep!r}, held out: {drop!r})")
        return weighted(dataset if len(idx) == len(names) else Subset(dataset, idx), source["weight"], seed=index)

    def setup(self, stage: str | None = None) -> None:
        if self.train_set is not None:
            return
        train, val = self.build_datasets()
        if self.crop is not None and len(train) > 0:  # checked now, not as a traceback of the first batch
            first = train[0]
            h, w = first.size
            if h < self.crop[0] or w < self.crop[1]:
                raise InputError(f"crop: expected [height, width] within the training frames, got "
                                 f"{list(self.crop)!r} for frame {first.name!r} of {h}x{w} (HxW)")
        augment: list[Callable[[Sample], Sample]] = []
        if self.flip > 0:
            augment.append(HorizontalFlip(p=self.flip))
        if self.crop is not None:
            augment.append(RandomCrop(*self.crop))
        if self.thin is not None:
            augment.append(RandomThinning(*self.thin))
        transform = (augment[0] if len(augment) == 1 else Compose(augment)) if augment else None
        self.train_set, self.val_set = TransformedDataset(train, transform), val
        self._frames_sha256 = frames_digest(dataset_names(train))
        log.info("data: %d training frames (%s), %d validation frames (%s)",
                 len(train), self.layout, len(val), self.val_layout)

    # -- loaders --------------------------------------------------------------------------
    def _loader_options(self, batch_size: int) -> dict[str, Any]:
        return dict(batch_size=batch_size, num_workers=self.num_workers, collate_fn=collate_samples,
                    persistent_workers=self.num_workers > 0)

    def train_dataloader(self) -> DataLoader:
        """The training frames in :class:`~train.sampling.EpochOrder` (this process's share under DDP), in
        a loader whose position Lightning checkpoints, so that a run resumed mid-epoch goes on where it
        stopped (:mod:`train.sampling`)."""
        trainer = self.trainer
        if self._restored_seed is not None:
            self._order_seed = self._restored_seed
        else:
            self._order_seed = torch.initial_seed() % 2**63 if self.seed is None else self.seed
        order = EpochOrder(self.train_set, num_replicas=trainer.world_size if trainer else 1,
                           rank=trainer.global_rank if trainer else 0, shuffle=self.shuffle, seed=self._order_seed)
        return ResumableLoader(self.train_set, order=order, trained=self._trained_batches,
                               **self._loader_options(self.batch_size))

    def _trained_batches(self) -> int:
        """The batches the trainer has trained in the current epoch (0 outside a fit)."""
        trainer = self.trainer
        return 0 if trainer is None else trainer.fit_loop.epoch_loop.batch_progress.current.processed

    def val_dataloader(self) -> DataLoader:
        return DataLoader(self.val_set, shuffle=False, **self._loader_options(self.val_batch_size))

    # -- the run a checkpoint belongs to ---------------------------------------------------
    def training_run(self, processes: int | None = None) -> dict[str, Any]:
        """What makes a training run this one (after :meth:`setup`): the number of training frames, the
        SHA-256 of their names in order, the batch size and the number of processes (``processes``, or
        the attached trainer's ``world_size``; left out when neither is known)."""
        if self.train_set is None:
            raise RuntimeError("CRFDataModule.training_run: call setup() first")
        if processes is None and self.trainer is not None:
            processes = self.trainer.world_size
        run = {"frames": len(self.train_set), "frames_sha256": self._frames_sha256, "batch_size": self.batch_size}
        return run if processes is None else {**run, "processes": int(processes)}

    def check_resumable(self, saved: dict[str, Any], processes: int | None = None) -> None:
        """Refuse a checkpoint of another training run (:func:`train.sampling.check_same_run`): ``saved`` is
        the ``training_run`` this module stored in it, or the training loader's state of an older one;
        ``processes`` as :meth:`training_run` takes it (not compared when unknown)."""
        check_same_run(saved, self.training_run(processes))

    def state_dict(self) -> dict[str, Any]:
        """Stored in every checkpoint (Lightning saves it under ``"CRFDataModule"``): the training run
        (:meth:`training_run`), where it stood (epoch, batches trained in it) and the order's seed."""
        if self.train_set is None or self.trainer is None:
            return {}
        return {"training_run": {**self.training_run(), "epoch": self.trainer.current_epoch,
                                 "batches": self._trained_batches(), "seed": self._order_seed}}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        """Lightning gives the stored state back on ``--ckpt_path``: when fitting, a checkpoint of another
        training run is refused, whichever point it was saved at (the loader refuses it too, but Lightning
        gives the loader its state only in the middle of an epoch); the training order keeps the run's seed.
        Validating or testing a checkpoint on other data is allowed."""
        run = state.get("training_run") if isinstance(state, dict) else None
        fitting = self.trainer is not None and self.trainer.state.fn == TrainerFn.FITTING
        if not isinstance(run, dict) or not fitting:
            return
        self.check_resumable(run)
        if isinstance(run.get("seed"), int):
            self._restored_seed = run["seed"]


__all__ = ["CRFDataModule", "TransformedDataset", "dataset_names"]
