"""How far the shipped model's depth is from the fully converged solution of the same pipeline.

The model is ``CRFDepth.from_pretrained("kitti")`` as shipped: float32, its solves stopped at the configured
``rtol`` (1e-5). The reference is the same model (same configuration and weights) converted to float64
(``model.double()``, inputs in float64) with every solve run to ``--rtol`` (default 1e-10) within ``--max-iter``
(default 20000) iterations: ``CRFDepth(model.config, rtol=..., max_iter=...)``, the constructor's ``rtol`` and
``max_iter`` being ``model.solve_settings``' (a :class:`crfdepth.linalg.diagnostics.SolverSettings` derived from
``model.settings.solver``). Whether each reference solve reached its tolerance (``SolveInfo.converged``) is
reported; so is the reference's own error, the largest difference between it and a second reference at
``--rtol / 100``. Every forward runs under ``torch.inference_mode()``.

Frames: every frame of ``depth_selection/val_selection_cropped`` under ``--kitti-root`` (default
``../shared/data/kitti`` next to the repository; the sample has two, 1216 x 352), each on its own; the built-in
synthetic street ``make_scene(0)``, with a note, when that is absent. ``--crop HEIGHT WIDTH`` takes the
bottom-centre window of each frame instead (``K`` following it).

Per frame, of ``|depth - reference|`` in metres: the largest, the 99th percentile and the share of pixels more
than 5 cm off, over all pixels and over the pixels with ground truth (``target > 0``); the RMSE (mm,
:func:`crfdepth.metrics.depth_metrics`) of the shipped depth and of the reference against the ground truth;
the CG iterations of each solve of both. CPU, ``--threads`` (default 2) torch threads. Prints a table, then one
JSON line.

    python benchmarks/converged.py [--threads 2] [--rtol 1e-10] [--max-iter 20000] [--crop HEIGHT WIDTH]
                                   [--kitti-root PATH]
"""

from __future__ import annotations

import json
import sys
import time
import warnings
from pathlib import Path

import numpy as np
import torch

from crfdepth.data.sample import Sample
from crfdepth.errors import ConvergenceWarning
from crfdepth.metrics import depth_metrics
from crfdepth.model import CRFDepth

if str(Path(__file__).resolve().parent) not in sys.path:  # a load by the file's path (the tests) has not
    sys.path.append(str(Path(__file__).resolve().parent))

import script_args as sa  # noqa: E402  (benchmarks/script_args.py: one-line errors, checked option types)
from train_step import DEFAULT_ROOT, load_samples  # noqa: E402  (benchmarks/train_step.py: the frames, cropped)

OFF_M = 0.05  # a pixel "off": more than 5 cm from the reference
CHECK_FACTOR = 100.0  # the reference's own error: against a second reference at rtol / CHECK_FACTOR


def reference_model(model: CRFDepth, rtol: float, max_iter: int) -> CRFDepth:
    """``model`` (its configuration and weights) in float64 with every solve run to ``rtol`` within ``max_iter``
    iterations, in eval mode; ``model`` is left as it was."""
    reference = CRFDepth(model.config, rtol=rtol, max_iter=max_iter)
    reference.load_state_dict(model.state_dict())
    return reference.double().eval()


def run(model: CRFDepth, sample: Sample, dtype: torch.dtype) -> tuple[torch.Tensor, list, float]:
    """(1, 1, H, W) depth in metres of ``model`` on ``sample`` in ``dtype``, its solves' ``SolveInfo`` and the
    forward's seconds; a solve short of its tolerance is reported by the caller from the infos, not warned."""
    with torch.inference_mode(), warnings.catch_warnings():
        warnings.simplefilter("ignore", ConvergenceWarning)
        start = time.perf_counter()
        out = model(sample.image[None].to(dtype), sample.sparse[None].to(dtype), sample.K.to(dtype))
        seconds = time.perf_counter() - start
    return out.depth, out.info, seconds


def differences(depth: torch.Tensor, reference: torch.Tensor, target: torch.Tensor) -> dict:
    """Of ``|depth - reference|`` (metres; both (..., H, W) depth in metres), over all pixels and over those with
    ``target > 0`` (``gt_``): the largest (``max_m``), the 99th percentile (``p99_m``) and the share of pixels
    more than 5 cm off (``over_5cm``); None over the ground truth when ``target`` has none."""
    diff = (depth.detach().double() - reference.detach().double()).abs().cpu().numpy().ravel()
    on_target = diff[(target.detach() > 0).cpu().numpy().ravel()]
    out = {}
    for prefix, values in (("", diff), ("gt_", on_target)):
        empty = values.size == 0
        out[f"{prefix}max_m"] = None if empty else float(values.max())
        out[f"{prefix}p99_m"] = None if empty else float(np.percentile(values, 99))
        out[f"{prefix}over_5cm"] = None if empty else float((values > OFF_M).mean())
    out["gt_pixels"] = int(on_target.size)
    return out


def solves(infos: list) -> dict:
    """Iterations, relative residuals and convergence of each solve (max over the batch's graphs)."""
    return dict(iterations=[int(i.iterations.max()) for i in infos],
                rel_residual=[float(i.rel_residual.max()) for i in infos],
                converged=all(bool(i.converged.all()) for i in infos), rtol=infos[0].rtol if infos else None)


