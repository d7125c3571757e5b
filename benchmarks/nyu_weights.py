"""Indoor weights: learned on real NYU Depth v2 frames, judged on a scene they never saw (issue 49, part 5).

The frames are NYU's protocol (:func:`crfdepth.data.sampling.nyu_protocol`: 320x240, centre 304x228) of the
scenes under ``--nyu-root`` (default ``../shared/data/nyu``): ``basement`` (the three ``official_test``
frames, ``nyu_sync``) and ``dining`` (``labeled_crop``, ``nyu_raw``). The structure is the default model's
sparse regime (docs/design.md section 17): the pixel grid with a coarse solve on 6-pixel blocks, the depth
unknown, no occlusion gate (registered depth has no see-through returns).

- **Training draws**: each frame gives ``--repeats`` x 3 draws of 200, 500 and 1000 samples of its depth as
  the input, the rest of its depth (the input's pixels removed) as the target; flipped at random; the
  Lightning trainer's module (:mod:`train.module`), L2 loss, Adam at ``--lr``, ``--epochs`` epochs, seed 0.
  Beside the real frames, ``--rooms`` synthetic rooms (:func:`crfdepth.data.synthetic.rooms.make_room`, seeds
  1000 onwards) give one draw of each count: the same rooms in every fit, never a held-out scene.
- **Leave one scene out**: for each scene, weights fitted on the other scenes are scored on it at 500 and
  200 samples (NYU's protocol: the draw's depth all scored, seed 0), beside the shipped KITTI weights
  (``CRFDepth.from_pretrained(adaptive=False)``), the paper's structure with hand-set weights (``CRFDepth()``:
  SLIC superpixels and a pixel refinement), the default's hand-set scattered regime
  (``CRFDepth.from_pretrained().sparse_regime``), the default model with the weights fitted without the scene
  as its indoor regime (as it would ship without that scene: its routing on real frames) and the nearest fill.
  RMSE in metres, per image then averaged.
- ``--write FILE``: then fit on every scene, fit the predictive std to the training draws
  (:func:`train.calibrate.fit_predictive_std`) and write the weights file (``crfdepth/weights/nyu.json`` is
  this file, shipped as ``--weights nyu``).

    python benchmarks/nyu_weights.py [--nyu-root PATH] [--epochs 6] [--repeats 4] [--lr 0.02]
        [--rooms 12] [--threads 2] [--write FILE]

Prints a table and one JSON line.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
import time
import warnings
from collections.abc import Sequence
from pathlib import Path

import torch

ROOT = Path(__file__).resolve().parents[1]
for folder in (ROOT, ROOT / "benchmarks"):
    if str(folder) not in sys.path:
        sys.path.insert(0, str(folder))

import script_args as sa  # noqa: E402

from crfdepth.config import CRFConfig  # noqa: E402
from crfdepth.data.factory import build_dataset  # noqa: E402
from crfdepth.data.sampling import SparseSamples  # noqa: E402
from crfdepth.data.transforms import Compose, HorizontalFlip  # noqa: E402
from crfdepth.fill.nearest import nearest_fill  # noqa: E402
from crfdepth.metrics import depth_metrics  # noqa: E402
from crfdepth.model import CRFDepth  # noqa: E402

DEFAULT_ROOT = ROOT.parent / "shared" / "data" / "nyu"
SCENES = {"basement": ("nyu_sync", "official_test"), "dining": ("nyu_raw", "labeled_crop")}
STRUCTURE = {"structure": {"mode": "pixel", "coarse": 6, "variable": "depth"}, "gate": {"enabled": False}}
"""The structure of the NYU weights: the default model's sparse regime (docs/design.md section 17)."""
TRAIN_SAMPLES = (200, 500, 1000)
ROOMS = 12
"""Synthetic rooms beside the real frames in every fit (``--rooms``; section 17 has the count's effect)."""
ROOM_SEED = 1000
TEST_SAMPLES = (500, 200)


