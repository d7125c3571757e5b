"""Frames per second of the training data path and of the model step (issue "Beyond one machine").

The data is the ``data:`` section of a trainer config (``--config``, default
``configs/kitti_weights.yaml``, the shipped weights' recipe: KITTI raw scans with two
hold-outs, object frames, random 320 x 896 crops, flips and LiDAR thinning), built with
:class:`train.data.CRFDataModule` exactly as ``python -m train fit`` builds it. Its KITTI
folders are re-rooted at ``--data`` (default ``../shared/data/kitti`` next to the
repository: the config's roots under ``../shared/data/kitti`` become roots under
``--data``). When ``--data`` holds no KITTI raw drive, the built-in synthetic street at
1216 x 352 (``layout: synthetic``, ``--frames`` scenes) with the config's augmentation
stands in, and a note says so.

Cases:

- ``loader``: ``train_dataloader()`` with ``num_workers`` = each of ``--workers`` (default 0
  2 4; the config's ``persistent_workers`` and collation), iterated until ``--frames``
  frames (epochs repeat as needed). ``startup_s`` is the wait for the first batch (worker
  start and the first frames); ``frames_per_s`` is over the batches after it.
- ``step``: :meth:`train.module.CRFDepthModule.training_step` (the config's ``model:``)
  plus ``backward()`` on a batch of that loader, ``--steps`` times after one warm-up;
  ``frames_per_s`` = batch size / median seconds; ``seconds_min`` is the fastest step (on a
  shared machine the least disturbed one: every step does the same work, the same CG
  iterations). No optimiser step (a few scalars: not measurable beside the solves).

The loader and the step run one after the other, so a training run whose loader has
workers overlaps the two: its frames per second are about the smaller of the two numbers
when the machine has cores for both. ``torch.set_num_threads(--threads)`` in the main
process; DataLoader workers run one thread each (PyTorch's default). Prints a table, then
one JSON line per case.

    python benchmarks/train_data.py [--config configs/kitti_weights.yaml] [--data PATH]
                                    [--workers 0 2 4] [--frames 48] [--steps 5] [--threads 2]
"""

from __future__ import annotations

import copy
import json
import statistics
import sys
import time
import warnings
from pathlib import Path
from typing import Any

import torch
import yaml

if str(Path(__file__).resolve().parent) not in sys.path:  # a load by the file's path (the tests) has not
    sys.path.append(str(Path(__file__).resolve().parent))

import script_args as sa  # noqa: E402  (benchmarks/script_args.py: one-line errors, checked option types)

REPO = Path(__file__).resolve().parent.parent
DEFAULT_CONFIG = REPO / "configs" / "kitti_weights.yaml"
DEFAULT_DATA = REPO.parent / "shared" / "data" / "kitti"
CONFIG_KITTI = "../shared/data/kitti"  # how the configs name the KITTI folder (relative to the repository)
SYNTHETIC_SIZE = dict(height=352, width=1216)


def _reroot(root: str | None, data: Path) -> str | None:
    """A config's KITTI root under ``data`` instead of ``../shared/data/kitti``; other roots unchanged."""
    if root is None or not str(root).startswith(CONFIG_KITTI):
        return root
    return str(data / str(root)[len(CONFIG_KITTI):].lstrip("/"))


def data_options(config: dict[str, Any], data: Path, frames: int) -> tuple[dict[str, Any], str]:
    """``CRFDataModule`` arguments of ``config``'s ``data:`` section on ``data``, and what the data is; the
    synthetic street with the same augmentation when ``data`` holds no KITTI raw drive."""
    options = copy.deepcopy(config.get("data") or {})
    options["root"] = _reroot(options.get("root"), data)
    for source in options.get("extra_train") or []:
        source["root"] = _reroot(source.get("root"), data)
    if options.get("layout") == "synthetic" or (data / "raw").is_dir():
        return options, f"{options.get('layout')} under {data}" if options.get("layout") != "synthetic" else "synthetic"
    print(f"note: no KITTI raw drive under {data}; using {frames} synthetic street scenes at 1216x352 "
          "with the config's augmentation")
    keep = {k: options[k] for k in ("flip", "crop", "thin", "batch_size", "shuffle") if k in options}
    return dict(layout="synthetic", train_options=dict(count=frames, seed=0, **SYNTHETIC_SIZE),
                val_options=dict(count=1, seed=1000, **SYNTHETIC_SIZE), **keep), "synthetic (no KITTI data)"


