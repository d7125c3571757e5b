"""Accuracy, uncertainty and speed of crfdepth on the real KITTI sample frames (issue 6).

Frames come from ``--kitti-root`` (default ``../shared/data/kitti`` next to this
repository), through :func:`crfdepth.data.factory.build_dataset`, all 1216 x 352:

- protocol **a**: official depth-completion input and semi-dense ground truth
  (``depth_selection/val_selection_cropped``, 2 frames: drive 0001 frame 5, cameras 2/3);
- protocol **b**: raw Velodyne scans (``raw/``: drives 0001 and 0060; ``object/training``)
  with a random 20% of the points held out as the target (``holdout="fraction"``);
- protocol **bu**: protocol b scored against the held-out points as they are
  (``clean_target=False``: see-through points kept);
- protocol **c**: the same scans keeping every 4th laser ring (16 beams) as the input,
  the other rings as the target (``holdout="rings", keep_every_ring=4``);
- protocol **s**: 12 built-in synthetic street scenes (seeds 1000-1011, no data folder),
  KITTI's 64-beam LiDAR mount with its see-through leaks, scored against the camera's
  true depth (``SyntheticScene.target()``): the one protocol besides (a) whose target is
  what the camera sees, and one the structure may be chosen on;
- protocol **q**: the reported block of the raw sequence ``sequences/`` (drive 0060 frames
  52-77; every recipe trains on frames 0-46 at most), the frame's own scan as input,
  scored against the camera-view targets that ``crfdepth targets`` accumulates from the
  scans around it (k = 5, poses from LiDAR odometry; made into ``--targets-root`` when
  missing, about 30 s): what the camera sees, on real frames, without annotation;
- protocols **a22** and **q22**: clean inputs. The frames of a and q with a random 22% of
  their target pixels (KITTI's annotation, the camera-view targets) as the input and the
  other 78% as the target: an input without see-through returns and off the laser rings
  (a LiDAR beside the camera, an input cleaned upstream).

Targets in b and c are raw LiDAR points (sparse, noisy), not KITTI's semi-dense
annotation, cleaned of see-through points against the whole scan
(``KittiRawScans(clean_target=True)``, the default); each frame's input and target pixels
are disjoint.

Methods (every CRF is :class:`crfdepth.model.CRFDepth`, float32, batch size 1):

- ``nn``: nearest-LiDAR fill (:func:`crfdepth.fill.nearest.nearest_fill`);
- ``ipbasic``: IP-Basic (Ku et al. 2018), fast configuration, as written here in torch
  (:func:`crfdepth.fill.ip_basic.ip_basic_fill`); the classical baseline to beat;
- ``inpaint``: OpenCV ``cv2.inpaint`` (Telea, radius 5) of the sparse map as float32
  metres (OpenCV 5 takes 1-channel float32), clipped to the input's depth range (Telea
  overshoots below 0 near the image border otherwise);
- ``paper``: ``CRFDepth()`` (superpixel 5500, all potentials, pixel refinement) with the
  hand-set weights (``CRFDepth.from_pretrained("paper")``);
- ``hand-set``: the structure of the shipped weights (the recipe's ``model.crf``
  section) with the constructor's hand-set weights: what learning is measured against;
- ``learned``: that structure with weights learned by the recipe of the shipped weights
  (``configs/kitti_weights.yaml``: the Lightning trainer, its loss, optimiser,
  augmentation, hold-outs, epochs and seed), always on frames **outside** the
  evaluated set. Protocol a: the shipped weights themselves (``crfdepth/weights/kitti.json``,
  the package default; trained on drive 0060 and the object frames, never on drive 0001).
  Protocol s: the shipped weights (never trained on synthetic scenes).
  Protocols b and c: 2-fold by source, since the shipped weights saw those frames: the
  raw-drive frames get weights fitted on the object frames, the object frames weights
  fitted on the raw drives. The NLL term is off in these fits (it moves only the std
  scale, which changes neither the depth nor the AUSE). Which fit served which frames is
  in the output (``fit``);
- ``pixel``: ``CRFDepth(mode="pixel")``;
- ``sp-c``, ``sp-cn``, ``sp-cnd``: the paper's Table 1 ablation (colour; + normal; +
  3D distance), superpixel 5500, piecewise-constant painting (``refine=False``);
  ``sp-c+r``, ``sp-cn+r``: the same with the pixel refinement (``sp-cnd+r`` is ``paper``);
- ``sp1200``, ``sp2400``: the paper's Table 2 segment counts, all potentials, no
  refinement (5500 is ``sp-cnd``);
- ``inv``, ``inv+gate``, ``pixel+gate``, ``pixel+inv+gate``, ``pixel+inv+gate+ipb``,
  ``pixel+inv+gate+irls``, ``pixel+log+gate``: the extensions of docs/design.md section 3b
  with hand-set weights (``variable="inverse"`` or ``"log"``, ``gate=True``,
  ``mode="pixel"``, ``prior="ip_basic"``, ``irls=1``).

The ablations and segment counts use the hand-set weights, as ``paper`` does. With
``--learn-ablations``, protocol a also gets ``sp-c/learned`` .. ``sp-cn+r/learned``: each
ablation with weights learned for its own configuration by the shipped recipe on the
shipped weights' training frames (drive 0060 and the object frames, never drive 0001), as
the paper trains each row of its Table 1 (5 more fits, about 5 minutes each on 2 cores).

Metrics: :func:`crfdepth.metrics.depth_metrics` per image over target pixels, averaged
over images (RMSE/MAE mm, iRMSE/iMAE 1/km, REL, delta < 1.25), docs/design.md section 7.

Uncertainty (docs/design.md section 5), for ``paper``, ``hand-set`` and ``learned``, of three
maps: ``std``, the model's predictive std (:mod:`crfdepth.uncertainty.predictive`); ``posterior``, the
posterior-only std ``s sqrt(diag(A^-1))`` (``learned`` only: ``uncertainty="posterior"``
with ``--posterior-samples`` samples, its scale ``s`` calibrated in closed form on the fit's
frames); ``count``, the paper's count map (a score, not a std). Per image, then averaged
(:func:`crfdepth.metrics.uncertainty_metrics`): AUSE of RMSE in mm and the random order's
(ties in the count map are removed in random order in expectation), their ratio from the
averaged areas, Spearman(std, |error|), and for the stds the share of errors within 1 and 2
std and the Gaussian NLL. The learned std is fitted like the depth weights, on frames
outside the evaluated set: the shipped weights' std (fitted on their 48 training frames), or
for the 2-fold fits :func:`train.calibrate.fit_predictive_std` on the fit's frames.

Speed: median over frames of the wall clock of one forward (batch 1, ``no_grad``,
``torch.set_num_threads(--threads)``); for ``paper``/``learned`` the ``uncertainty`` stage
is subtracted (their forwards also return the std). On CUDA clocks are read after a
synchronise (untested: this was written on a CPU-only machine).

Sub-sampling study: RMSE of ``paper`` and ``nn`` on protocol b for ``keep_fraction``
in ``--fractions`` (the target is the same pixels for every fraction), table and PNG.

Outputs under ``--out-dir`` (default ``./accuracy_results``): ``results.md`` (the printed
tables and verdicts), ``results.jsonl`` (one JSON line per method and protocol, one per
sub-sampling point), ``subsampling.png``, ``sparsification.png`` (per protocol: the learned
model's std, posterior std and count map against the oracle and a random order),
``reliability.png`` (share within k std against the Gaussian's).

    python benchmarks/accuracy.py [--kitti-root PATH] [--protocols a b c] [--methods ...]
        [--max-frames N] [--fit-epochs E] [--fit-frames N] [--learn-ablations]
        [--fractions 0.2 0.4 0.6 0.8 1.0]
        [--no-subsample] [--device cpu|cuda] [--threads 1] [--quick] [--out-dir DIR]
"""

