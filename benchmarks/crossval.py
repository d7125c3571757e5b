"""Choose a training recipe by cross-validation over scenes, never on the frames that are reported.

For every recipe and every fold: train on the frames of all the other folds, then score the left-out
fold's frames with the learned weights and with the hand-set weights of the same structure, in the
same run, and report learned / hand-set (RMSE, mean of the per-frame RMSE in mm, KITTI's per-image
mean). The folds are whole scenes (docs/design.md section 16):

- ``0001-05-09``, ``0001-10-14``, ``0001-50``, ``0001-100``: KITTI's annotated frames of drive 0001
  (frame 5 from ``depth_completion``, the rest from ``annotated``). Scored with 22% of the annotation
  as input and the other 78% as target (protocol a22 of ``benchmarks/accuracy.py``), and frame 5
  also with its own scan as input and the whole annotation as target (protocol a);
- ``0060-00-24``, ``0060-30-48``, ``0060-54-72``: the sample frames of raw drive 0060, LiDAR held out
  of each scan as the target (20% of the returns, see-through returns removed);
- ``object``: the object-benchmark frames, the same hold-out;
- ``0048``: the three frames of drive 0048 (``stereo/``), the same hold-out.

Training uses each training fold's frames as its recipe says: annotated frames with a random 22% of
their annotation as input, or the pixels of a random 16-, 32- or 64-beam ring pattern ("rings"), the
scans with 20% of their returns or three of every four rings held out; each source weighted
(:func:`train.sources.weighted`).

    python benchmarks/crossval.py                       # every recipe, every fold
    python benchmarks/crossval.py --recipes l1 huber --folds 0001-50 object --epochs 2

Prints one table row per recipe (the mean and the worst fold of learned / hand-set, then each fold)
and one JSON line. ``--kitti-root`` defaults to ``../shared/data/kitti`` beside the repository.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

import torch
from torch.utils.data import ConcatDataset, Dataset, Subset

ROOT = Path(__file__).resolve().parents[1]
for folder in (ROOT, ROOT / "benchmarks"):  # the package, and accuracy_parts beside this file
    if str(folder) not in sys.path:
        sys.path.insert(0, str(folder))

from accuracy_parts.fits import train_module  # noqa: E402

from crfdepth.config import CRFConfig  # noqa: E402
from crfdepth.data import build_dataset  # noqa: E402
from crfdepth.errors import InputError  # noqa: E402
from crfdepth.model import CRFDepth  # noqa: E402
from crfdepth.potentials.head import PotentialHead  # noqa: E402

if str(Path(__file__).resolve().parent) not in sys.path:  # a load by the file's path (the tests) has not
    sys.path.append(str(Path(__file__).resolve().parent))

import script_args as sa  # noqa: E402  (benchmarks/script_args.py: one-line errors, checked option types)

DEFAULT_ROOT = ROOT.parent / "shared" / "data" / "kitti"
SHIPPED_STRUCTURE = {"structure": {"mode": "pixel", "variable": "log"}, "gate": {"enabled": True}}


def _frames(drive: str, *numbers: int) -> list[str]:
    return [f"{drive}_sync_{'velodyne_raw_' if drive.endswith('0001') else ''}{n:010d}" for n in numbers]


# fold -> its groups: (kind, folder under --kitti-root, the sample-name parts of its frames; None = all)
FOLDS: dict[str, list[tuple[str, str, list[str] | None]]] = {
    "0001-05-09": [("dc", "depth_completion", _frames("drive_0001", 5)),
                   ("annotated", "annotated", _frames("drive_0001", 6, 7, 8, 9))],
    "0001-10-14": [("annotated", "annotated", _frames("drive_0001", 10, 11, 12, 13, 14))],
    "0001-50": [("annotated", "annotated", _frames("drive_0001", 50))],
    "0001-100": [("annotated", "annotated", _frames("drive_0001", 100))],
    "0060-00-24": [("raw", "raw", _frames("drive_0060", 0, 6, 12, 18, 24))],
    "0060-30-48": [("raw", "raw", _frames("drive_0060", 30, 36, 42, 48))],
    "0060-54-72": [("raw", "raw", _frames("drive_0060", 54, 60, 66, 72))],
    "object": [("object", "object/training", None)],
    "0048": [("raw", "stereo", None)],
}


@dataclass(frozen=True)
class Recipe:
    """What a fold trains: the model's structure and loss, the sources and their weights, the inputs."""

    loss: str = "l1"
    head: bool = False
    lr: float = 0.02
    sources: dict[str, float] = field(default_factory=lambda: {"annotated": 1.0, "scans": 1.0})
    annotated_inputs: tuple[str, ...] = ("share", "rings")  # how an annotated frame's input is drawn
    thin: tuple[float, float] | None = (0.5, 1.0)  # density augmentation of every input
    head_hidden: int = 16  # channels of the head's hidden layers (PotentialHead(hidden=...)); 16 is the model's

    def crf(self) -> dict:
        structure = {**SHIPPED_STRUCTURE["structure"], **({"head": True} if self.head else {})}
        return {**SHIPPED_STRUCTURE, "structure": structure}


