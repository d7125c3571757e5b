"""Where a model's squared error against camera-view targets lies (issue 26, docs/design.md section 15).

Section 15 explains why squared error trained on camera-view targets learns to blur depth edges:
a few target pixels far from what any input can predict carry most of the squared error. This
script measures that on a recording. For every ``--every``-th frame of the block ``--frames``
of the drives under ``--raw-root`` (KITTI raw layout, read by
:class:`crfdepth.data.sequences.SequenceFrames` with the targets of ``crfdepth targets`` under
``--targets-root``), it runs the model on the frame's own scan and reports, over the target
pixels:

- ``rmse_mm``, ``mae_mm``: the model's error;
- ``top_share``: the share of the squared error carried by the ``--top`` (default 1%) of pixels
  with the largest error;
- ``far``: the share of pixels off by more than ``--far`` metres (default 3), and of those:
  ``far_nearer`` the share whose target is nearer than the prediction, ``far_own`` the share
  where the frame's own scan has a return in the pixel (the rest come from the other scans of
  the window), ``far_support1`` the share with one supporting scan (``proj_depth/support``).

Frames are full size (not cropped). The default block is drive 0060's training block (frames 0-46,
``configs/kitti_sequence.yaml``);
its targets are made under ``--targets-root`` (k = 5, LiDAR odometry, the q protocol's) when
missing. ``--weights``: ``handset`` (the shipped structure with the constructor's weights), a
name of :meth:`crfdepth.CRFDepth.from_pretrained`, or a checkpoint path. Prints a table and one
JSON line. ``--val-selection DIR`` adds the frames of KITTI's ``val_selection_cropped`` layout
against their annotation, for contrast (no support count there: ``far_support1`` is left out).

    python benchmarks/target_residuals.py [--raw-root ../shared/data/kitti/sequences]
        [--targets-root ./targets] [--frames 0 46] [--every 9] [--weights handset]
        [--val-selection ../shared/data/kitti/depth_selection/val_selection_cropped]
"""

from __future__ import annotations

import json
import sys
from dataclasses import asdict, dataclass
from pathlib import Path

import cv2
import numpy as np
import torch

from crfdepth.checkpoints import load_model
from crfdepth.cli import main as cli
from crfdepth.data.factory import build_dataset
from crfdepth.errors import InputError
from crfdepth.model import CRFDepth

# A run as a script has this folder on the path; a load from the file's path (the tests) has not.
HERE = Path(__file__).resolve().parent
if str(HERE) not in sys.path:
    sys.path.append(str(HERE))

from accuracy_parts.methods import method_config  # noqa: E402

if str(Path(__file__).resolve().parent) not in sys.path:  # a load by the file's path (the tests) has not
    sys.path.append(str(Path(__file__).resolve().parent))

import script_args as sa  # noqa: E402  (benchmarks/script_args.py: one-line errors, checked option types)

REPO = HERE.parent
DEFAULT_RAW = REPO.parent / "shared" / "data" / "kitti" / "sequences"


@dataclass
class Residuals:
    """The error of one frame's prediction over its target pixels (module docstring)."""

    pixels: int
    rmse_mm: float
    mae_mm: float
    top_share: float
    far: float
    far_nearer: float
    far_own: float
    far_support1: float | None


def residuals(prediction: np.ndarray, target: np.ndarray, own: np.ndarray, support: np.ndarray | None,
              top: float = 0.01, far_m: float = 3.0) -> Residuals:
    """(H, W) prediction, target (0 = none), the frame's own scan (0 = none) and support count (None:
    not known), in metres -> :class:`Residuals`. ``top``: the share of pixels whose squared error is summed."""
    have = target > 0
    r = prediction[have] - target[have]
    squared = np.sort(r * r)[::-1]
    n = len(squared)
    total = float(squared.sum())
    k = max(1, int(round(top * n))) if n else 0
    big = np.abs(r) > far_m

    def share(mask: np.ndarray) -> float:
        return float(mask[big].mean()) if big.any() else 0.0

    return Residuals(pixels=n, rmse_mm=1000 * float(np.sqrt(squared.mean())) if n else 0.0,
                     mae_mm=1000 * float(np.abs(r).mean()) if n else 0.0,
                     top_share=float(squared[:k].sum()) / total if total > 0 else 0.0,
                     far=float(big.mean()) if n else 0.0, far_nearer=share(r > 0),
                     far_own=share(own[have] > 0),
                     far_support1=None if support is None else share(support[have] <= 1))


def _model(weights: str) -> CRFDepth:
    if weights == "handset":  # as benchmarks/accuracy.py's hand-set: the recipe's structure, the constructor's weights
        return CRFDepth(**method_config("hand-set")).eval()
    if Path(weights).suffix in (".ckpt", ".pt"):
        return load_model(weights).eval()
    return CRFDepth.from_pretrained(weights).eval()