from __future__ import annotations

import argparse
import json
import logging
import statistics
import time
import warnings
from pathlib import Path
from typing import Callable, Sequence

import numpy as np
import torch

from crfdepth.fill.ip_basic import ip_basic_fill
from crfdepth.data.factory import build_dataset
from crfdepth.fill.nearest import nearest_fill
from crfdepth.metrics import SPARSIFY_STEPS, ause, average_metrics, depth_metrics, reliability, uncertainty_metrics
from crfdepth.model import CRFDepth

DEFAULT_ROOT = Path(__file__).resolve().parent.parent.parent / "shared" / "data" / "kitti"
TARGET_GAIN_C = 0.20  # learned must beat NN on protocol c by >= 20% RMSE

REPORTED_BLOCK = (52, 77)  # protocol q: the frames of drive 0060 that no recipe trains on
TARGETS_DRIVE = "2011_09_26/2011_09_26_drive_0060_sync"  # under <kitti-root>/sequences
CLEAN_SHARE = 0.22  # protocols a22, q22: share of the target pixels given as the (clean) input
SYNTHETIC_SEED = 1000  # protocol s: scenes no recipe trains on (the trainer's synthetic validation seeds)
# protocol -> (title, [(group, layout, sub-folder (None: no data folder), dataset options)])
PROTOCOLS = {
    "a": ("(a) val_selection_cropped: official input, semi-dense ground truth",
          [("val", "val_selection", "depth_selection/val_selection_cropped", {})]),
    "b": ("(b) raw scans, 20% of the LiDAR points held out as target",
          [("raw", "raw", "raw", dict(holdout="fraction", holdout_fraction=0.2)),
           ("object", "object", "object/training", dict(holdout="fraction", holdout_fraction=0.2))]),
    "bu": ("(b) with uncleaned targets: the held-out points as they are, see-through points kept",
           [("raw", "raw", "raw", dict(holdout="fraction", holdout_fraction=0.2, clean_target=False)),
            ("object", "object", "object/training",
             dict(holdout="fraction", holdout_fraction=0.2, clean_target=False))]),
    "c": ("(c) raw scans, every 4th ring kept (16 beams), other rings as target",
          [("raw", "raw", "raw", dict(holdout="rings", keep_every_ring=4)),
           ("object", "object", "object/training", dict(holdout="rings", keep_every_ring=4))]),
    "s": ("(s) built-in synthetic street scenes (seeds 1000-1011): the camera's true depth as target",
          [("synthetic", "synthetic", None, dict(count=12, seed=SYNTHETIC_SEED))]),
    "q": ("(q) drive 0060 frames 52-77: own scan in, its camera-view targets (crfdepth targets, k=5) as target",
          [("drive", "sequence", "sequences", dict(frames=list(REPORTED_BLOCK)))]),
    "a22": ("(a22) the frames of (a), 22% of the ground truth as input, the other 78% as target",
            [("val", "val_selection", "depth_selection/val_selection_cropped", dict(input_share=CLEAN_SHARE))]),
    "q22": ("(q22) the frames of (q), 22% of the camera-view targets as input, the other 78% as target",
            [("drive", "sequence", "sequences", dict(frames=list(REPORTED_BLOCK), input_share=CLEAN_SHARE))]),
}
# (protocol, evaluated group) -> training group of its learned weights ("shipped": the package's file)
FIT_SOURCE = {("a", "val"): "shipped", ("b", "raw"): "object", ("b", "object"): "raw",
              ("bu", "raw"): "object", ("bu", "object"): "raw",
              ("c", "raw"): "object", ("c", "object"): "raw", ("s", "synthetic"): "shipped",
              ("q", "drive"): "shipped", ("a22", "val"): "shipped", ("q22", "drive"): "shipped"}
