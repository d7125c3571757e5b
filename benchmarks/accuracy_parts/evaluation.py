"""The evaluation of each protocol: metrics, uncertainty and speed per method, and the
sub-sampling study.

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
"""

from __future__ import annotations

import itertools
import statistics
from collections.abc import Callable

import numpy as np
import torch

from crfdepth.metrics import ause, average_metrics, depth_metrics, reliability, uncertainty_metrics
from crfdepth.model import CRFDepth

from .fits import FIT_SOURCE, get_fit, posterior_view
from .methods import CRF_METHODS, LEARNED_ABLATIONS, PRETRAINED, method_config, predict
from .protocols import INDOOR_PROTOCOLS, PROTOCOLS, batch, ensure_targets, load_group

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


def log10_error(depth: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """(1,) mean |log10 depth - log10 target| over the target pixels (the paper's Table 4 reports it)."""
    mask = target > 0
    return (depth[mask].double().log10() - target[mask].double().log10()).abs().mean().reshape(1).cpu()


def evaluate_protocol(key: str, args, fits: dict, log: Callable[[str], None]) -> tuple[list[dict], dict]:
    """Rows (one per method) of protocol ``key`` and its mean sparsification curves."""
    groups = PROTOCOLS[key][1]
    methods = list(args.methods) + (list(LEARNED_ABLATIONS) if args.learn_ablations and key == "a" else [])
    per = {m: {"metrics": [], "seconds": [], "unc": {}, "bins": []} for m in methods}
    curves: dict = {}
    fit_note = {}
    for group, layout, folder, options in groups:
        frames = load_group(args.kitti_root, layout, folder, options, args.max_frames,
                            targets_root=ensure_targets(args) if layout == "sequence" else None,
                            nyu_root=args.nyu_root)
        models = {m: CRFDepth(**method_config(m)).to(args.device) for m in args.methods
                  if m in CRF_METHODS and m != "learned" and m not in PRETRAINED}
        models.update({m: CRFDepth.from_pretrained(**PRETRAINED[m]).to(args.device) for m in args.methods
                       if m in PRETRAINED})
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
                per[m]["metrics"].append({**depth_metrics(depth, target), "log10": log10_error(depth, target)})
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
                  for lo, hi in itertools.pairwise(DEPTH_BINS_M)]
        # pooled over the protocol's target pixels: RMSE within each bin and its share of all squared error
        row["depth_bins"] = {lab: {"pixels": int(n), "rmse_mm": float(np.sqrt(e / max(n, 1)) * 1000.0),
                                   "share_of_squared_error": float(e / max(se.sum(), 1e-12))}
                             for lab, e, n in zip(labels, se, count)}
        sec = statistics.median(per[m]["seconds"])
        row.update(seconds_median=sec, fps_median=1.0 / sec, device=args.device, batch_size=1,
                   threads=torch.get_num_threads(), size=f"{w}x{h}")
        if m in LEARNED_ABLATIONS:
            row["config"] = _as_json(LEARNED_ABLATIONS[m])
            row["fit"] = (f"weights learned for this configuration by the shipped recipe on its "
                          f"{fits[('recipe', m)]['frames']} frames (drive 0060, object frames; both hold-outs)")
            row["weights"] = fits[("recipe", m)]["weights"]
        elif m in PRETRAINED:
            row["config"] = f"CRFDepth.from_pretrained({', '.join(f'{k}={v}' for k, v in PRETRAINED[m].items())})"
            if m == "default" and key in INDOOR_PROTOCOLS:
                row["fit"] = ("in-sample: its indoor regime (--weights nyu) was fitted on these frames; "
                              "benchmarks/nyu_weights.py scores it on held-out scenes")
        elif m in CRF_METHODS:
            row["config"] = _as_json(method_config(m))
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


def _as_json(config: dict) -> dict:
    """A model configuration as it is written to the JSON line (tuples as lists)."""
    return {k: (list(v) if isinstance(v, tuple) else v) for k, v in config.items()}


def subsampling(args, log) -> list[dict]:
    """RMSE of the hand-set weights and NN on protocol b for every keep fraction."""
    rows = []
    model = CRFDepth().to(args.device)
    for frac in args.fractions:
        res = {"paper": [], "nn": []}
        for group, layout, folder, options in PROTOCOLS["b"][1]:
            for s in load_group(args.kitti_root, layout, folder, options, args.subsample_frames, frac):
                image, sparse, target, K = batch(s, args.device)
                for m, items in res.items():
                    depth, *_ = predict(m, model if m == "paper" else None, image, sparse, K, args.device)
                    items.append(depth_metrics(depth, target))
        for m, items in res.items():
            stacked = {k: torch.cat([d[k] for d in items]) for k in items[0]}
            avg = average_metrics(stacked)
            rows.append({"study": "subsampling", "protocol": "b", "method": m, "keep_fraction": frac,
                         "frames": len(items), "rmse": avg["rmse"], "mae": avg["mae"]})
        log(f"  keep {frac:.0%}: paper {rows[-2]['rmse']:.0f} mm, nn {rows[-1]['rmse']:.0f} mm")
    return rows
