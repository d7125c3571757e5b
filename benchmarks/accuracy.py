"""Accuracy, uncertainty and speed of crfdepth on the real KITTI sample frames (issue 6).

Frames come from ``--kitti-root`` (default ``../shared/data/kitti`` next to this
repository), through :func:`crfdepth.data.factory.build_dataset`, all 1216 x 352. The
protocols, methods, metrics and report are documented in the modules of
``accuracy_parts/`` beside this file: ``protocols.py``, ``methods.py``, ``fits.py``,
``evaluation.py``, ``report.py``.

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
import sys
import time
from collections.abc import Sequence
from pathlib import Path

import torch

# A run as a script has this folder on the path; a load from the file's path (the tests) has not.
HERE = Path(__file__).resolve().parent
if str(HERE) not in sys.path:
    sys.path.append(str(HERE))

from accuracy_parts import evaluation, methods, protocols, report

if str(Path(__file__).resolve().parent) not in sys.path:  # a load by the file's path (the tests) has not
    sys.path.append(str(Path(__file__).resolve().parent))

import script_args as sa  # noqa: E402  (benchmarks/script_args.py: one-line errors, checked option types)

DEFAULT_ROOT = HERE.parent.parent / "shared" / "data" / "kitti"
DEFAULT_NYU_ROOT = HERE.parent.parent / "shared" / "data" / "nyu"


def parse_args(argv: Sequence[str] | None) -> argparse.Namespace:
    parser = sa.ScriptParser(prog="accuracy.py", description=__doc__.split("\n\n")[0])
    parser.add_argument("--kitti-root", type=Path, default=DEFAULT_ROOT, help="KITTI root (default: %(default)s)")
    parser.add_argument("--nyu-root", type=Path, default=DEFAULT_NYU_ROOT,
                        help="NYU Depth v2 frames of protocols n500/n200 (default: %(default)s)")
    parser.add_argument("--protocols", nargs="+", choices=list(protocols.PROTOCOLS), default=list(protocols.PROTOCOLS))
    parser.add_argument("--methods", nargs="+", choices=list(methods.METHODS), default=list(methods.METHODS))
    parser.add_argument("--max-frames", type=sa.count(1), default=None, help="frames per group (evenly spaced); default all")
    parser.add_argument("--fit-epochs", type=sa.count(1), default=None,
                        help="epochs of each learned-weight fit (default: the recipe's, configs/kitti_weights.yaml)")
    parser.add_argument("--fit-frames", type=sa.count(1), default=None, help="frames per group of each fit; default all")
    parser.add_argument("--learn-ablations", action="store_true",
                        help="protocol a: also the Table 1 ablations with weights learned per configuration by the "
                             "shipped recipe (5 more fits)")
    parser.add_argument("--fractions", type=sa.share(include_one=True, meaning="share of the LiDAR points"), nargs="+", default=[0.2, 0.4, 0.6, 0.8, 1.0])
    parser.add_argument("--subsample-frames", type=sa.count(1), default=None, help="frames per group of the sub-sampling "
                        "study (default: --max-frames)")
    parser.add_argument("--no-subsample", action="store_true", help="skip the sub-sampling study")
    parser.add_argument("--posterior-samples", type=sa.count(1, 4096), default=8,
                        help="samples of the posterior-only std (the model default is 32; 8 keeps the run short)")
    parser.add_argument("--device", type=sa.device, default="cpu")
    parser.add_argument("--threads", type=sa.count(1, sa.MAX_THREADS), default=1, help="torch CPU threads")
    parser.add_argument("--quick", action="store_true", help="smoke run: 1 frame per group, 1 fit epoch on "
                        "1 frame per group, fractions 0.5 and 1.0")
    parser.add_argument("--out-dir", type=sa.out_folder, default=Path("accuracy_results"))
    parser.add_argument("--targets-root", type=sa.out_folder, default=None,
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
        args.fit_epochs = int(methods.recipe()["trainer"]["max_epochs"])
    if args.targets_root is None:
        args.targets_root = args.out_dir / "targets"
    if args.fit_epochs < 1:
        parser.error(f"--fit-epochs: expected >= 1, got {args.fit_epochs}")
    needed = sorted({folder for key in args.protocols for _, _, folder, _ in protocols.PROTOCOLS[key][1]
                     if folder and not folder.startswith("nyu:")}
                    | ({"raw", "object/training"} if args.learn_ablations else set())
                    | (set() if args.no_subsample else {"raw", "object/training"}))
    missing = [f for f in needed if not (args.kitti_root / f).is_dir()]
    if missing:
        parser.error(f"--kitti-root: expected the folders {', '.join(needed)} under {args.kitti_root} "
                     f"(the layout of ../shared/data/kitti), missing: {', '.join(missing)}")
    nyu = sorted({folder[4:] for key in args.protocols for _, _, folder, _ in protocols.PROTOCOLS[key][1]
                  if folder and folder.startswith("nyu:")})
    missing = [f for f in nyu if not (args.nyu_root / f).is_dir()]
    if missing:
        parser.error(f"--nyu-root: expected the folders {', '.join(nyu)} under {args.nyu_root} "
                     f"(the layout of ../shared/data/nyu), missing: {', '.join(missing)}")
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
        r, c = evaluation.evaluate_protocol(key, args, fits, log)
        rows += r
        curves[key] = c
    sub_rows = [] if args.no_subsample else (log("sub-sampling study") or evaluation.subsampling(args, log))
    lines = [f"# crfdepth accuracy benchmark ({args.kitti_root})", *report.markdown_tables(rows)]
    if sub_rows:
        lines += report.subsampling_table(sub_rows)
    lines += report.verdicts(rows)
    lines.append(f"\ntotal run time {time.perf_counter() - start:.0f} s")
    text = "\n".join(lines)
    print(text)
    all_rows = rows + sub_rows
    with open(args.out_dir / "results.jsonl", "w") as fh:
        for r in all_rows:
            print(json.dumps(r))
            fh.write(json.dumps(r) + "\n")
    (args.out_dir / "results.md").write_text(text + "\n")
    for p in report.plots(args.out_dir, sub_rows, curves):
        print(f"plot: {p}")
    return all_rows


if __name__ == "__main__":
    sys.exit(sa.run_script(main, "accuracy.py"))