RECIPE = Path(__file__).resolve().parent.parent / "configs" / "kitti_weights.yaml"
CRF_METHODS = {
    "paper": dict(),
    "learned": dict(),
    "hand-set": dict(),  # the recipe's structure (recipe_crf()), the constructor's weights
    "pixel": dict(mode="pixel"),
    "sp-c": dict(potentials=("colour",), refine=False),
    "sp-cn": dict(potentials=("colour", "normal"), refine=False),
    "sp-cnd": dict(refine=False),
    "sp-c+r": dict(potentials=("colour",)),
    "sp-cn+r": dict(potentials=("colour", "normal")),
    "sp1200": dict(superpixels=1200, refine=False),
    "sp2400": dict(superpixels=2400, refine=False),
    # docs/design.md section 3b, hand-set weights: 1/z unknown, occlusion gate, on both graphs
    "inv": dict(variable="inverse"),
    "inv+gate": dict(variable="inverse", gate=True),
    "pixel+gate": dict(mode="pixel", gate=True),
    "pixel+inv+gate": dict(mode="pixel", variable="inverse", gate=True),
    "pixel+inv+gate+ipb": dict(mode="pixel", variable="inverse", gate=True, prior="ip_basic"),
    "pixel+inv+gate+irls": dict(mode="pixel", variable="inverse", gate=True, irls=1),
    "pixel+log+gate": dict(mode="pixel", variable="log", gate=True),
}
METHODS = ("nn", "ipbasic", "inpaint", *CRF_METHODS)
WITH_STD = ("paper", "hand-set", "learned")
GROUP_FOLDERS = {"raw": "raw", "object": "object/training"}
TARGET_VS_IPBASIC = 0.85  # issue targets: learned RMSE <= 0.85 x IP-Basic's, same run
TARGET_VS_HANDSET = 0.95  # issue 26: learned RMSE <= 0.95 x the same structure with hand-set weights
TARGET_AUSE_RATIO, TARGET_SPEARMAN, TARGET_COVERAGE = 0.7, 0.3, (0.6, 0.8)  # issue 14, the learned std
DEPTH_BINS_M = (0.0, 10.0, 20.0, 40.0, float("inf"))  # target depth bins of the error breakdown


def depth_bin_errors(depth: torch.Tensor, target: torch.Tensor) -> tuple[np.ndarray, np.ndarray]:
    """(sum of squared errors in m^2, target pixels) per :data:`DEPTH_BINS_M` bin of the target depth."""
    mask = target > 0
    t = target[mask].double().cpu()
    se = (depth[mask].double().cpu() - t) ** 2
    b = torch.bucketize(t, torch.tensor(DEPTH_BINS_M[1:-1], dtype=t.dtype), right=True)
    n_bins = len(DEPTH_BINS_M) - 1
    return (torch.zeros(n_bins, dtype=t.dtype).index_add(0, b, se).numpy(),
            torch.bincount(b, minlength=n_bins).numpy())


def recipe() -> dict:
    import yaml

    return yaml.safe_load(RECIPE.read_text())


def recipe_crf() -> dict:
    """The model structure of the shipped recipe (its ``model.crf`` section)."""
    return dict(recipe()["model"].get("crf") or {})


def method_config(method: str) -> dict:
    return recipe_crf() if method == "hand-set" else dict(CRF_METHODS[method])
# The Table 1 ablations with weights learned for each configuration (protocol a only:
# ``--learn-ablations``), as the paper does.
LEARNED_ABLATIONS = {f"{m}/learned": CRF_METHODS[m] for m in ("sp-c", "sp-cn", "sp-cnd", "sp-c+r", "sp-cn+r")}


def load_group(root: Path, layout: str, folder: str, options: dict, max_frames: int | None,
               keep_fraction: float = 1.0, targets_root: Path | None = None) -> list:
    """Samples of one frame group, evenly spaced down to ``max_frames``; ``options["input_share"]``
    turns each into a clean-input sample (:func:`clean_input`)."""
    options = dict(options)
    share = options.pop("input_share", None)
    if layout in ("raw", "object"):
        options["keep_fraction"] = keep_fraction
    if layout == "sequence":
        options.update(targets_root=targets_root, offsets=[-1, 1])
    ds = build_dataset(layout, None if folder is None else root / folder, **options)
    idx = list(range(len(ds)))
    if max_frames is not None and len(idx) > max_frames:
        idx = sorted({round(i * (len(ds) - 1) / max(max_frames - 1, 1)) for i in range(max_frames)})
    return [ds[i] if share is None else clean_input(ds[i], share, seed=i) for i in idx]


def clean_input(sample, share: float, seed: int):
    """``sample`` with a random ``share`` of its target pixels as the input and the rest as the target."""
    import dataclasses

    target = sample.target
    given = (target > 0) & (torch.rand(target.shape, generator=torch.Generator().manual_seed(seed)) < share)
    zero = torch.zeros_like(target)
    return dataclasses.replace(sample, sparse=torch.where(given, target, zero),
                               target=torch.where(given, zero, target), neighbours=None, poses=None)


