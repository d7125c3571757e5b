"""Speed against accuracy: RMSE against milliseconds per frame of the classical fills and every crfdepth configuration.

Methods (the classical fills, then the configurations of ``benchmarks/speed.py``, built by its ``make_model``):

- ``nearest``: nearest-LiDAR fill, :func:`crfdepth.fill.nearest.nearest_fill`;
- ``ip-basic-opencv``: IP-Basic's original fast fill in OpenCV (``benchmarks/ip_basic_opencv.py``);
- ``ip-basic``: crfdepth's torch port of it, :func:`crfdepth.fill.ip_basic.ip_basic_fill`;
- ``default``: the shipped model, ``CRFDepth.from_pretrained("kitti")``; ``default+std`` is the same
  forward with ``return_std=True`` (the same depth: its RMSE is its own, and equal; it differs in time);
- ``pixel``: ``CRFDepth(mode="pixel")``; ``superpixel``: ``CRFDepth()``; ``no-refine``: ``CRFDepth(refine=False)``.

Accuracy: RMSE in mm of :func:`crfdepth.metrics.depth_metrics` per image over its target pixels, averaged over
images (as ``benchmarks/accuracy.py``), on the KITTI frames under ``--kitti-root`` (default ``../shared/data/kitti``),
loaded by ``benchmarks/accuracy_parts/protocols.py``:

- protocol **a**: ``depth_selection/val_selection_cropped``, 2 frames, the official input and semi-dense ground truth;
- protocol **c**: the raw scans (``raw/``, ``object/training``; 25 frames) keeping every 4th laser ring (16 beams)
  as the input, the other rings as the target. The shipped weights (``default``) were trained on these scans
  with this very hold-out, except drive 0001's (the recipe's ``val_names_contain``): its RMSE there is
  in-sample. The RMSE on the frames outside the recipe's training set is given beside it (``rmse_unseen``).

Without ``depth_selection/val_selection_cropped`` under ``--kitti-root`` (a note says so), the built-in synthetic
street ``make_scene(0)`` at ``--synthetic-size`` is the one frame, scored against its dense true depth (sky excluded).

Speed: on the CPU, median over ``--repeats`` forwards (after a warm-up of each), round-robin over the methods so
that outside load spreads over all of them, on the first frame (1216 x 352 on KITTI), batch 1,
``torch.set_num_threads(--threads)`` and as many OpenCV threads, under ``torch.inference_mode()``; crfdepth's
compiled CPU kernels as found (``CRFDEPTH_NATIVE=0``: the eager path; the JSON's ``native``).

Draws a log-x scatter of RMSE against ms (one panel per protocol, each point labelled) to ``--out``
(default ``docs/speed_accuracy.png``), prints a table, then one JSON line with everything.

    python benchmarks/speed_accuracy.py [--kitti-root PATH] [--protocols a c] [--max-frames N]
        [--threads 2] [--repeats 5] [--synthetic-size 1216x352] [--out docs/speed_accuracy.png]
"""

from __future__ import annotations

import json
import math
import statistics
import sys
import time
from collections.abc import Callable
from pathlib import Path

import cv2
import torch

from crfdepth import native
from crfdepth.data.synthetic import make_scene
from crfdepth.fill.ip_basic import ip_basic_fill
from crfdepth.fill.nearest import nearest_fill
from crfdepth.metrics import average_metrics, depth_metrics

HERE = Path(__file__).resolve().parent
if str(HERE) not in sys.path:  # a load by the file's path (the tests) has not this folder on the path
    sys.path.append(str(HERE))

import script_args as sa  # noqa: E402  (benchmarks/script_args.py: one-line errors, checked option types)
import speed  # noqa: E402  (benchmarks/speed.py: its configurations, frame size option, KITTI root)
from accuracy_parts import methods as accuracy_methods  # noqa: E402
from accuracy_parts import protocols  # noqa: E402  (the frames, inputs and targets of protocols a and c)
from ip_basic_opencv import ip_basic_opencv_fill  # noqa: E402

DEFAULT_OUT = HERE.parent / "docs" / "speed_accuracy.png"
# method -> (label in the table and the picture, speed.py configuration or None, return_std)
METHODS = {
    "nearest": ("nearest fill", None, False),
    "ip-basic-opencv": ("IP-Basic (OpenCV original)", None, False),
    "ip-basic": ("IP-Basic (crfdepth torch port)", None, False),
    "default": ("default (shipped weights)", "default", False),
    "default+std": ("default + std", "default", True),
    "pixel": ("pixel", "pixel", False),
    "superpixel": ("superpixel", "superpixel", False),
    "no-refine": ("no-refine", "no-refine", False),
}
CLASSICAL = ("nearest", "ip-basic-opencv", "ip-basic")
PROTOCOL_CHOICES = ("a", "c")