def parse_args(argv: Sequence[str] | None) -> argparse.Namespace:
    parser = sa.ScriptParser(prog="nyu_weights.py", description=__doc__.split("\n\n")[0])
    parser.add_argument("--nyu-root", type=sa.folder("--nyu-root"), default=DEFAULT_ROOT,
                        help="NYU Depth v2 sample frames (default: %(default)s)")
    parser.add_argument("--epochs", type=sa.count(1, 1000), default=6)
    parser.add_argument("--repeats", type=sa.count(1, 100), default=4, help="draws of each count per frame")
    parser.add_argument("--lr", type=sa.positive("learning rate"), default=0.02)
    parser.add_argument("--rooms", type=sa.count(0, 1000), default=ROOMS,
                        help="synthetic rooms among the training draws (default: %(default)s)")
    parser.add_argument("--threads", type=sa.count(1, sa.MAX_THREADS), default=2, help="torch CPU threads")
    parser.add_argument("--write", type=Path, default=None, metavar="FILE",
                        help="also fit on every scene and write the weights file here")
    return parser.parse_args(argv)


def scene_frames(root: Path) -> dict[str, list]:
    """The protocol-size frames of each scene (resize and crop, the stored depth as input and target)."""
    frames = {}
    for scene, (layout, folder) in SCENES.items():
        if not (root / folder).is_dir():
            raise SystemExit(f"--nyu-root: expected {folder}/ under {root} (the layout of ../shared/data/nyu)")
        frames[scene] = list(build_dataset(layout, root / folder, protocol=True))
    return frames


def training_draws(frames: list, repeats: int) -> list:
    """Inputs of 200, 500 and 1000 samples; targets: the rest of the depth."""
    draws = []
    for s in frames:
        for r in range(repeats):
            for j, n in enumerate(TRAIN_SAMPLES):
                t = SparseSamples(n, seed=100 + 10 * r + j)(dataclasses.replace(s, sparse=s.target))
                draws.append(dataclasses.replace(t, target=torch.where(t.sparse > 0, torch.zeros_like(t.target),
                                                                       t.target)))
    return draws


def room_draws(count: int) -> list:
    """The training draws of ``count`` synthetic rooms: one draw of each count of samples per room."""
    from crfdepth.data.synthetic.rooms import make_room

    return training_draws([make_room(ROOM_SEED + i) for i in range(count)], 1)


def fit(draws: list, args) -> CRFDepth:
    """The sparse regime's structure fitted to ``draws`` by the Lightning module (no validation or logging)."""
    from accuracy_parts.fits import train_module

    from train.data import TransformedDataset
    from train.module import CRFDepthModule

    torch.manual_seed(0)
    module = CRFDepthModule(crf=CRFConfig.build(STRUCTURE).groups(), loss="l2", lr=args.lr, nll_weight=0.0)
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", category=UserWarning)
        train_module(module, TransformedDataset(draws, Compose([HorizontalFlip(p=0.5)])), args.epochs, "cpu")
    return module.model.eval()


def rmse(model, frames: list) -> float:
    """Mean per-image RMSE in metres (``model`` None: the nearest fill)."""
    values = []
    for s in frames:
        with torch.no_grad():
            depth = nearest_fill(s.sparse[None]) if model is None else model(s.image[None], s.sparse[None],
                                                                             s.K[None]).depth
        values.append(float(depth_metrics(depth.clamp_min(1e-3), s.target[None])["rmse"][0]) / 1000.0)
    return sum(values) / len(values)