# how an annotated frame's input is drawn (Recipe.annotated_inputs): KittiAnnotated's options
ANNOTATED_INPUTS = {
    "share": {"input_from": "share"},  # 22% of the annotation, a clean input
    "rings": {"input_from": "rings"},  # the annotated pixels on a 64-beam ring pattern, a clean input
    "lidar": {"input_from": "lidar"},  # a simulated 64-beam scan, see-through returns included
    "lidar16": {"input_from": "lidar", "keep_every_ring": 4},  # the same, 16 beams
}

RECIPES = {
    "l1": Recipe(),
    "huber": Recipe(loss="huber"),
    "l2": Recipe(loss="l2"),
    "l1-annotated": Recipe(sources={"annotated": 1.0}),
    # the annotation alone, half its inputs clean, half a simulated scan with its see-through returns
    "l1-annotated-lidar": Recipe(sources={"annotated": 1.0}, annotated_inputs=("share", "lidar")),
    # as l1-annotated-lidar, and a 16-beam simulated scan: the weights also see sparse inputs
    "l1-annotated-lidar-beams": Recipe(sources={"annotated": 1.0}, annotated_inputs=("share", "lidar", "lidar16")),
    # as l1-annotated-lidar-beams with the learned head, which sees the local LiDAR mask (the input's density)
    "head-annotated-lidar-beams": Recipe(head=True, sources={"annotated": 1.0},
                                         annotated_inputs=("share", "lidar", "lidar16")),
    # a head of 8 hidden channels (1.3x the shipped model's time per frame, 16 channels 1.5x), and the real
    # scans' 20% and 16-beam hold-outs beside the annotation at half weight: real see-through returns
    "head8-annotated-lidar-beams-scans": Recipe(head=True, head_hidden=8, sources={"annotated": 1.0, "scans": 0.5},
                                                annotated_inputs=("share", "lidar", "lidar16")),
    "head8-annotated-lidar-beams": Recipe(head=True, head_hidden=8, sources={"annotated": 1.0},
                                          annotated_inputs=("share", "lidar", "lidar16")),
    "l1-scans": Recipe(sources={"scans": 1.0}),  # the shipped recipe's sources: LiDAR hold-outs only
    "l1-share": Recipe(annotated_inputs=("share",)),
    "l1-annotated-x3": Recipe(sources={"annotated": 3.0, "scans": 1.0}),
    "head-huber": Recipe(loss="huber", head=True),
}


def _names(dataset: Dataset) -> list[str]:
    return list(dataset.names)


def _only(dataset: Dataset, frames: list[str] | None) -> Dataset | None:
    """The frames of ``dataset`` whose names hold one of ``frames`` (camera 02 only); None if none."""
    keep = [i for i, n in enumerate(_names(dataset))
            if (frames is None or any(f in n for f in frames)) and not n.endswith("image_03")]
    return Subset(dataset, keep) if keep else None


