"""``crfdepth evaluate``: KITTI metrics of a trained model over a dataset (docs/design.md section 7).

::

    crfdepth evaluate --checkpoint last.ckpt --layout val_selection \\
        --data depth_selection/val_selection_cropped [--limit N] [--std] [--save-png] [--out-dir DIR] \\
        [--batch-size B] [--workers N]

Runs :class:`~crfdepth.model.CRFDepth` (``--checkpoint`` read by
:func:`crfdepth.load_model`; without it, the shipped ``--weights``, by default
the ones learned on KITTI), in the structure stored with the weights unless ``--mode``
etc. override it (the line ``model: ...`` says which; ``--quiet`` drops it), over the
frames of ``crfdepth.data.build_dataset(--layout, --data, ...)`` under
``torch.no_grad()`` and compares the float depth with the ground truth of each frame.
The metrics are KITTI's (:func:`crfdepth.metrics.depth_metrics`): over the pixels with
ground truth > 0, RMSE and MAE in mm, iRMSE and iMAE in 1/km, REL and delta < 1.25,
computed **per frame, then averaged over frames** (the devkit's convention). The
prediction is evaluated before PNG quantisation (1/256 m).

``--workers N`` DataLoader processes (default 0: this one; every layout's dataset pickles)
read and check the frames; up to ``--batch-size B`` (default 1) consecutive frames of one
size share a model call (:func:`crfdepth.runs.batches.frame_batches`). Per-frame metrics
differ from batch 1 by the solver tolerance only (measured: within 1.1e-6 relative,
delta1 equal). A frame that cannot be read or checked stops the run with its own one-line
message, the same for any ``--workers``.

With ``--std`` the model also returns its predicted standard deviation (``CRFDepth(...,
return_std=True)``; slower, above all in pixel mode) and each frame gets the uncertainty
metrics of :func:`crfdepth.metrics.uncertainty_metrics` (docs/design.md section 5) over
the same ground-truth pixels, with ``error = depth - target`` and the std in metres:
``ause`` and ``ause_random`` in **mm** (like RMSE), ``ause_ratio`` (their ratio, 0 =
perfect ranking, 1 = random), ``spearman`` (rank correlation of std and ``|error|``),
``coverage_1`` / ``coverage_2`` (share of ``|error| <= 1 / 2 std``; 0.683 / 0.954 if
calibrated), ``nll`` and ``nll_laplace`` (mean Gaussian / Laplace negative log-likelihood
in **nats, with errors in metres**). A metric that is undefined for a frame (the Spearman
of a constant std, the ratio when every ``|error|`` is equal) is nan.

Output: a table on stdout (the per-frame mean of each metric, the number of frames and
of ground-truth pixels; with ``--std`` then one line per uncertainty metric) and, in
``--out-dir`` (default ``./evaluation``, created if missing):

- ``per_frame.csv``: one row per frame: ``name`` and every metric (``rmse`` ... ``delta1``
  in the units above, ``pixels`` the frame's ground-truth pixels), with ``--std`` followed
  by ``ause`` ... ``nll_laplace`` in the units above (``nan`` where undefined);
- ``summary.json``: the mean metrics and their units, frames, pixels, the checkpoint
  path (or the shipped weight set's name), layout, data root and dataset options, the model configuration
  (``CRFDepth.config``), the learned weights (``CRFDepth.weights()``), dtype and device;
  with ``--std`` also an ``uncertainty`` block, the per-frame mean of each uncertainty
  metric (:func:`crfdepth.metrics.average_uncertainty`: ``ause_ratio`` is recomputed as
  mean ``ause`` / mean ``ause_random``, as a benchmark table reports it; ``null`` where
  undefined), and their units in ``units``;
- with ``--save-png``: ``depth/<frame name>.png``, the prediction as a KITTI depth PNG
  (uint16, metres * 256, clipped below at 1/256 m), named like the frames (for
  ``val_selection``, the ``velodyne_raw`` file names the benchmark devkit expects).

Every check that needs no computation comes first (options, data folder and layout,
output folder, checkpoint), so bad input exits with status 2 and a one-line message
before anything is written. The output folder is locked for the run (``.crfdepth.lock``,
:func:`crfdepth.runs.outputs.output_folders`): a second run into it is refused naming the
first. The CSV and JSON are written atomically at the end, so a run
that fails midway leaves neither (PNGs written before the failure stay). Frames with
ground truth but no ground-truth pixel (possible after a crop) are skipped with a
warning and listed in the summary. The ``test_selection`` layout has no ground truth:
for benchmark submissions use ``crfdepth complete --input-dir DIR --out-dir OUT``.

NYU Depth v2 (docs/rgbd.md): ``--layout nyu_sync`` (``rgb_XXXXX.jpg`` + ``sync_depth_XXXXX.png``), ``nyu_raw``
(``images.png`` + ``rawdepth.png`` + ``depth.png``) or ``nyu_h5`` (the Sparse-to-Dense HDF5 release; needs h5py).
``--samples N`` applies the published protocol (:func:`crfdepth.data.sampling.nyu_protocol`: resize to 320x240,
centre crop 304x228, N pixels of the ground truth drawn as the input with ``--seed``, default 0); without it the
frames are evaluated as stored (``nyu_raw``: the raw depth's holes filled, scored against the filled depth), except
``nyu_sync``, whose target is its input, which requires ``--samples``. The model runs with the occlusion gate off
(registered depth, :func:`~crfdepth.cli.model_options.build_model`), and the table is followed by the three
numbers as NYU papers report them: RMSE in metres, REL and delta < 1.25 (also ``nyu`` in ``summary.json``).
``--samples`` larger than a frame's valid ground-truth pixels stops the run naming ``--samples`` and the frame.

Needs no Lightning: a machine with the crfdepth library alone can evaluate a ``.ckpt``.
"""