def main(argv: Sequence[str] | None = None) -> dict:
    args = parse_args(argv)
    torch.set_num_threads(args.threads)
    start = time.perf_counter()
    scenes = scene_frames(args.nyu_root)
    rooms = room_draws(args.rooms)
    default = CRFDepth.from_pretrained()
    others = {"kitti": CRFDepth.from_pretrained(adaptive=False), "paper": CRFDepth().eval(),
              "scattered": default.sparse_regime, "default": default}
    rows = []
    for held, frames in scenes.items():
        real = training_draws([s for k, v in scenes.items() if k != held for s in v], args.repeats)
        learned = fit(real + rooms, args)
        default.indoor_regime = learned  # the default as it would ship without this scene
        for n in TEST_SAMPLES:
            test = [SparseSamples(n, seed=0)(dataclasses.replace(s, sparse=s.target)) for s in frames]
            row = {"held_out": held, "samples": n, "frames": len(test), "nearest": rmse(None, test),
                   "learned": rmse(learned, test), **{k: rmse(m, test) for k, m in others.items()}}
            row["learned_vs_kitti"] = row["learned"] / row["kitti"]
            row["learned_vs_nearest"] = row["learned"] / row["nearest"]
            rows.append(row)
    print("| held-out scene | samples | nearest fill | KITTI weights | paper structure | scattered regime "
          "| learned here | default | learned / KITTI | learned / nearest |")
    print("|---|---|---|---|---|---|---|---|---|---|")
    for r in rows:
        print(f"| {r['held_out']} | {r['samples']} | {r['nearest']:.3f} | {r['kitti']:.3f} | {r['paper']:.3f} "
              f"| {r['scattered']:.3f} "
              f"| {r['learned']:.3f} | {r['default']:.3f} | {r['learned_vs_kitti']:.3f} "
              f"| {r['learned_vs_nearest']:.3f} |")
    summary = frame_means(rows)
    print("\n| samples | frames | nearest fill | KITTI weights | paper structure | default | default / nearest "
          "| default / paper |")
    print("|---|---|---|---|---|---|---|---|")
    for r in summary:
        print(f"| {r['samples']} | {r['frames']} | {r['nearest']:.4f} | {r['kitti']:.4f} | {r['paper']:.4f} "
              f"| {r['default']:.4f} | {r['default_vs_nearest']:.3f} | {r['default_vs_paper']:.3f} |")
    result = {"benchmark": "nyu_weights", "rows": rows, "summary": summary, "epochs": args.epochs,
              "repeats": args.repeats, "lr": args.lr, "rooms": args.rooms, "structure": STRUCTURE}
    if args.write is not None:
        result["written"] = str(write(scenes, rooms, args, rows))
    result["seconds"] = time.perf_counter() - start
    print(json.dumps(result))
    return result


def frame_means(rows: list[dict]) -> list[dict]:
    """For each count of samples, each column's RMSE averaged over every held-out frame (each scene's mean
    weighted by its frames), with the default's ratios to the nearest fill and to the paper structure."""
    summary = []
    for n in TEST_SAMPLES:
        rs = [r for r in rows if r["samples"] == n]
        frames = sum(r["frames"] for r in rs)
        means = {k: sum(r[k] * r["frames"] for r in rs) / frames
                 for k in ("nearest", "kitti", "paper", "scattered", "learned", "default")}
        summary.append({"samples": n, "frames": frames, **means,
                        "default_vs_nearest": means["default"] / means["nearest"],
                        "default_vs_paper": means["default"] / means["paper"]})
    return summary


def write(scenes: dict, rooms: list, args, rows: list) -> Path:
    """Fit on every scene, fit the predictive std to the same draws, write the weights file."""
    from crfdepth.weights import write_weights
    from train.calibrate import fit_predictive_std

    draws = training_draws([s for frames in scenes.values() for s in frames], args.repeats) + rooms
    model = fit(draws, args)
    std_terms = fit_predictive_std(model, draws)
    values = {"alpha": model.alpha, "beta": model.beta, "gamma": model.gamma, "delta": model.delta,
              "sigma_d": model.sigma_d, "sigma_n": model.sigma_n, "sigma_p": model.sigma_p,
              "confidence": model.confidence, "refine_prior": model.refine_prior}
    config = CRFConfig.build(STRUCTURE, **{k: float(v.detach()) for k, v in values.items()},
                             std_terms={k: float(v) for k, v in std_terms.items()}).groups()
    about = {"recipe": "python benchmarks/nyu_weights.py " + " ".join(
        f"--{k} {getattr(args, k)}" for k in ("epochs", "repeats", "lr", "rooms")) + " --write FILE",
        "trained_on": {k: [s.name for s in v] for k, v in scenes.items()}, "leave_one_scene_out": rows}
    return write_weights(args.write, config, about)


if __name__ == "__main__":
    sys.exit(sa.run_script(main, "nyu_weights.py"))