def runners() -> dict[str, Callable[[dict], torch.Tensor]]:
    """method -> a function of a frame dict (image, sparse, K) returning its (1, 1, H, W) depth."""
    models = {name: speed.make_model(name, "cpu") for name in ("default", "pixel", "superpixel", "no-refine")}
    out: dict[str, Callable[[dict], torch.Tensor]] = {
        "nearest": lambda f: nearest_fill(f["sparse"]),
        "ip-basic-opencv": lambda f: ip_basic_opencv_fill(f["sparse"]),
        "ip-basic": lambda f: ip_basic_fill(f["sparse"]),
    }
    for method, (_, config, std) in METHODS.items():
        if config is not None:
            out[method] = (lambda model, std: lambda f: model(f["image"], f["sparse"], f["K"], return_std=std).depth)(
                models[config], std)
    return out


def unseen_marker() -> str:
    """The name part of the frames the shipped weights' recipe never trains on (configs/kitti_weights.yaml)."""
    return str(accuracy_methods.recipe()["data"]["val_names_contain"])


def kitti_frames(root: Path, key: str, max_frames: int | None) -> list[dict]:
    """Frames of protocol ``key`` (every group), as dicts of (1, ...) CPU tensors, a name and ``unseen``."""
    marker = unseen_marker()
    frames = []
    for _, layout, folder, options in protocols.PROTOCOLS[key][1]:
        for s in protocols.load_group(root, layout, folder, options, max_frames):
            image, sparse, target, K = protocols.batch(s, "cpu")
            frames.append(dict(image=image, sparse=sparse, target=target, K=K, name=s.name,
                               unseen=marker in s.name))
    return frames


def synthetic_frame(width: int, height: int) -> dict:
    """The synthetic street ``make_scene(0)``, with its dense true depth (0 = sky) as the target."""
    scene = make_scene(0, height=height, width=width)
    t = scene.to_tensors()
    return dict(image=t["image"][None], sparse=t["sparse"][None], target=t["depth"][None], K=t["K"], name=scene.name,
                unseen=True)


def load_protocols(args) -> tuple[dict[str, dict], list[str]]:
    """protocol -> {title, frames}; and the notes printed (a missing folder, a protocol left out)."""
    notes = []
    val = args.kitti_root / "depth_selection" / "val_selection_cropped"
    if not val.is_dir():
        width, height = args.synthetic_size
        notes.append(f"note: no KITTI frames under {args.kitti_root} ({val.name} missing); using the synthetic street "
                     f"make_scene(0) at {width}x{height}, scored against its dense true depth")
        return {"synthetic": dict(title=f"synthetic street make_scene(0), {width}x{height}, dense true depth",
                                  frames=[synthetic_frame(width, height)])}, notes
    out = {}
    for key in args.protocols:
        folders = [folder for _, _, folder, _ in protocols.PROTOCOLS[key][1]]
        missing = [f for f in folders if not (args.kitti_root / f).is_dir()]
        if missing:
            notes.append(f"note: protocol ({key}) left out: {', '.join(missing)} missing under {args.kitti_root}")
            continue
        frames = kitti_frames(args.kitti_root, key, args.max_frames)
        title = {"a": f"(a) val_selection_cropped, {len(frames)} frames, semi-dense ground truth",
                 "c": f"(c) raw scans, every 4th ring kept (16 beams), other rings as target, {len(frames)} frames"}[key]
        out[key] = dict(title=title, frames=frames)
    return out, notes


def accuracy(run: Callable[[dict], torch.Tensor], frames: list[dict]) -> dict:
    """Metrics per image, averaged (crfdepth.metrics), and the RMSE averaged over the ``unseen`` frames only."""
    per = []
    with torch.inference_mode():
        for f in frames:
            per.append(depth_metrics(run(f).clamp_min(1e-3), f["target"]))  # as accuracy_parts.methods.predict
    stacked = {k: torch.cat([d[k] for d in per]) for k in per[0]}
    avg = average_metrics(stacked)
    unseen = [float(d["rmse"][0]) for d, f in zip(per, frames) if f["unseen"]]
    return dict(rmse=avg["rmse"], mae=avg["mae"], frames=len(frames),
                rmse_unseen=statistics.fmean(unseen) if unseen else None, unseen_frames=len(unseen),
                rmse_per_frame=[float(d["rmse"][0]) for d in per])