def ensure_targets(args) -> Path:
    """The camera-view targets of the drive of protocol q under ``--targets-root``, made there by
    ``crfdepth targets`` (k = 5, LiDAR odometry) when missing."""
    drive = args.kitti_root / "sequences" / TARGETS_DRIVE
    if not (args.targets_root / drive.name / "poses.txt").is_file():
        from crfdepth.cli import main as cli

        code = cli(["targets", "--drive", str(drive), "--out-dir", str(args.targets_root), "--poses", "odometry",
                    "-k", "5", "--quiet"])
        if code:
            raise SystemExit(f"--targets-root: `crfdepth targets` failed on {drive} (exit {code})")
    return args.targets_root


def batch(s, device: str):
    return s.image[None].to(device), s.sparse[None].to(device), s.target[None].to(device), s.K.to(device)


# -- methods -----------------------------------------------------------------------------
def inpaint(sparse: torch.Tensor) -> torch.Tensor:
    """cv2.inpaint (Telea, radius 5) of a (1, 1, H, W) sparse map in metres, float32."""
    import cv2

    d = sparse[0, 0].detach().cpu().numpy().astype(np.float32)
    valid = d > 0
    out = cv2.inpaint(d, (~valid).astype(np.uint8), 5, cv2.INPAINT_TELEA)
    out = np.clip(out, d[valid].min(), d[valid].max())
    return torch.from_numpy(out)[None, None].to(sparse)


def fit_recipe(frames: Sequence, epochs: int, device: str, crf: dict | None = None) -> tuple[CRFDepth, float]:
    """``CRFDepth`` weights learned on ``frames`` by the shipped recipe (:data:`RECIPE`).

    The Lightning trainer's module and optimiser with the recipe's ``model`` settings
    (the NLL term off), its augmentation (flip, crop, LiDAR thinning), batch size and seed,
    for ``epochs`` epochs;
    no validation, logging or checkpoints. ``crf`` overrides the recipe's model structure
    (e.g. ``{"potentials": ["colour"]}``). Returns the model (eval mode) and the last
    epoch's mean training loss.
    """
    import lightning.pytorch as pl
    import yaml
    from torch.utils.data import DataLoader

    from crfdepth.data import Compose, HorizontalFlip, RandomCrop, RandomThinning, collate_samples
    from train.data import TransformedDataset
    from train.module import CRFDepthModule

    logging.getLogger("lightning.pytorch").setLevel(logging.WARNING)  # no device / summary banners
    recipe = yaml.safe_load(RECIPE.read_text())
    data = recipe["data"]
    pl.seed_everything(recipe.get("seed_everything", 0), verbose=False)
    model = recipe["model"]
    module = CRFDepthModule(**{**model, "crf": {**(model.get("crf") or {}), **(crf or {})}, "nll_weight": 0.0})
    augment = ([HorizontalFlip(p=data["flip"])] if data.get("flip") else []) + \
        ([RandomCrop(*data["crop"])] if data.get("crop") else []) + \
        ([RandomThinning(*data["thin"])] if data.get("thin") else [])
    dataset = TransformedDataset(list(frames), Compose(augment)) if augment else list(frames)
    loader = DataLoader(dataset, batch_size=data.get("batch_size", 1), shuffle=True, collate_fn=collate_samples)
    trainer = pl.Trainer(max_epochs=epochs, accelerator="gpu" if device.startswith("cuda") else "cpu", devices=1,
                         logger=False, enable_checkpointing=False, enable_progress_bar=False,
                         enable_model_summary=False, num_sanity_val_steps=0, limit_val_batches=0)
    with warnings.catch_warnings():  # "validation_step but no val_dataloader": intended
        warnings.filterwarnings("ignore", message=".*val_dataloader.*")
        trainer.fit(module, train_dataloaders=loader)
    loss = float(trainer.callback_metrics.get("train/loss_epoch", float("nan")))
    return module.model.to(device).eval(), loss


def sync(device: str) -> None:
    if device.startswith("cuda"):
        torch.cuda.synchronize()


def predict(method: str, model: CRFDepth | None, image, sparse, K, device: str):
    """(depth (1, 1, H, W), std or None, count map or None, seconds); ``std`` is the model's own
    (the predictive std unless it was built with ``uncertainty="posterior"``)."""
    sync(device)
    t = time.perf_counter()
    std = count = None
    with torch.no_grad():
        if method == "nn":
            depth = nearest_fill(sparse)
        elif method == "ipbasic":
            depth = ip_basic_fill(sparse)
        elif method == "inpaint":
            depth = inpaint(sparse)
        else:
            out = model(image, sparse, K, return_std=method in WITH_STD)
            depth, std, count = out.depth, out.std, out.count_uncertainty
    sync(device)
    seconds = time.perf_counter() - t
    if model is not None and method in WITH_STD:
        seconds -= out.timings.get("uncertainty", 0.0)
    return depth.clamp_min(1e-3), std, count, seconds


