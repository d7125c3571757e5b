"""Where the ``learned`` weights of each protocol come from: the shipped file, or a fit by
the shipped recipe on frames outside the evaluated set (:mod:`.methods`, ``learned``)."""

from __future__ import annotations

import logging
import time
import warnings
from collections.abc import Sequence

from crfdepth.model import CRFDepth

from .methods import LEARNED_ABLATIONS, recipe
from .protocols import load_group

# (protocol, evaluated group) -> training group of its learned weights ("shipped": the package's file)
FIT_SOURCE = {("a", "val"): "shipped", ("b", "raw"): "object", ("b", "object"): "raw",
              ("bu", "raw"): "object", ("bu", "object"): "raw",
              ("c", "raw"): "object", ("c", "object"): "raw", ("s", "synthetic"): "shipped",
              ("q", "drive"): "shipped", ("a22", "val"): "shipped", ("q22", "drive"): "shipped",
              **{(f"t{n}", g): "shipped" for n in (500, 200) for g in ("raw", "object")},
              **{(f"n{n}", g): "shipped" for n in (500, 200) for g in ("basement", "dining")}}
GROUP_FOLDERS = {"raw": "raw", "object": "object/training"}


def fit_recipe(frames: Sequence, epochs: int, device: str, crf: dict | None = None) -> tuple[CRFDepth, float]:
    """``CRFDepth`` weights learned on ``frames`` by the shipped recipe (:data:`.methods.RECIPE`).

    The Lightning trainer's module and optimiser with the recipe's ``model`` settings
    (the NLL term off), its augmentation (flip, crop, LiDAR thinning), batch size and seed,
    for ``epochs`` epochs;
    no validation, logging or checkpoints. ``crf`` overrides the recipe's model structure
    (e.g. ``{"potentials": ["colour"]}``). Returns the model (eval mode) and the last
    epoch's mean training loss.
    """
    import lightning.pytorch as pl

    from crfdepth.config import CRFConfig
    from crfdepth.data import Compose, HorizontalFlip, RandomCrop, RandomThinning
    from train.data import TransformedDataset
    from train.module import CRFDepthModule

    config = recipe()
    data = config["data"]
    pl.seed_everything(config.get("seed_everything", 0), verbose=False)
    model = config["model"]
    module = CRFDepthModule(**{**model, "crf": CRFConfig.build(model.get("crf"), **(crf or {})).groups(),
                                "nll_weight": 0.0})
    augment = ([HorizontalFlip(p=data["flip"])] if data.get("flip") else []) + \
        ([RandomCrop(*data["crop"])] if data.get("crop") else []) + \
        ([RandomThinning(*data["thin"])] if data.get("thin") else [])
    dataset = TransformedDataset(list(frames), Compose(augment)) if augment else list(frames)
    trainer = train_module(module, dataset, epochs, device, batch_size=data.get("batch_size", 1))
    loss = float(trainer.callback_metrics.get("train/loss_epoch", float("nan")))
    return module.model.to(device).eval(), loss


def train_module(module, dataset, epochs: int, device: str, batch_size: int = 1, workers: int = 0):
    """Fit the trainer's ``module`` on ``dataset`` (shuffled, ``epochs`` epochs) with Lightning: no validation,
    logging or checkpoints. Returns the Trainer (its ``callback_metrics`` hold the last epoch's loss)."""
    import lightning.pytorch as pl
    from torch.utils.data import DataLoader

    from crfdepth.data import collate_samples

    loader = DataLoader(dataset, batch_size=batch_size, shuffle=True, collate_fn=collate_samples,
                        num_workers=workers, persistent_workers=workers > 0)
    lightning_log = logging.getLogger("lightning.pytorch")
    level = lightning_log.level
    lightning_log.setLevel(logging.WARNING)  # no device / summary banners, for this fit only
    try:
        trainer = pl.Trainer(max_epochs=epochs, accelerator="gpu" if device.startswith("cuda") else "cpu", devices=1,
                             logger=False, enable_checkpointing=False, enable_progress_bar=False,
                             enable_model_summary=False, num_sanity_val_steps=0, limit_val_batches=0)
        with warnings.catch_warnings():  # "validation_step but no val_dataloader": intended
            warnings.filterwarnings("ignore", message=".*val_dataloader.*")
            trainer.fit(module, train_dataloaders=loader)
    finally:
        lightning_log.setLevel(level)
    return trainer