from __future__ import annotations

import argparse
import contextlib
import functools
import json
import logging
import os
import time
from pathlib import Path
from typing import Any

import torch
from torch.utils.data import Subset

from crfdepth.checkpoints import describe
from crfdepth.cli.arguments import MAX_RINGS, add_batch_arguments, fraction, int_at_least, seed_type
from crfdepth.cli.completion import cli_advice
from crfdepth.cli.model_options import add_model_arguments, build_model, model_maker
from crfdepth.cli.progress import FrameBars
from crfdepth.data.factory import LAYOUTS, build_dataset
from crfdepth.errors import InputError
from crfdepth.metrics import UNITS
from crfdepth.runs.evaluation import EvaluationRun, evaluate_dataset
from crfdepth.runs.evaluation_report import UNCERTAINTY_UNITS, csv_text, format_table, summarize
from crfdepth.runs.outputs import is_inside, output_folders, same_file, write_files
from crfdepth.runs.ranks import Ranks, Spread, run_in_group
from crfdepth.weights import DEFAULT_WEIGHTS

logger = logging.getLogger(__name__)

CSV_NAME = "per_frame.csv"
# How crfdepth.data.sampling.SparseSamples refuses a frame with fewer valid pixels than asked for.
_SAMPLES_REFUSAL = "samples: expected"
JSON_NAME = "summary.json"
PNG_FOLDER = "depth"

# The NYU Depth v2 layouts (registered depth: the model's occlusion gate off; RMSE also in metres).
NYU_LAYOUTS = tuple(layout for layout in LAYOUTS if layout.startswith("nyu_"))
# Dataset options: command-line flag -> (build_dataset keyword, layouts that take it).
_DATASET_OPTIONS = {
    "--split": ("split", ("depth_completion", "nyu_h5")),
    "--holdout": ("holdout", ("raw", "object")),
    "--holdout-fraction": ("holdout_fraction", ("raw", "object")),
    "--keep-every-ring": ("keep_every_ring", ("raw", "object")),
    "--seed": ("seed", ("raw", "object", "synthetic", *NYU_LAYOUTS)),
    "--samples": ("samples", NYU_LAYOUTS),
    "--targets-root": ("targets_root", ("sequence",)),
}