def timing(run_by: dict[str, Callable[[dict], torch.Tensor]], frame: dict, repeats: int) -> dict[str, list[float]]:
    """Seconds of ``repeats`` forwards of every method on ``frame``, round-robin, after one warm-up each."""
    seconds: dict[str, list[float]] = {m: [] for m in run_by}
    with torch.inference_mode():
        for run in run_by.values():
            run(frame)
        for _ in range(repeats):
            for m, run in run_by.items():
                start = time.perf_counter()
                run(frame)
                seconds[m].append(time.perf_counter() - start)
    return seconds


def plot(rows: list[dict], found: dict[str, dict], path: Path, header: str) -> None:
    """One log-x panel per protocol: RMSE (mm) against ms per frame, every point labelled."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, len(found), figsize=(6.4 * len(found), 4.6), squeeze=False)
    for ax, (key, p) in zip(axes[0], found.items()):
        xs, ys = [r["ms"] for r in rows], [r["rmse"][key] for r in rows]
        low, high = min(ys), max(ys)
        pad = 0.08 * ((high - low) or high)
        ax.set_xscale("log")
        ax.set_xlim(min(xs) / 1.6, max(xs) * 4)  # room for the labels on the right
        ax.set_ylim(low - pad, high + 2 * pad)
        for r in rows:
            classical = r["method"] in CLASSICAL
            ax.scatter([r["ms"]], [r["rmse"][key]], s=36, marker="s" if classical else "o",
                       color="tab:gray" if classical else "tab:blue", zorder=3)
        label_points(ax, [(r["ms"], r["rmse"][key], r["label"]) for r in rows])
        ax.set_xlabel(f"ms per frame (timing frame: {rows[0]['timing_size']}, median of {rows[0]['repeats']})")
        ax.set_ylabel("RMSE (mm)")
        title = p["title"]
        if key == "c":
            seen = sum(not f["unseen"] for f in p["frames"])
            title += f"\n(default's weights were trained on {seen} of these {len(p['frames'])} frames)" if seen else ""
        ax.set_title(title, fontsize=9)
        ax.grid(True, which="both", alpha=0.3)
    fig.suptitle(header, fontsize=10)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)


def label_points(ax, points: list[tuple[float, float, str]], fontsize: float = 8.0) -> None:
    """Label each (x, y, text) of a log-x axes beside its point, on the first side (right then left, above then
    below) where the text's box overlaps no point, no label placed before and stays inside the axes."""
    fig, box = ax.figure, ax.get_position()
    width, height = box.width * fig.get_figwidth() * 72, box.height * fig.get_figheight() * 72  # points
    (x0, x1), (y0, y1) = ax.get_xlim(), ax.get_ylim()
    at = [(width * math.log(x / x0) / math.log(x1 / x0), height * (y - y0) / (y1 - y0), text) for x, y, text in points]
    taken = [(px - 4, py - 4, px + 4, py + 4) for px, py, _ in at]  # the markers

    def overlaps(a, b) -> bool:
        return a[0] < b[2] and b[0] < a[2] and a[1] < b[3] and b[1] < a[3]

    sides = ((6, 2, "left", "bottom"), (6, -2, "left", "top"), (-6, 2, "right", "bottom"), (-6, -2, "right", "top"))
    for (x, y, text), (px, py, _) in sorted(zip(points, at), key=lambda item: -item[0][1]):
        w, h = 0.55 * fontsize * len(text), 1.2 * fontsize  # the text's box, roughly
        best = None
        for dx, dy, ha, va in sides:
            left = px + dx if ha == "left" else px + dx - w
            bottom = py + dy if va == "bottom" else py + dy - h
            candidate = (left, bottom, left + w, bottom + h)
            clashes = sum(overlaps(candidate, t) for t in taken) + (left < 0 or left + w > width or bottom < 0
                                                                     or bottom + h > height)
            if best is None or clashes < best[0]:
                best = (clashes, candidate, dx, dy, ha, va)
            if not clashes:
                break
        _, candidate, dx, dy, ha, va = best
        taken.append(candidate)
        ax.annotate(text, (x, y), xytext=(dx, dy), textcoords="offset points", ha=ha, va=va, fontsize=fontsize)