def get_fit(source, args, fits: dict, log) -> CRFDepth:
    """The learned model for frames of groups other than ``source`` (cached in ``fits``).

    ``source``: "shipped" (the package's file), a group name (fit on that group's frames),
    or ``("recipe", method)``: the structure of ``method`` fitted on the shipped weights'
    own training frames (all but drive 0001)."""
    if source not in fits:
        t = time.perf_counter()
        if isinstance(source, tuple):
            frames = [s for group in GROUP_FOLDERS for s in recipe_frames(group, args) if "drive_0001" not in s.name]
            model, loss = fit_recipe(frames, args.fit_epochs, args.device, crf=LEARNED_ABLATIONS[source[1]])
            count = len(frames) // 2
            log(f"  fit of {source[1]} ({count} frames x 2 hold-outs): {args.fit_epochs} epochs in "
                f"{time.perf_counter() - t:.0f} s")
        elif source == "shipped":
            model, loss, count = CRFDepth.from_pretrained("kitti", adaptive=False).to(args.device), float("nan"), 0
            frames = None
        else:
            from train.calibrate import fit_predictive_std

            frames = recipe_frames(source, args)
            model, loss = fit_recipe(frames, args.fit_epochs, args.device)
            fit_predictive_std(model, frames)  # the std's weights, on the same frames, whole and unflipped
            count = len(frames) // 2
            log(f"  fit on {source} ({count} frames x 2 hold-outs): {args.fit_epochs} epochs in "
                f"{time.perf_counter() - t:.0f} s, last-epoch loss {loss:.4f}; "
                + ", ".join(f"{k} {v:.3g}" for k, v in model.weights().items())
                + "; std " + ", ".join(f"{k} {v:.3g}" for k, v in model.std_head.terms().items()))
        fits[source] = {"model": model, "weights": model.weights(), "loss": loss, "frames": count,
                        "std_terms": model.std_head.terms(), "train_frames": frames}
    return fits[source]["model"]


def posterior_view(model: CRFDepth, fits: dict, args) -> CRFDepth:
    """``model`` with ``uncertainty="posterior"`` (``--posterior-samples`` samples), its scale
    calibrated in closed form on the frames ``model`` was fitted on (the shipped weights carry
    theirs); cached in ``fits``."""
    from train.calibrate import calibrate_std_scale

    fit = next(f for f in fits.values() if f["model"] is model)
    if "posterior" not in fit:
        view = CRFDepth(model.config, uncertainty="posterior", std_samples=args.posterior_samples)
        view.load_state_dict({k: v for k, v in model.state_dict().items() if not k.startswith("std_head.")})
        view = view.to(args.device).eval()
        if fit["train_frames"] is not None:
            calibrate_std_scale(view, fit["train_frames"])
        fit["posterior"] = view
    return fit["posterior"]


def recipe_frames(group: str, args) -> list:
    """The recipe's training samples of one group's frames ("raw" or "object"): every data
    source of ``configs/kitti_weights.yaml`` with that layout, with its hold-out options."""
    data = recipe()["data"]
    sources = [(data["layout"], data.get("train_options") or {})]
    sources += [(extra["layout"], extra.get("options") or {}) for extra in data.get("extra_train") or []]
    return [s for layout, options in sources if layout == group
            for s in load_group(args.kitti_root, layout, GROUP_FOLDERS[group], options, args.fit_frames)]