HELP = "KITTI (and NYU Depth v2) metrics of a checkpoint over a dataset (table, per-frame CSV, summary JSON)"
DESCRIPTION = ("Run a checkpoint (or the shipped weights) over a dataset with ground truth and "
               "report the KITTI depth-completion metrics (per-frame mean; RMSE/MAE in mm, "
               "iRMSE/iMAE in 1/km; NYU Depth v2 layouts also RMSE in m, REL and delta<1.25 as papers "
               "report them). For test-set submissions use 'crfdepth complete --input-dir'.")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """The options of ``crfdepth evaluate``."""
    data = parser.add_argument_group("data")
    data.add_argument("--layout", required=True, choices=LAYOUTS, metavar="LAYOUT",
                      help=f"dataset layout (crfdepth.data.build_dataset): {', '.join(LAYOUTS)}; test_selection "
                           "has no ground truth and is refused")
    data.add_argument("--data", metavar="DIR",
                      help="dataset folder (not needed for --layout synthetic)")
    data.add_argument("--split", choices=("train", "val"), default=None,
                      help="depth_completion: split (default: the dataset's, train); nyu_h5: split (default: "
                           "the folder's own, or both)")
    data.add_argument("--targets-root", metavar="DIR", default=None,
                      help="sequence (required): the --out-dir of 'crfdepth targets', whose camera-view targets "
                           "are the ground truth; --data is the raw root holding <date>/<drive>/")
    data.add_argument("--holdout", choices=("fraction", "rings"), default=None,
                      help="raw / object: how LiDAR points are held out as targets (default: fraction)")
    data.add_argument("--holdout-fraction", type=fraction(include_one=False), default=None, metavar="F",
                      help="raw / object with --holdout fraction: share of points held out (default 0.2)")
    data.add_argument("--keep-every-ring", type=int_at_least(2, MAX_RINGS), default=None, metavar="N",
                      help="raw / object with --holdout rings: keep every N-th laser ring as input "
                           "(default 4)")
    data.add_argument("--seed", type=seed_type(), default=None, metavar="S",
                      help="raw / object: hold-out seed; synthetic: first scene; NYU layouts with --samples: "
                           "the samples' draw (default 0)")
    data.add_argument("--samples", type=int_at_least(1), default=None, metavar="N",
                      help="NYU layouts: the published protocol (resize 320x240, centre crop 304x228, N pixels "
                           "of the ground truth drawn as the input; papers use 500); required for nyu_sync, "
                           "whose target is its input; without it nyu_raw / nyu_h5 are evaluated as stored")
    data.add_argument("--limit", type=int_at_least(1), default=None, metavar="N",
                      help="evaluate only the first N frames")
    add_batch_arguments(data)
    out = parser.add_argument_group("output")
    out.add_argument("--out-dir", default="evaluation", metavar="DIR",
                     help=f"folder for {CSV_NAME}, {JSON_NAME} and {PNG_FOLDER}/ (created if missing; "
                          f"default ./evaluation)")
    out.add_argument("--std", action="store_true",
                     help="also compute the predicted standard deviation and report uncertainty metrics")
    out.add_argument("--save-png", action="store_true",
                     help=f"also write each prediction to {PNG_FOLDER}/<frame name>.png (KITTI uint16, "
                          f"metres * 256)")
    out.add_argument("--quiet", action="store_true", help="no progress bar and no 'model: ...' line")
    add_model_arguments(parser)


# --------------------------------------------------------------------------- setup


def _dataset_options(args: argparse.Namespace) -> dict[str, Any]:
    """build_dataset keywords from the options given; an option of another layout is an error."""
    options = {}
    for flag, (keyword, layouts) in _DATASET_OPTIONS.items():
        value = getattr(args, flag[2:].replace("-", "_"))
        if value is None:
            continue
        if args.layout not in layouts:
            raise InputError(f"{flag}: only applies to --layout {' / '.join(layouts)}, got --layout {args.layout}")
        options[keyword] = value
    if args.layout in NYU_LAYOUTS and args.samples is None:
        if args.layout == "nyu_sync":
            raise InputError("--samples: required with --layout nyu_sync: its ground truth is the stored depth "
                             "itself, so the input must be drawn from it (--samples 500: the published protocol)")
        if args.seed is not None:
            raise InputError(f"--seed {args.seed}: applies with --samples (it seeds their draw) for --layout "
                             f"{args.layout}")
    if args.holdout == "rings" and args.holdout_fraction is not None:
        logger.warning("--holdout-fraction is ignored with --holdout rings (it sets the share of points held out "
                       "with --holdout fraction)")
    return options


