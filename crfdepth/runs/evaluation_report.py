"""The report of an evaluation (``crfdepth evaluate``, :mod:`crfdepth.runs.evaluation`): the summary of the
per-frame metrics (docs/design.md section 7), the table of their means and the per-frame CSV."""

from __future__ import annotations

import csv
import io
import math
from typing import Any

import numpy as np

from crfdepth.metrics import METRICS, UNCERTAINTY_METRICS, UNITS, average_uncertainty

__all__ = ["UNCERTAINTY_UNITS", "csv_text", "format_table", "summarize"]

_LABELS = {"rmse": "RMSE", "mae": "MAE", "irmse": "iRMSE", "imae": "iMAE", "rel": "REL", "delta1": "d<1.25"}
_DECIMALS = {"rmse": 2, "mae": 2, "irmse": 3, "imae": 3, "rel": 4, "delta1": 4}
# Units of the --std columns: errors and std in metres, AUSE scaled to mm like RMSE.
UNCERTAINTY_UNITS = {"ause": "mm", "ause_random": "mm", "ause_ratio": "", "spearman": "", "coverage_1": "",
                     "coverage_2": "", "nll": "nats (errors in metres)", "nll_laplace": "nats (errors in metres)"}


def summarize(rows: list[dict[str, Any]], with_std: bool) -> dict[str, Any]:
    """The per-frame mean of each metric over ``rows``, the frames and the ground-truth pixels; with ``with_std``
    also the ``uncertainty`` block (:func:`crfdepth.metrics.average_uncertainty`, nan as None)."""
    means = {m: float(np.mean([r[m] for r in rows])) for m in METRICS}
    summary = {"metrics": means, "frames": len(rows), "pixels": int(sum(r["pixels"] for r in rows))}
    if with_std:
        means = average_uncertainty([{m: r[m] for m in UNCERTAINTY_METRICS} for r in rows])
        summary["uncertainty"] = {m: _json_number(v) for m, v in means.items()}
    return summary


def _json_number(value: float) -> float | None:
    """``value``, or None (JSON null) for nan: strict JSON has no NaN."""
    return None if math.isnan(value) else value


def format_table(summary: dict[str, Any]) -> str:
    """The stdout table: one line per metric (per-frame mean, KITTI units), frames, pixels;
    then, when ``summary`` has an ``uncertainty`` block, one line per uncertainty metric."""
    lines = [f"KITTI depth-completion metrics, mean over {summary['frames']} frame(s) "
             f"(per-frame metrics over {summary['pixels']:,} ground-truth pixels):"]
    for m in METRICS:
        value = summary["metrics"][m]
        lines.append(f"  {_LABELS[m]:<7}{value:>12.{_DECIMALS[m]}f}  {UNITS[m]}".rstrip())
    if "uncertainty" in summary:
        u = {k: (math.nan if v is None else v) for k, v in summary["uncertainty"].items()}
        lines += [
            f"Uncertainty of the predicted std, mean over {summary['frames']} frame(s):",
            f"  {'AUSE':<22}{u['ause']:>10.2f}  mm ({u['ause_ratio']:.2f} x random, {u['ause_random']:.2f} mm)",
            f"  {'Spearman(std, |err|)':<22}{u['spearman']:>10.4f}",
            f"  {'within 1 std':<22}{u['coverage_1']:>10.4f}  (Gaussian 0.683)",
            f"  {'within 2 std':<22}{u['coverage_2']:>10.4f}  (Gaussian 0.954)",
            f"  {'NLL Gaussian':<22}{u['nll']:>10.4f}  nats (errors in metres)",
            f"  {'NLL Laplace':<22}{u['nll_laplace']:>10.4f}  nats (errors in metres)",
        ]
    return "\n".join(lines)


def csv_text(rows: list[dict[str, Any]], with_std: bool) -> str:
    buffer = io.StringIO()
    fields = ["name", *METRICS, "pixels", *(UNCERTAINTY_METRICS if with_std else ())]
    writer = csv.DictWriter(buffer, fieldnames=fields, lineterminator="\n")
    writer.writeheader()
    for row in rows:
        writer.writerow({k: (repr(v) if isinstance(v, float) else v) for k, v in row.items()})
    return buffer.getvalue()