# -- evaluation --------------------------------------------------------------------------
def evaluate_protocol(key: str, args, fits: dict, log: Callable[[str], None]) -> tuple[list[dict], dict]:
    """Rows (one per method) of protocol ``key`` and its mean sparsification curves."""
    title, groups = PROTOCOLS[key]
    methods = list(args.methods) + (list(LEARNED_ABLATIONS) if args.learn_ablations and key == "a" else [])
    per = {m: dict(metrics=[], seconds=[], unc={}, bins=[]) for m in methods}
    curves: dict = {}
    fit_note = {}
    for group, layout, folder, options in groups:
        frames = load_group(args.kitti_root, layout, folder, options, args.max_frames,
                            targets_root=ensure_targets(args) if layout == "sequence" else None)
        models = {m: CRFDepth(**method_config(m)).to(args.device) for m in args.methods
                  if m in CRF_METHODS and m != "learned"}
        for m in methods:
            if m in LEARNED_ABLATIONS:
                models[m] = get_fit(("recipe", m), args, fits, log)
        if "learned" in args.methods:
            source = FIT_SOURCE[(key, group)]
            models["learned"] = get_fit(source, args, fits, log)
            fit_note[group] = (f"{group} frames: the shipped weights (crfdepth/weights/kitti.json)" if source == "shipped"
                               else f"{group} frames: fitted on the {fits[source]['frames']} {source} frames "
                                    f"(the recipe's hold-outs, {args.fit_epochs} epochs)")
        log(f"  protocol {key}, {group}: {len(frames)} frame(s)")
        for s in frames:
            image, sparse, target, K = batch(s, args.device)
            mask = (target > 0)[0, 0]
            for m in methods:
                depth, std, count, seconds = predict(m, models.get(m), image, sparse, K, args.device)
                per[m]["metrics"].append(depth_metrics(depth, target))
                per[m]["seconds"].append(seconds)
                per[m]["bins"].append(depth_bin_errors(depth, target))
                if std is None:
                    continue
                maps = {"std": std, "count": count}
                if m == "learned":
                    maps["posterior"] = predict(m, posterior_view(models[m], fits, args), image, sparse, K,
                                                args.device)[1]
                err = (depth[0, 0][mask] - target[0, 0][mask]).double().cpu().numpy()  # metres
                for name, u in maps.items():
                    u = u[0, 0][mask].double().cpu().numpy()
                    a = ause(err * 1000.0, u)  # curves in mm
                    a.update(uncertainty_metrics(err, u, is_std=name != "count"))
                    if name != "count":
                        a["reliability"] = reliability(err, u)["observed"]
                    per[m]["unc"].setdefault(name, []).append(a)
    rows = []
    h, w = frames[0].size
    for m in methods:
        stacked = {k: torch.cat([d[k] for d in per[m]["metrics"]]) for k in per[m]["metrics"][0]}
        row = {"protocol": key, "method": m, "frames": len(per[m]["metrics"])}
        row.update({k: v for k, v in average_metrics(stacked).items()})
        se = np.sum([b[0] for b in per[m]["bins"]], 0)
        count = np.sum([b[1] for b in per[m]["bins"]], 0)
        labels = [f"{lo:g}-{hi:g} m" if np.isfinite(hi) else f">= {lo:g} m"
                  for lo, hi in zip(DEPTH_BINS_M[:-1], DEPTH_BINS_M[1:])]
        # pooled over the protocol's target pixels: RMSE within each bin and its share of all squared error
        row["depth_bins"] = {lab: dict(pixels=int(n), rmse_mm=float(np.sqrt(e / max(n, 1)) * 1000.0),
                                       share_of_squared_error=float(e / max(se.sum(), 1e-12)))
                             for lab, e, n in zip(labels, se, count)}
        sec = statistics.median(per[m]["seconds"])
        row.update(seconds_median=sec, fps_median=1.0 / sec, device=args.device, batch_size=1,
                   threads=torch.get_num_threads(), size=f"{w}x{h}")
        if m in LEARNED_ABLATIONS:
            row["config"] = {k: (list(v) if isinstance(v, tuple) else v) for k, v in LEARNED_ABLATIONS[m].items()}
            row["fit"] = (f"weights learned for this configuration by the shipped recipe on its "
                          f"{fits[('recipe', m)]['frames']} frames (drive 0060, object frames; both hold-outs)")
            row["weights"] = fits[("recipe", m)]["weights"]
        elif m in CRF_METHODS:
            row["config"] = {k: (list(v) if isinstance(v, tuple) else v) for k, v in method_config(m).items()}
        for name, items in per[m]["unc"].items():
            row[f"ause_{name}_mm"] = 1000.0 * float(np.mean([a["ause"] for a in items]))
            row[f"ause_random_{name}_mm"] = 1000.0 * float(np.mean([a["ause_random"] for a in items]))
            row[f"ause_ratio_{name}"] = row[f"ause_{name}_mm"] / row[f"ause_random_{name}_mm"]
            row[f"spearman_{name}"] = float(np.mean([a["spearman"] for a in items]))
            if name != "count":
                for k in ("coverage_1", "coverage_2", "nll", "nll_laplace"):
                    row[f"{k}_{name}"] = float(np.mean([a[k] for a in items]))
                curves[(m, f"reliability {name}")] = np.mean([a["reliability"] for a in items], 0)
            curves[(m, name)] = np.mean([a["curve"] for a in items], 0)
            curves[(m, "oracle")] = np.mean([a["oracle"] for a in items], 0)
        if m == "learned" and "std" in per[m]["unc"]:
            row["std_terms"] = {g: fits[FIT_SOURCE[(key, g)]]["std_terms"] for g in fit_note}
        if m == "learned":
            row["fit"] = "; ".join(fit_note.values())
            row["weights"] = {g: fits[FIT_SOURCE[(key, g)]]["weights"] for g in fit_note}
            row["fit_last_epoch_loss"] = {g: fits[FIT_SOURCE[(key, g)]]["loss"] for g in fit_note}
        rows.append(row)
    return rows, curves


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
            model, loss, count = CRFDepth.from_pretrained("kitti").to(args.device), float("nan"), 0
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
        fits[source] = dict(model=model, weights=model.weights(), loss=loss, frames=count,
                            std_terms=model.std_head.terms(), train_frames=frames)
    return fits[source]["model"]