def measure_loader(options: dict[str, Any], workers: int, frames: int) -> dict[str, Any]:
    """Frames per second of ``CRFDataModule(**options, num_workers=workers).train_dataloader()``."""
    from train.data import CRFDataModule

    module = CRFDataModule(**{**options, "num_workers": workers})
    module.setup("fit")
    loader = module.train_dataloader()
    torch.manual_seed(0)  # the same frames, crops and flips in every case
    start = time.perf_counter()
    seen, first, size = 0, None, None
    while seen < frames:
        for batch in loader:
            seen += batch.image.shape[0]
            size = tuple(batch.image.shape[2:])
            if first is None:
                first = time.perf_counter()
                seen_at_first = seen
            if seen >= frames:
                break
    end = time.perf_counter()
    del loader  # stops persistent workers
    steady = seen - seen_at_first
    return dict(case="loader", workers=workers, frames=seen, dataset_frames=len(module.train_set), size=list(size),
                startup_s=first - start, seconds=end - first,
                frames_per_s=steady / (end - first) if steady and end > first else None)


def measure_step(options: dict[str, Any], model: dict[str, Any], steps: int) -> dict[str, Any]:
    """Seconds of ``training_step`` + ``backward`` of the config's module on one training batch."""
    from train.data import CRFDataModule
    from train.module import CRFDepthModule

    data = CRFDataModule(**{**options, "num_workers": 0})
    data.setup("fit")
    torch.manual_seed(0)  # the loader cases' first batch
    batch = next(iter(data.train_dataloader()))
    module = CRFDepthModule(**model).train()
    times = []
    with warnings.catch_warnings():  # self.log without a Trainer: Lightning warns and skips it
        warnings.filterwarnings("ignore", message=".*self.log.*")
        for i in range(steps + 1):
            module.zero_grad(set_to_none=True)
            start = time.perf_counter()
            loss = module.training_step(batch, 0)
            loss.backward()
            if i:
                times.append(time.perf_counter() - start)
    seconds = statistics.median(times)
    return dict(case="step", workers=None, frames=batch.image.shape[0] * steps, size=list(batch.image.shape[2:]),
                batch_size=batch.image.shape[0], names=list(batch.names), seconds=seconds, seconds_min=min(times), seconds_max=max(times),
                frames_per_s=batch.image.shape[0] / seconds, loss=float(loss.detach()))


def print_table(rows: list[dict[str, Any]]) -> None:
    head = ("case", "workers", "frames", "size", "startup s", "frames/s", "step s", "fastest s")
    print("  ".join(f"{h:>10}" for h in head))
    for r in rows:
        size = "x".join(str(v) for v in r["size"][::-1])
        startup = f"{r['startup_s']:.2f}" if "startup_s" in r else "-"
        fps = f"{r['frames_per_s']:.2f}" if r["frames_per_s"] is not None else "-"
        workers = "-" if r["workers"] is None else str(r["workers"])
        step = f"{r['seconds']:.2f}" if r["case"] == "step" else "-"
        fastest = f"{r['seconds_min']:.2f}" if r["case"] == "step" else "-"
        print("  ".join(f"{c:>10}" for c in (r["case"], workers, r["frames"], size, startup, fps, step, fastest)))


def main(argv: list[str] | None = None) -> int:
    parser = sa.ScriptParser(prog="train_data.py", description=__doc__.split("\n\n")[0])
    parser.add_argument("--config", type=sa.file("a trainer config (YAML)"), default=DEFAULT_CONFIG, help="trainer config (its data: and model:)")
    parser.add_argument("--data", type=sa.folder("the KITTI folder (raw/, object/, ...)"), default=DEFAULT_DATA, help="the KITTI folder (raw/, object/, ...)")
    parser.add_argument("--workers", type=sa.count(0, sa.MAX_WORKERS), nargs="+", default=[0, 2, 4], help="DataLoader num_workers cases")
    parser.add_argument("--frames", type=sa.count(2), default=48, help="frames per loader case")
    parser.add_argument("--steps", type=sa.count(1), default=5, help="timed training steps (after one warm-up)")
    parser.add_argument("--threads", type=sa.count(1, sa.MAX_THREADS), default=2, help="torch threads of the main process")
    args = parser.parse_args(argv)
    if args.frames < 2 or args.steps < 1 or any(w < 0 for w in args.workers):
        print("train_data.py: error: --frames: expected >= 2, --steps >= 1, --workers >= 0", file=sys.stderr)
        return 2
    try:
        config = yaml.safe_load(args.config.read_text()) or {}
    except (OSError, yaml.YAMLError) as err:
        print(f"train_data.py: error: --config: cannot read {args.config}: {' '.join(str(err).split())}", file=sys.stderr)
        return 2
    sys.path.insert(0, str(REPO))  # the train package lives beside crfdepth, not in it
    torch.set_num_threads(args.threads)
    options, what = data_options(config, args.data.resolve(), args.frames)
    rows = [measure_loader(options, w, args.frames) for w in args.workers]
    rows.append(measure_step(options, config.get("model") or {}, args.steps))
    print(f"config {args.config.name}, data {what}, {args.threads} torch threads, torch {torch.__version__}")
    print_table(rows)
    for r in rows:
        print(json.dumps(dict(config=args.config.name, data=what, threads=args.threads, **r)))
    return 0


if __name__ == "__main__":
    sys.exit(sa.run_script(main, "train_data.py"))