def print_table(rows: list[dict], found: dict[str, dict]) -> None:
    keys = list(found)
    head = ["method", "ms", "min-max ms"] + [f"RMSE {k} (mm)" for k in keys]
    if "c" in found:
        head.append("RMSE c unseen (mm)")
    widths = [30, 8, 14] + [14] * (len(head) - 3)
    print("  ".join(f"{h:>{w}}" for h, w in zip(head, widths)))
    for r in rows:
        cells = [r["label"], f"{r['ms']:.1f}", f"{r['spread_ms'][0]:.1f}-{r['spread_ms'][1]:.1f}"]
        cells += [f"{r['rmse'][k]:.0f}" for k in keys]
        if "c" in found:
            cells.append(f"{r['rmse_unseen']['c']:.0f}" if r["rmse_unseen"].get("c") is not None else "-")
        print("  ".join(f"{c:>{w}}" for c, w in zip(cells, widths)))


def png_path(text: str) -> Path:
    """``--out``: a .png file to write (not a folder)."""
    path = Path(text)
    if not text or path.is_dir() or path.suffix.lower() != ".png":
        why = "which is a folder" if text and path.is_dir() else "not a .png name"
        raise sa.argparse.ArgumentTypeError(f"expected a .png file to write, got {text!r} ({why})")
    return path


def main(argv: list[str] | None = None) -> int:
    parser = sa.ScriptParser(prog="speed_accuracy.py", description=__doc__.split("\n\n")[0])
    parser.add_argument("--kitti-root", type=sa.folder("the KITTI sample folder"), default=speed.DEFAULT_ROOT)
    parser.add_argument("--protocols", nargs="+", choices=list(PROTOCOL_CHOICES), default=list(PROTOCOL_CHOICES))
    parser.add_argument("--max-frames", type=sa.count(1), default=None,
                        help="frames per group of each protocol (evenly spaced); default all")
    parser.add_argument("--threads", type=sa.count(1, sa.MAX_THREADS), default=2, help="torch and OpenCV CPU threads")
    parser.add_argument("--repeats", type=sa.count(1), default=5, help="timed forwards per method (the median)")
    parser.add_argument("--synthetic-size", type=speed.frame_size, default="1216x352",
                        help="WIDTHxHEIGHT of the synthetic frame used without the KITTI folder")
    parser.add_argument("--out", type=png_path, default=DEFAULT_OUT, help="the picture (PNG)")
    args = parser.parse_args(argv)
    torch.set_num_threads(args.threads)
    cv2.setNumThreads(args.threads)
    found, notes = load_protocols(args)
    for note in notes:
        print(note)
    kernels = native.kernels() is not None
    run_by = runners()
    first = next(iter(found.values()))["frames"][0]
    height, width = first["image"].shape[-2:]
    rows = []
    quality = {m: {key: accuracy(run, p["frames"]) for key, p in found.items()} for m, run in run_by.items()}
    seconds = timing(run_by, first, args.repeats)
    for m, run in run_by.items():
        ms = [1000.0 * s for s in seconds[m]]
        rows.append(dict(method=m, label=METHODS[m][0], ms=statistics.median(ms), spread_ms=[min(ms), max(ms)],
                         repeats=args.repeats, timing_frame=first["name"], timing_size=f"{width}x{height}",
                         rmse={k: q["rmse"] for k, q in quality[m].items()},
                         mae={k: q["mae"] for k, q in quality[m].items()},
                         rmse_unseen={k: q["rmse_unseen"] for k, q in quality[m].items()},
                         rmse_per_frame={k: q["rmse_per_frame"] for k, q in quality[m].items()}))
    subject = "RMSE against time per frame: " + ("KITTI protocols " + ", ".join(f"({k})" for k in found)
                                                 if "synthetic" not in found else "synthetic street (no KITTI folder)")
    setting = f"CPU, {args.threads} threads, compiled kernels {'on' if kernels else 'off'}"
    plot(rows, found, args.out, f"{subject}\n{setting}")
    print(f"{subject}; {setting}; timing frame {first['name']} ({width}x{height})")
    for key, p in found.items():
        print(f"{key}: {p['title']}")
    print_table(rows, found)
    print(f"picture: {args.out}")
    print(json.dumps(dict(threads=args.threads, repeats=args.repeats, native=kernels, notes=notes,
                          protocols={k: dict(title=p["title"], frames=[f["name"] for f in p["frames"]],
                                             unseen=[f["name"] for f in p["frames"] if f["unseen"]])
                                     for k, p in found.items()},
                          rows=rows, out=str(args.out), torch=torch.__version__, opencv=cv2.__version__)))
    return 0


if __name__ == "__main__":
    sys.exit(sa.run_script(main, "speed_accuracy.py"))