def posterior_view(model: CRFDepth, fits: dict, args) -> CRFDepth:
    """``model`` with ``uncertainty="posterior"`` (``--posterior-samples`` samples), its scale
    calibrated in closed form on the frames ``model`` was fitted on (the shipped weights carry
    theirs); cached in ``fits``."""
    from train.calibrate import calibrate_std_scale

    fit = next(f for f in fits.values() if f["model"] is model)
    if "posterior" not in fit:
        view = CRFDepth(**{**model.config, "uncertainty": "posterior", "std_samples": args.posterior_samples})
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


def subsampling(args, log) -> list[dict]:
    """RMSE of the hand-set weights and NN on protocol b for every keep fraction."""
    rows = []
    model = CRFDepth().to(args.device)
    for frac in args.fractions:
        res = {"paper": [], "nn": []}
        for group, layout, folder, options in PROTOCOLS["b"][1]:
            for s in load_group(args.kitti_root, layout, folder, options, args.subsample_frames, frac):
                image, sparse, target, K = batch(s, args.device)
                for m in res:
                    depth, *_ = predict(m, model if m == "paper" else None, image, sparse, K, args.device)
                    res[m].append(depth_metrics(depth, target))
        for m, items in res.items():
            stacked = {k: torch.cat([d[k] for d in items]) for k in items[0]}
            avg = average_metrics(stacked)
            rows.append(dict(study="subsampling", protocol="b", method=m, keep_fraction=frac, frames=len(items),
                             rmse=avg["rmse"], mae=avg["mae"]))
        log(f"  keep {frac:.0%}: paper {rows[-2]['rmse']:.0f} mm, nn {rows[-1]['rmse']:.0f} mm")
    return rows


# -- reporting ---------------------------------------------------------------------------
def markdown_tables(rows: list[dict]) -> list[str]:
    lines = []
    for key in dict.fromkeys(r["protocol"] for r in rows):
        rs = [r for r in rows if r["protocol"] == key]
        lines += ["", f"**{PROTOCOLS[key][0]}** ({rs[0]['frames']} frames, {rs[0]['size']}, "
                      f"{rs[0]['device']}, batch 1, {rs[0]['threads']} thread(s))", "",
                  "| method | RMSE mm | MAE mm | iRMSE 1/km | iMAE 1/km | REL | d<1.25 | fps |",
                  "|---|---|---|---|---|---|---|---|"]
        for r in rs:
            lines.append(f"| {r['method']} | {r['rmse']:.0f} | {r['mae']:.0f} | {r['irmse']:.2f} | {r['imae']:.2f} "
                         f"| {r['rel']:.4f} | {r['delta1']:.4f} | {r['fps_median']:.2f} |")
        for r in rs:
            if "fit" in r:
                lines.append(f"\n{r['method']}: {r['fit']}")
    binned = [r for r in rows if "depth_bins" in r]
    if binned:
        labels = list(binned[0]["depth_bins"])
        lines += ["", "**Where the error is: pooled RMSE mm by target depth (share of the squared error)**", "",
                  "| protocol | method | " + " | ".join(labels) + " |", "|---|---|" + "---|" * len(labels)]
        for r in binned:
            cells = [f"{v['rmse_mm']:.0f} ({v['share_of_squared_error']:.0%})" for v in r["depth_bins"].values()]
            lines.append(f"| {r['protocol']} | {r['method']} | " + " | ".join(cells) + " |")
    unc = [r for r in rows if "ause_std_mm" in r]
    if unc:
        lines += ["", "**Uncertainty** (per image, averaged; AUSE of RMSE in mm, lower is better; within k std: "
                      "a calibrated Gaussian has 0.683 / 0.954; NLL: Gaussian, nats, errors in m)", "",
                  "| protocol | method | map | AUSE mm | random mm | AUSE / random | Spearman | within 1 std "
                  "| within 2 std | NLL |", "|---|---|---|---|---|---|---|---|---|---|"]
        for r in unc:
            for name in ("std", "posterior", "count"):
                if f"ause_{name}_mm" not in r:
                    continue
                cal = (f"{r[f'coverage_1_{name}']:.3f} | {r[f'coverage_2_{name}']:.3f} | {r[f'nll_{name}']:.2f}"
                       if name != "count" else "- | - | -")
                lines.append(f"| {r['protocol']} | {r['method']} | {name} | {r[f'ause_{name}_mm']:.0f} "
                             f"| {r[f'ause_random_{name}_mm']:.0f} | {r[f'ause_ratio_{name}']:.3f} "
                             f"| {r[f'spearman_{name}']:.3f} | {cal} |")
    return lines


def subsampling_table(rows: list[dict]) -> list[str]:
    lines = ["", f"**Sub-sampling, protocol (b): RMSE mm vs share of input LiDAR points kept** "
                 f"({rows[0]['frames']} frames)", "", "| kept | paper | nn |", "|---|---|---|"]
    for frac in dict.fromkeys(r["keep_fraction"] for r in rows):
        d = {r["method"]: r["rmse"] for r in rows if r["keep_fraction"] == frac}
        lines.append(f"| {frac:.0%} | {d['paper']:.0f} | {d['nn']:.0f} |")
    return lines