def _open_dataset(args: argparse.Namespace, options: dict[str, Any]):
    if args.layout == "test_selection":
        raise InputError("--layout test_selection: the KITTI test frames have no ground truth, so there is "
                         "nothing to evaluate; for a benchmark submission run 'crfdepth complete "
                         "--input-dir DIR --out-dir OUT'")
    if args.layout == "sequence" and "targets_root" not in options:
        raise InputError("--targets-root: required with --layout sequence (the --out-dir of 'crfdepth targets', "
                         "whose camera-view targets are scored)")
    if args.layout == "synthetic":
        if args.data is not None:
            logger.warning("--data %s is not used by --layout synthetic; ignored", args.data)
        root = None
    else:
        if args.data is None:
            raise InputError(f"--data: a dataset folder is needed for --layout {args.layout}")
        root = Path(args.data)
    try:
        dataset = build_dataset(args.layout, root, **options)
    except (InputError, FileNotFoundError) as exc:
        where = f"--data {root} (--layout {args.layout})" if root is not None else f"--layout {args.layout}"
        raise type(exc)(f"{where}: {exc}") from None
    if len(dataset) == 0:
        raise InputError(f"--data {root} (--layout {args.layout}): no frames to evaluate")
    if args.limit is not None and args.limit < len(dataset):
        dataset = Subset(dataset, range(args.limit))
    return dataset, root


def _check_out_dir(args: argparse.Namespace, root: Path | None) -> Path:
    """The output folder: not a file, not the data folder, writable where it exists."""
    out_dir = Path(args.out_dir)
    if out_dir.exists() and not out_dir.is_dir():
        raise InputError(f"--out-dir: expected a folder, got a file: {out_dir}")
    if root is not None and os.path.realpath(out_dir) == os.path.realpath(root):
        raise InputError(f"--out-dir: {out_dir} is the --data folder; refusing to write there")
    for flag, folder in (("--data", root), ("--targets-root", args.targets_root)):
        if folder is not None and (same_file(out_dir, folder) or is_inside(out_dir, folder)):
            raise InputError(f"--out-dir: {out_dir} is or lies inside the {flag} folder {folder}; refusing to write "
                             f"among the inputs, choose a folder outside it")
    existing = next((p for p in (out_dir, *out_dir.parents) if p.exists()), Path("."))
    if not os.access(existing, os.W_OK | os.X_OK):
        raise PermissionError(f"--out-dir: cannot create or write {out_dir} ({existing} is not writable)")
    return out_dir


def _atomic_write_text(path: Path, text: str) -> None:
    write_files([("--out-dir", path, text.encode("utf-8"))])


# --------------------------------------------------------------------------- entry point


def run(args: argparse.Namespace) -> int:
    """Evaluate as ``args`` asks; print the table; write the CSV and JSON; return 0.

    Bad input raises InputError / FileNotFoundError / PermissionError naming the option
    or file, which ``crfdepth.cli.main`` turns into exit status 2 and a one-line message.
    As ranks of a group (``--num-nodes`` under torchrun, ``--strategy ddp``), rank 0 opens, checks and locks,
    the ranks evaluate the runs of frames dealt to them, and rank 0 merges their rows and writes the report
    (:mod:`crfdepth.runs.ranks`, :func:`crfdepth.runs.evaluation.evaluate_dataset`).
    """
    argv = getattr(args, "argv", None)
    spread = Spread(args.devices, args.num_nodes, args.strategy, args.device, tuple(argv) if argv is not None else None)
    return run_in_group(spread, functools.partial(_run, args, spread))


def _run(args: argparse.Namespace, spread: Spread, ranks: Ranks | None) -> int:
    built: dict = {}
    run = EvaluationRun(make_model=model_maker(args, args.layout in NYU_LAYOUTS), batch_size=args.batch_size,
                        workers=args.workers, std=args.std, quiet=args.quiet, spread=spread, memory_advice=functools.partial(cli_advice, args.device),
                        progress=FrameBars())
    with contextlib.ExitStack() as stack:
        prepared = _prepare(args, stack, built) if ranks is None else \
            ranks.share(lambda: _prepare(args, stack, built))
        options, dataset, root, out_dir, png_dir = prepared
        start = time.perf_counter()
        try:
            rows, skipped = evaluate_dataset(built.get("model"), dataset, run, png_dir, ranks)
        except InputError as exc:  # a frame with fewer valid pixels than --samples: the dataset names "samples"
            if args.samples is None or _SAMPLES_REFUSAL not in str(exc):
                raise
            raise InputError(str(exc).replace(_SAMPLES_REFUSAL, f"--samples {args.samples}: expected", 1)) from None
        if ranks is None or ranks.is_main:
            return _write_report(args, options, dataset, root, built["model"], out_dir, png_dir, rows, skipped,
                                 time.perf_counter() - start)
    return 0