def fold_datasets(root: Path, fold: str, train: bool, recipe: Recipe | None = None) -> list[tuple[str, Dataset]]:
    """(source or protocol, dataset) pairs of ``fold``: its training sets (``train=True``, as ``recipe``
    draws them) or its scored sets."""
    out = []
    for kind, folder, frames in FOLDS[fold]:
        where = root / folder
        group = []
        if kind in ("dc", "annotated"):
            if train and "annotated" in recipe.sources:
                for mode in recipe.annotated_inputs:
                    group.append(("annotated", build_dataset("annotated", where, **ANNOTATED_INPUTS[mode])))
            elif not train:
                group.append(("a22", build_dataset("annotated", where, input_from="share", seed=0)))
                if kind == "dc":
                    group.append(("a", build_dataset("annotated", where, input_from="scan")))
        elif not train or "scans" in recipe.sources:
            layout = "object" if kind == "object" else "raw"
            fraction = {"holdout": "fraction", "holdout_fraction": 0.2, "seed": 0}
            sixteen = {"holdout": "rings", "keep_every_ring": 4}
            for protocol, options in ([("scans", fraction), ("scans", sixteen)] if train
                                      else [("holdout", fraction), ("holdout16", sixteen)]):
                group.append((protocol, build_dataset(layout, where, **options)))
        picked = [(p, _only(d, frames)) for p, d in group]
        if not train and any(d is None for _, d in picked):
            raise InputError(f"--folds: fold {fold!r} would be empty: no frame of {', '.join(frames)} in {where}")
        out += [(p, d) for p, d in picked if d is not None]
    if train:
        return out
    merged: dict[str, list[Dataset]] = {}
    for protocol, dataset in out:  # one set per protocol (frame 5 and frames 6-9 are both a22)
        merged.setdefault(protocol, []).append(dataset)
    return [(p, ds[0] if len(ds) == 1 else ConcatDataset(ds)) for p, ds in merged.items()]


def train_fold(root: Path, folds: Sequence[str], recipe: Recipe, epochs: int, seed: int,
               device: str, workers: int = 0) -> tuple[CRFDepth, float, int]:
    """Weights learned on ``folds`` by ``recipe``: (model, seconds, frames per epoch)."""
    import lightning.pytorch as pl

    from crfdepth.data import Compose, HorizontalFlip, RandomCrop, RandomThinning
    from train.data import TransformedDataset
    from train.module import CRFDepthModule
    from train.sources import weighted

    start = time.perf_counter()
    parts = []
    for fold in folds:
        for source, dataset in fold_datasets(root, fold, train=True, recipe=recipe):
            parts.append(weighted(dataset, recipe.sources[source], seed=seed))
    if not parts:
        raise InputError(f"--recipes: recipe trains on no frame of folds {list(folds)}")
    augment = [HorizontalFlip(p=0.5), RandomCrop(320, 896)] + ([RandomThinning(*recipe.thin)] if recipe.thin else [])
    data = TransformedDataset(ConcatDataset(parts), Compose(augment))
    pl.seed_everything(seed, verbose=False)
    module = CRFDepthModule(crf=CRFConfig.build(recipe.crf()).groups(), loss=recipe.loss, lr=recipe.lr)
    if recipe.head and recipe.head_hidden != module.model.head.net[0].out_channels:
        # another width: replaced before fit, which builds the optimiser from the module's parameters
        # (the model's own width is left as built, so runs before this option draw the same weights)
        module.model.head = PotentialHead(hidden=recipe.head_hidden)
    train_module(module, data, epochs, device, workers=workers)
    return module.model.to(device).eval(), time.perf_counter() - start, len(data)


def rmse_mm(model: CRFDepth, dataset: Dataset, device: str) -> list[float]:
    """Per-frame RMSE (mm) of ``model`` on ``dataset``'s target pixels."""
    out = []
    with torch.no_grad():
        for i in range(len(dataset)):
            s = dataset[i]
            depth = model(s.image[None].to(device), s.sparse[None].to(device), s.K.to(device)).depth[0].cpu()
            valid = s.target > 0
            out.append(1000.0 * float(((depth[valid] - s.target[valid]) ** 2).mean().sqrt()))
    return out


def check_folds(folds: Sequence[str], name: str = "--folds") -> list[str]:
    unknown = [f for f in folds if f not in FOLDS]
    if unknown:
        raise InputError(f"{name}: expected fold names among {', '.join(FOLDS)}, got {unknown}")
    if len(set(folds)) < 2:
        raise InputError(f"{name}: expected at least two distinct folds (one to score, the rest to train on), "
                         f"got {list(folds)}")
    return list(dict.fromkeys(folds))


def scored_sets(root: Path, folds: Sequence[str]) -> dict[str, list[tuple[str, Dataset]]]:
    """Each fold's scored sets; a missing folder or an empty fold is refused, named."""
    out = {}
    for fold in folds:
        try:
            out[fold] = fold_datasets(root, fold, train=False)
        except FileNotFoundError as e:
            raise InputError(f"--kitti-root: fold {fold!r} needs a folder that does not exist ({e})") from None
    return out