def verdicts(rows: list[dict]) -> list[str]:
    out = ["", "**Verdicts**", ""]
    by = {(r["protocol"], r["method"]): r for r in rows}
    for key in dict.fromkeys(r["protocol"] for r in rows):
        if (key, "learned") in by and (key, "nn") in by:
            l, n = by[(key, "learned")]["rmse"], by[(key, "nn")]["rmse"]
            gain = (n - l) / n
            need = TARGET_GAIN_C if key == "c" else 0.0
            ok = gain > need if need == 0 else gain >= need
            out.append(f"- protocol {key}: learned {l:.0f} mm vs nn {n:.0f} mm: {gain:+.1%} "
                       f"(target {'> 0' if need == 0 else f'>= {need:.0%}'}): "
                       f"{'meets' if ok else f'misses by {(need - gain) * 100:.1f} points'}")
        for other, label, target in (("ipbasic", "IP-Basic", TARGET_VS_IPBASIC),
                                     ("hand-set", "the same structure hand-set", TARGET_VS_HANDSET)):
            if (key, "learned") in by and (key, other) in by:
                l, o = by[(key, "learned")]["rmse"], by[(key, other)]["rmse"]
                verdict = "meets" if l <= target * o else f"misses by {l - target * o:.0f} mm"
                out.append(f"- protocol {key}: learned {l:.0f} mm vs {label} {o:.0f} mm: {l / o:.3f} x "
                           f"(target <= {target}, {target * o:.0f} mm): {verdict}")
    for key in dict.fromkeys(r["protocol"] for r in rows):
        r = by.get((key, "learned"))
        if r is None or "ause_std_mm" not in r:
            continue
        lo, hi = TARGET_COVERAGE
        checks = [(f"AUSE {r['ause_ratio_std']:.3f} x random (target <= {TARGET_AUSE_RATIO})",
                   r["ause_ratio_std"] <= TARGET_AUSE_RATIO),
                  (f"AUSE {r['ause_std_mm']:.0f} mm vs count map {r['ause_count_mm']:.0f} mm (target below)",
                   r["ause_std_mm"] < r["ause_count_mm"]),
                  (f"Spearman {r['spearman_std']:.3f} (target >= {TARGET_SPEARMAN})", r["spearman_std"] >= TARGET_SPEARMAN),
                  (f"within 1 std {r['coverage_1_std']:.3f} (target {lo}-{hi})", lo <= r["coverage_1_std"] <= hi)]
        out += [f"- protocol {key}, learned std: {text}: {'meets' if ok else 'misses'}" for text, ok in checks]
    chains = [("no refinement, hand-set weights", ["sp-c", "sp-cn", "sp-cnd"]),
              ("with refinement, hand-set weights", ["sp-c+r", "sp-cn+r", "paper"]),
              ("no refinement, weights learned per configuration", ["sp-c/learned", "sp-cn/learned", "sp-cnd/learned"]),
              ("with refinement, weights learned per configuration", ["sp-c+r/learned", "sp-cn+r/learned", "learned"])]
    for label, chain in chains:
        if all(("a", m) in by for m in chain):
            v = [by[("a", m)]["rmse"] for m in chain]
            steps = [f"{chain[i]} -> {chain[i + 1]}: {v[i]:.1f} -> {v[i + 1]:.1f} mm "
                     f"({'ok' if v[i + 1] <= v[i] else f'worse by {v[i + 1] - v[i]:.1f} mm'})" for i in range(2)]
            ok = all(v[i + 1] <= v[i] for i in range(2))
            out.append(f"- Table 1 order on protocol a ({label}): {'; '.join(steps)}: {'meets' if ok else 'misses'}")
    return out


def plots(out_dir: Path, sub_rows: list[dict], curves: dict) -> list[Path]:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    paths = []
    if sub_rows:
        fig, ax = plt.subplots(figsize=(5, 3.5))
        for m in ("paper", "nn"):
            rs = [r for r in sub_rows if r["method"] == m]
            ax.plot([100 * r["keep_fraction"] for r in rs], [r["rmse"] for r in rs], "o-", label=m)
        ax.set_xlabel("input LiDAR points kept (%)")
        ax.set_ylabel("RMSE (mm)")
        ax.set_title("protocol (b): sub-sampling")
        ax.grid(alpha=0.3)
        ax.legend()
        fig.tight_layout()
        paths.append(out_dir / "subsampling.png")
        fig.savefig(paths[-1], dpi=120)
        plt.close(fig)
    if curves:
        keys = list(curves)
        fig, axes = plt.subplots(1, len(keys), figsize=(4 * len(keys), 3.3), squeeze=False)
        for ax, key in zip(axes[0], keys):
            f = np.arange(SPARSIFY_STEPS) / SPARSIFY_STEPS * 100
            shown = "learned" if any(m == "learned" for m, _ in curves[key]) else "paper"
            for (m, name), c in curves[key].items():
                if m == shown and not name.startswith("reliability"):  # the oracle differs a little per method
                    ax.plot(f, c, "--" if name == "oracle" else "-",
                            label=f"{m} {name}" if name != "oracle" else f"oracle ({m} errors)")
                    if name == "oracle":
                        ax.axhline(c[0], color="grey", lw=0.8, ls=":", label="random order")
            _label(ax, f"protocol {key}: sparsification", "pixels removed (%)", "RMSE (mm)")
        paths.append(_save(fig, out_dir / "sparsification.png"))
        fig, axes = plt.subplots(1, len(keys), figsize=(4 * len(keys), 3.3), squeeze=False)
        ks = reliability(np.ones(1), np.ones(1))
        for ax, key in zip(axes[0], keys):
            ax.plot(ks["k"], ks["expected"], "k--", label="Gaussian")
            shown = "learned" if any(m == "learned" for m, _ in curves[key]) else "paper"
            for (m, name), c in curves[key].items():
                if name.startswith("reliability") and m == shown:
                    ax.plot(ks["k"], c, "-", label=f"{m} {name.split()[1]}")
            _label(ax, f"protocol {key}: reliability", "k (std)", "share of |error| <= k std")
        paths.append(_save(fig, out_dir / "reliability.png"))
    return paths