def _prepare(args: argparse.Namespace, stack: contextlib.ExitStack, built: dict) -> tuple:
    """The dataset opened, the output folder checked, the model built (kept in ``built``), the folder created
    and locked for the run (``.crfdepth.lock``, on ``stack``) and the PNG folder made: what the ranks share."""
    options = _dataset_options(args)
    dataset, root = _open_dataset(args, options)
    out_dir = _check_out_dir(args, root)
    built["model"] = build_model(args, args.layout in NYU_LAYOUTS)  # the model line: after every refusal of the options
    stack.enter_context(output_folders([("--out-dir", args.out_dir)]))
    png_dir = None
    if args.save_png:
        png_dir = out_dir / PNG_FOLDER
        png_dir.mkdir(parents=True, exist_ok=True)
    return options, dataset, root, out_dir, png_dir


def _write_report(args: argparse.Namespace, options: dict, dataset, root: Path | None, model, out_dir: Path,
                  png_dir: Path | None, rows: list, skipped: list, seconds: float) -> int:
    """Print the table and write the CSV and JSON of the evaluated ``rows``."""
    if not rows:
        raise InputError(f"none of the {len(dataset)} frame(s) has a ground-truth pixel; nothing to evaluate")

    summary = summarize(rows, args.std)
    with torch.no_grad():  # plain numbers (no autograd warning from float() of a parameter)
        weights = model.weights()
    summary.update({
        "units": {**UNITS, **(UNCERTAINTY_UNITS if args.std else {})},
        "averaging": "per-frame metrics over ground-truth pixels (> 0), then the mean over frames (KITTI)"
                     + ("; uncertainty likewise, except ause_ratio = mean ause / mean ause_random" if args.std else ""),
        "skipped": skipped,
        "checkpoint": str(Path(args.checkpoint).resolve()) if args.checkpoint is not None else None,
        "shipped_weights": (args.weights or DEFAULT_WEIGHTS) if args.checkpoint is None else None,
        "layout": args.layout,
        "data_root": str(root.resolve()) if root is not None else None,
        "dataset_options": options,
        "limit": args.limit,
        "model_config": dict(model.config),
        "weights": weights,
        "dtype": args.dtype,
        "device": args.device,
        "seconds": seconds,
        "png_dir": str(png_dir.resolve()) if png_dir is not None else None,
    })
    if args.layout in NYU_LAYOUTS:  # the numbers as NYU papers report them (per-frame means, RMSE in metres)
        metrics = summary["metrics"]
        summary["nyu"] = {"rmse_m": metrics["rmse"] / 1000.0, "rel": metrics["rel"], "delta1": metrics["delta1"],
                          "samples": args.samples}
    out_dir.mkdir(parents=True, exist_ok=True)
    _atomic_write_text(out_dir / CSV_NAME, csv_text(rows, args.std))
    _atomic_write_text(out_dir / JSON_NAME, json.dumps(summary, indent=2) + "\n")

    source = args.checkpoint if args.checkpoint is not None else f"{args.weights or DEFAULT_WEIGHTS} weights"
    data = f"{args.layout} {root}" if root is not None else args.layout
    print(f"crfdepth evaluate: {source} on {data}, {describe(model)}, {args.dtype}")
    print(format_table(summary))
    if "nyu" in summary:
        nyu = summary["nyu"]
        print(f"NYU Depth v2 as papers report it: RMSE {nyu['rmse_m']:.4f} m, REL {nyu['rel']:.4f}, "
              f"delta<1.25 {nyu['delta1']:.4f}"
              + (f" ({args.samples} samples, seed {options.get('seed', 0)})" if args.samples is not None else
                 " (the stored input, no --samples)"))
    if skipped:
        print(f"skipped {len(skipped)} frame(s) without ground-truth pixels (listed in {JSON_NAME})")
    print(f"wrote {out_dir / CSV_NAME} and {out_dir / JSON_NAME}"
          + (f"; predictions in {png_dir}/" if png_dir is not None else ""))
    logger.info("evaluated %d frame(s) in %.1f s (%.2f s/frame)", len(rows), seconds, seconds / len(rows))
    return 0