def run(args: argparse.Namespace, log=print) -> list[dict]:
    folds = check_folds(args.folds)
    scored = scored_sets(args.kitti_root, folds)
    hand_set = CRFDepth(CRFConfig.build(SHIPPED_STRUCTURE)).to(args.device).eval()
    hand = {fold: {p: rmse_mm(hand_set, d, args.device) for p, d in sets} for fold, sets in scored.items()}
    rows = []
    for name in args.recipes:
        recipe = RECIPES[name]
        row = {"recipe": name, "epochs": args.epochs, "folds": {}}
        for fold in args.score or folds:
            model, seconds, count = train_fold(args.kitti_root, [f for f in folds if f != fold], recipe,
                                               args.epochs, args.seed, args.device, args.workers)
            result = {"seconds": round(seconds, 1), "train_frames_per_epoch": count}
            for protocol, dataset in scored[fold]:
                learned = rmse_mm(model, dataset, args.device)
                base = hand[fold][protocol]
                result[protocol] = {"hand_set_mm": round(sum(base) / len(base), 1),
                                    "learned_mm": round(sum(learned) / len(learned), 1),
                                    "ratio": round(sum(learned) / sum(base), 4), "frames": len(base)}
            result["ratio"] = result[scored[fold][0][0]]["ratio"]  # a fold's figure: its first protocol
            row["folds"][fold] = result
            log(f"  {name} / {fold}: learned / hand-set {result['ratio']:.3f} ({seconds:.0f} s, {count} frames "
                f"per epoch); weights " + ", ".join(f"{k} {v:.3g}" for k, v in model.weights().items()))
        ratios = [r["ratio"] for r in row["folds"].values()]
        row["mean"] = round(sum(ratios) / len(ratios), 4)
        row["worst"] = round(max(ratios), 4)
        rows.append(row)
    return rows


def table(rows: list[dict], folds: Sequence[str]) -> list[str]:
    lines = ["| recipe | mean | worst | " + " | ".join(folds) + " |", "|---" * (3 + len(folds)) + "|"]
    for r in rows:
        lines.append(f"| {r['recipe']} | {r['mean']:.3f} | {r['worst']:.3f} | "
                     + " | ".join(f"{r['folds'][f]['ratio']:.3f}" for f in folds) + " |")
    return lines


def parse_args(argv: Sequence[str] | None = None) -> argparse.Namespace:
    parser = sa.ScriptParser(prog="crossval.py", description=__doc__.split("\n\n")[0])
    parser.add_argument("--recipes", nargs="+", default=list(RECIPES), choices=list(RECIPES), metavar="RECIPE",
                        help=f"recipes to cross-validate (default all: {', '.join(RECIPES)})")
    parser.add_argument("--folds", nargs="+", default=list(FOLDS), metavar="FOLD",
                        help=f"the folds (default all: {', '.join(FOLDS)})")
    parser.add_argument("--score", nargs="+", metavar="FOLD",
                        help="score only these of --folds (each still trained on all the other folds of --folds): "
                             "to spread one cross-validation over several machines; default all")
    parser.add_argument("--epochs", type=sa.count(1), default=4, help="training epochs per fold (default 4)")
    parser.add_argument("--seed", type=sa.seed, default=0)
    parser.add_argument("--device", type=sa.device, default="cpu", help="torch device of training and scoring (default cpu)")
    parser.add_argument("--workers", type=sa.count(0, sa.MAX_WORKERS), default=0, help="DataLoader worker processes per fold (default 0)")
    parser.add_argument("--kitti-root", type=Path, default=DEFAULT_ROOT)
    args = parser.parse_args(argv)
    if args.epochs < 1:
        parser.error(f"--epochs: expected an integer >= 1, got {args.epochs}")
    if args.workers < 0:
        parser.error(f"--workers: expected an integer >= 0, got {args.workers}")
    try:
        check_folds(args.folds)
    except InputError as e:
        parser.error(str(e))
    outside = [f for f in args.score or () if f not in args.folds]
    if outside:
        parser.error(f"--score: expected folds among --folds ({', '.join(args.folds)}), got {outside}")
    return args


def main(argv: Sequence[str] | None = None) -> list[dict]:
    args = parse_args(argv)
    try:
        rows = run(args, log=lambda m: print(m, flush=True))
    except InputError as e:
        print(f"crossval.py: error: {e}", file=sys.stderr)
        raise SystemExit(2) from None
    folds = check_folds(args.folds)
    print("\n".join(table(rows, args.score or folds)))
    print(json.dumps({"benchmark": "crossval", "rows": rows}))
    if any(not math.isfinite(r["mean"]) for r in rows):
        raise SystemExit(1)
    return rows


if __name__ == "__main__":
    sys.exit(sa.run_script(main, "crossval.py"))