def _ensure_targets(raw_root: Path, targets_root: Path) -> None:
    """``crfdepth targets`` (k = 5, LiDAR odometry) for every drive under ``raw_root`` without them."""
    drives = sorted(d for day in raw_root.iterdir() if day.is_dir() for d in day.iterdir()
                    if (d / "velodyne_points" / "data").is_dir())
    for drive in drives:
        if not (targets_root / drive.name / "poses.txt").is_file():
            code = cli(["targets", "--drive", str(drive), "--out-dir", str(targets_root), "--poses", "odometry",
                        "-k", "5", "--quiet"])
            if code:
                raise SystemExit(f"--targets-root: `crfdepth targets` failed on {drive} (exit {code})")


def measure(raw_root: Path, targets_root: Path, frames: tuple[int, int], every: int, weights: str,
            top: float = 0.01, far_m: float = 3.0) -> list[tuple[str, Residuals]]:
    """One :class:`Residuals` per measured frame, named."""
    data = build_dataset("sequence", raw_root, targets_root=targets_root, frames=list(frames), offsets=[-1, 1],
                         transform=None)
    model = _model(weights)
    rows = []
    for i in range(0, len(data), every):
        sample = data[i]
        with torch.no_grad():
            depth = model(sample.image[None], sample.sparse[None], sample.K).depth[0, 0].numpy()
        drive, stem, _, camera = sample.name.rsplit("_", 3)  # <drive>_<frame>_image_0X
        path = targets_root / drive / "proj_depth" / "support" / f"image_{camera}" / f"{stem}.png"
        support = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
        if support is None:
            raise InputError(f"--targets-root: expected the support count {path}, got no such image; rerun "
                             f"`crfdepth targets`")
        rows.append((sample.name, residuals(depth, sample.target[0].numpy(), sample.sparse[0].numpy(), support,
                                            top, far_m)))
    return rows


def measure_annotated(root: Path, weights: str, top: float = 0.01, far_m: float = 3.0) -> list[tuple[str, Residuals]]:
    """The same statistics on KITTI's annotated frames (``val_selection_cropped`` layout)."""
    model = _model(weights)
    rows = []
    for sample in build_dataset("val_selection", root):
        with torch.no_grad():
            depth = model(sample.image[None], sample.sparse[None], sample.K).depth[0, 0].numpy()
        rows.append((sample.name, residuals(depth, sample.target[0].numpy(), sample.sparse[0].numpy(), None,
                                            top, far_m)))
    return rows


def main(argv: list[str] | None = None) -> int:
    parser = sa.ScriptParser(prog="target_residuals.py", description=__doc__.split("\n\n")[0])
    parser.add_argument("--raw-root", type=Path, default=DEFAULT_RAW)
    parser.add_argument("--targets-root", type=sa.out_folder, default=Path("targets"))
    parser.add_argument("--frames", type=sa.count(0), nargs=2, default=(0, 46), metavar=("FIRST", "LAST"))
    parser.add_argument("--every", type=sa.count(1), default=9)
    parser.add_argument("--weights", default="handset")
    parser.add_argument("--top", type=sa.share(meaning="share of the target pixels"), default=0.01)
    parser.add_argument("--far", type=sa.positive("metres"), default=3.0)
    parser.add_argument("--threads", type=sa.count(1, sa.MAX_THREADS), default=2)
    parser.add_argument("--val-selection", type=sa.folder("a val_selection_cropped folder"), default=None)
    args = parser.parse_args(argv)
    if not args.raw_root.is_dir():
        parser.error(f"--raw-root: expected a folder of KITTI raw drives (<date>/<drive>_sync), got {args.raw_root}")
    if args.frames[0] > args.frames[1]:
        parser.error(f"--frames: expected FIRST <= LAST, got {args.frames[0]} {args.frames[1]}")
    if args.every < 1:
        parser.error(f"--every: expected a positive integer, got {args.every}")
    if not 0 < args.top < 1:
        parser.error(f"--top: expected a share in (0, 1), got {args.top}")
    torch.set_num_threads(args.threads)
    args.targets_root.mkdir(parents=True, exist_ok=True)
    _ensure_targets(args.raw_root, args.targets_root)
    try:
        rows = measure(args.raw_root, args.targets_root, tuple(args.frames), args.every, args.weights, args.top,
                       args.far)
        if args.val_selection is not None:
            rows += measure_annotated(args.val_selection, args.weights, args.top, args.far)
    except InputError as error:
        print(f"target_residuals.py: error: {error}", file=sys.stderr)
        return 2
    print(f"weights {args.weights}; top = {args.top:.0%} of the target pixels; far = off by more than {args.far} m")
    print(f"{'frame':60s} {'pixels':>7s} {'rmse mm':>8s} {'mae mm':>7s} {'top share':>9s} {'far':>6s} "
          f"{'nearer':>6s} {'own':>5s} {'sup 1':>5s}")
    for name, r in rows:
        print(f"{name:60s} {r.pixels:7d} {r.rmse_mm:8.0f} {r.mae_mm:7.0f} {r.top_share:9.2f} {r.far:6.3f} "
              f"{r.far_nearer:6.2f} {r.far_own:5.2f} {'-' if r.far_support1 is None else f'{r.far_support1:.2f}':>5s}")
    print(json.dumps(dict(weights=args.weights, top=args.top, far_m=args.far,
                          frames=[dict(name=name, **asdict(r)) for name, r in rows])))
    return 0


if __name__ == "__main__":
    raise SystemExit(sa.run_script(main, "target_residuals.py"))