def measure(model: CRFDepth, sample: Sample, rtol: float, max_iter: int) -> dict:
    """One frame's row: the shipped depth against the converged reference (:func:`differences`), the reference's
    own error, the RMSE of both against the ground truth, and the solves of each."""
    depth, infos, seconds = run(model, sample, torch.float32)
    reference, ref_infos, ref_seconds = run(reference_model(model, rtol, max_iter), sample, torch.float64)
    tighter, check_infos, _ = run(reference_model(model, rtol / CHECK_FACTOR, max_iter), sample, torch.float64)
    row = dict(frame=sample.name, size=list(sample.size), **differences(depth, reference, sample.target))
    row["reference_error_m"] = float((reference - tighter).abs().max())
    if row["gt_pixels"]:
        row["rmse_mm"] = float(depth_metrics(depth, sample.target[None])["rmse"][0])
        row["reference_rmse_mm"] = float(depth_metrics(reference, sample.target[None])["rmse"][0])
    else:
        row["rmse_mm"] = row["reference_rmse_mm"] = None
    row["default"] = dict(solves(infos), ms=1e3 * seconds, dtype="float32")
    row["reference"] = dict(solves(ref_infos), ms=1e3 * ref_seconds, dtype="float64", max_iter=max_iter)
    row["check"] = dict(solves(check_infos), dtype="float64")
    return row


def _m(value: float | None, scale: float = 1.0, digits: int = 3) -> str:
    return "-" if value is None else f"{value * scale:.{digits}f}"


def print_table(rows: list[dict]) -> None:
    print(f"{'frame':<62} {'max m':>7} {'p99 m':>7} {'>5cm':>6} | {'gt max':>7} {'gt p99':>7} {'gt >5cm':>7} | "
          f"{'RMSE mm':>8} {'ref RMSE':>8}")
    for r in rows:
        print(f"{r['frame'][:62]:<62} {_m(r['max_m']):>7} {_m(r['p99_m']):>7} {_m(r['over_5cm'], 100, 1) + '%':>6} | "
              f"{_m(r['gt_max_m']):>7} {_m(r['gt_p99_m']):>7} {_m(r['gt_over_5cm'], 100, 1) + '%':>7} | "
              f"{_m(r['rmse_mm'], 1, 1):>8} {_m(r['reference_rmse_mm'], 1, 1):>8}")
    for r in rows:
        d, ref, check = r["default"], r["reference"], r["check"]
        print(f"{r['frame']}: shipped float32 rtol {d['rtol']:g}: iterations {d['iterations']} ({d['ms']:.0f} ms); "
              f"reference float64 rtol {ref['rtol']:g}: iterations {ref['iterations']}, relative residuals "
              f"{', '.join(f'{v:.1e}' for v in ref['rel_residual'])}, converged {ref['converged']} ({ref['ms']:.0f} ms); "
              f"its own error against rtol {check['rtol']:g} (converged {check['converged']}): "
              f"{r['reference_error_m']:.2e} m")


def main(argv: list[str] | None = None) -> int:
    parser = sa.ScriptParser(prog="converged.py", description=__doc__.split("\n\n")[0])
    parser.add_argument("--threads", type=sa.count(1, sa.MAX_THREADS), default=2, help="torch CPU threads")
    parser.add_argument("--rtol", type=sa.share(meaning="the reference's relative residual"), default=1e-10,
                        help="tolerance of the reference's solves")
    parser.add_argument("--max-iter", type=sa.count(1), default=20000, help="iteration budget of each reference solve")
    parser.add_argument("--crop", type=sa.count(8, 4096, "pixels"), nargs=2, default=None,
                        metavar=("HEIGHT", "WIDTH"), help="compare on each frame's bottom-centre window")
    parser.add_argument("--kitti-root", type=sa.folder("the KITTI sample folder"), default=DEFAULT_ROOT)
    args = parser.parse_args(argv)
    torch.set_num_threads(args.threads)
    crop = None if args.crop is None else (int(args.crop[0]), int(args.crop[1]))
    samples, note = load_samples(args.kitti_root, crop, count=None)
    if note:
        print(f"note: {note}")
    model = CRFDepth.from_pretrained("kitti")
    rows = [measure(model, s, args.rtol, args.max_iter) for s in samples]
    print(f"shipped model (float32, rtol {model.solve_settings.rtol:g}) against its float64 solution at rtol "
          f"{args.rtol:g}, {args.threads} threads" + (f", crop {crop[0]} x {crop[1]} (HxW)" if crop else ""))
    print_table(rows)
    unconverged = [r["frame"] for r in rows if not r["reference"]["converged"]]
    if unconverged:
        print(f"warning: the reference did not reach rtol {args.rtol:g} within {args.max_iter} iterations on "
              f"{', '.join(unconverged)}: raise --max-iter")
    print(json.dumps(dict(frames=rows, synthetic=note is not None, crop=None if crop is None else list(crop),
                          threads=args.threads, rtol=args.rtol, max_iter=args.max_iter, shipped_rtol=model.solve_settings.rtol,
                          off_m=OFF_M, torch=torch.__version__)))
    return 0


if __name__ == "__main__":
    sys.exit(sa.run_script(main, "converged.py"))