def _label(ax, title: str, xlabel: str, ylabel: str) -> None:
    ax.set_title(title)
    ax.set_xlabel(xlabel)
    ax.set_ylabel(ylabel)
    ax.grid(alpha=0.3)
    if ax.get_legend_handles_labels()[0]:
        ax.legend(fontsize=8)


def _save(fig, path: Path) -> Path:
    import matplotlib.pyplot as plt

    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)
    return path


def parse_args(argv: Sequence[str] | None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--kitti-root", type=Path, default=DEFAULT_ROOT, help="KITTI root (default: %(default)s)")
    parser.add_argument("--protocols", nargs="+", choices=list(PROTOCOLS), default=list(PROTOCOLS))
    parser.add_argument("--methods", nargs="+", choices=list(METHODS), default=list(METHODS))
    parser.add_argument("--max-frames", type=int, default=None, help="frames per group (evenly spaced); default all")
    parser.add_argument("--fit-epochs", type=int, default=None,
                        help="epochs of each learned-weight fit (default: the recipe's, configs/kitti_weights.yaml)")
    parser.add_argument("--fit-frames", type=int, default=None, help="frames per group of each fit; default all")
    parser.add_argument("--learn-ablations", action="store_true",
                        help="protocol a: also the Table 1 ablations with weights learned per configuration by the "
                             "shipped recipe (5 more fits)")
    parser.add_argument("--fractions", type=float, nargs="+", default=[0.2, 0.4, 0.6, 0.8, 1.0])
    parser.add_argument("--subsample-frames", type=int, default=None, help="frames per group of the sub-sampling "
                        "study (default: --max-frames)")
    parser.add_argument("--no-subsample", action="store_true", help="skip the sub-sampling study")
    parser.add_argument("--posterior-samples", type=int, default=8,
                        help="samples of the posterior-only std (the model default is 32; 8 keeps the run short)")
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--threads", type=int, default=1, help="torch CPU threads")
    parser.add_argument("--quick", action="store_true", help="smoke run: 1 frame per group, 1 fit epoch on "
                        "1 frame per group, fractions 0.5 and 1.0")
    parser.add_argument("--out-dir", type=Path, default=Path("accuracy_results"))
    parser.add_argument("--targets-root", type=Path, default=None,
                        help="camera-view targets of protocols q/q22 (the --out-dir of crfdepth targets); made there "
                             "when missing (default: <out-dir>/targets)")
    args = parser.parse_args(argv)
    if args.quick:
        args.max_frames, args.fit_epochs, args.fit_frames = 1, 1, 1
        if args.fractions == parser.get_default("fractions"):
            args.fractions = [0.5, 1.0]
    if args.subsample_frames is None:
        args.subsample_frames = args.max_frames
    if args.fit_epochs is None:
        import yaml

        args.fit_epochs = int(yaml.safe_load(RECIPE.read_text())["trainer"]["max_epochs"])
    if args.targets_root is None:
        args.targets_root = args.out_dir / "targets"
    if args.fit_epochs < 1:
        parser.error(f"--fit-epochs: expected >= 1, got {args.fit_epochs}")
    needed = sorted({folder for key in args.protocols for _, _, folder, _ in PROTOCOLS[key][1] if folder}
                    | ({"raw", "object/training"} if args.learn_ablations else set())
                    | (set() if args.no_subsample else {"raw", "object/training"}))
    missing = [f for f in needed if not (args.kitti_root / f).is_dir()]
    if missing:
        parser.error(f"--kitti-root: expected the folders {', '.join(needed)} under {args.kitti_root} "
                     f"(the layout of ../shared/data/kitti), missing: {', '.join(missing)}")
    return args


def main(argv: Sequence[str] | None = None) -> list[dict]:
    """Run the benchmark; returns the JSON rows (also printed and written to ``--out-dir``)."""
    args = parse_args(argv)
    torch.set_num_threads(args.threads)
    args.out_dir.mkdir(parents=True, exist_ok=True)
    start = time.perf_counter()

    def log(msg: str) -> None:
        print(f"[{time.perf_counter() - start:6.0f} s] {msg}", flush=True)

    rows, fits, curves = [], {}, {}
    for key in args.protocols:
        log(f"protocol {key}")
        r, c = evaluate_protocol(key, args, fits, log)
        rows += r
        curves[key] = c
    sub_rows = [] if args.no_subsample else (log("sub-sampling study") or subsampling(args, log))
    lines = [f"# crfdepth accuracy benchmark ({args.kitti_root})", *markdown_tables(rows)]
    if sub_rows:
        lines += subsampling_table(sub_rows)
    lines += verdicts(rows)
    lines.append(f"\ntotal run time {time.perf_counter() - start:.0f} s")
    text = "\n".join(lines)
    print(text)
    all_rows = rows + sub_rows
    with open(args.out_dir / "results.jsonl", "w") as fh:
        for r in all_rows:
            print(json.dumps(r))
            fh.write(json.dumps(r) + "\n")
    (args.out_dir / "results.md").write_text(text + "\n")
    for p in plots(args.out_dir, sub_rows, curves):
        print(f"plot: {p}")
    return all_rows


if __name__ == "__main__":
    main()
