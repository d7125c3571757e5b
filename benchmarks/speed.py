"""Speed and memory of every configuration beside the classical fill, in one run (issue 15).

Two frames:

- ``kitti``: 1216 x 352, ``depth_selection/val_selection_cropped`` frame 0 under
  ``--kitti-root`` (default ``../shared/data/kitti`` next to the repository), or the built-in
  synthetic street ``make_scene(0)`` with a note when that is absent;
- ``large``: ``--large`` (default 4000 x 3000), the synthetic street rendered at that size
  (``make_scene(0, height, width)``: a 12-megapixel camera with the same 64-beam LiDAR).

Configurations (each without and with the std, ``return_std=True``):

- ``default``: the shipped model, ``CRFDepth.from_pretrained("kitti")`` (pixel grid, log depth, occlusion gate);
- ``pixel``: ``CRFDepth(mode="pixel")``, the constructor's potentials on the pixel grid;
- ``superpixel``: ``CRFDepth()``, 5500 SLIC segments at 1216 x 352 (scaled with the area) and the pixel refinement;
- ``no-refine``: ``CRFDepth(refine=False)``, the paper's piecewise-constant painting;
- ``ip-basic``: :func:`crfdepth.fill.ip_basic.ip_basic_fill`, crfdepth's torch port of the classical fill
  (the accuracy benchmark's);
- ``ip-basic-opencv``: IP-Basic's original algorithm in OpenCV (``benchmarks/ip_basic_opencv.py``:
  Ku et al. 2018, ``fill_in_fast`` with extrapolation and the Gaussian blur), always on the CPU
  with ``--threads`` OpenCV threads: the reference every row's "x IP-Basic" ratio is taken
  against (row time / this row's time at the same frame size).

Per configuration and frame: the model's per-stage times (``CRFOutput.timings``: on CUDA
each stage is synchronised), the total (median over ``--repeats`` forwards, run
round-robin over the configurations so that outside load spreads over all of them; the
large frame is run once), frames per second, CG iterations of each solve, and the peak
memory: on the CPU the growth of the resident set of a fresh process running one forward
(after a forward on a corner of the frame, which loads libraries and kernels, its peak
resident set ``VmHWM``, reset just before the measured forward, less the resident set
then; Linux only; everything the forward allocates); on CUDA the allocator's peak (``torch.cuda.max_memory_allocated``). Memory is
also given per pixel. On CUDA the default configuration is also run at ``--batch``
frames per forward (frames per second at that batch). With ``--solvers``, every pixel-grid
solve of the default and the superpixel model (captured from a forward on each frame) is
timed alone with the Jacobi and multigrid preconditioners and "auto" (iterations, and the
fastest of ``--repeats`` runs; one on the large frame).

Also the stage split of the default model on the 1216 x 352 frame (median over ``--repeats``
forwards): LiDAR evidence (fill and gate), grid potentials, grid system, CG, output, and the
rest (input checks and glue), timed by wrapping the stage functions that
``crfdepth.inference.pixel`` calls (its module attributes, patched here and restored after).

Verdicts (issue 15): default <= 100 ms per 1216 x 352 frame and <= 20x the classical fill
(IP-Basic's OpenCV original; the torch port when that row is missing);
moonshot <= 25 ms; peak memory at the large size <= 8 GB for every configuration (or the
model refuses it up front, which is reported as ``refused``); on CUDA >= 100 frames/s at
the batch. Prints a table, the verdicts, then one JSON line with everything.

    python benchmarks/speed.py [--device cpu|cuda] [--threads 2] [--repeats 5]
                               [--large 4000x3000] [--skip-large] [--batch 8] [--kitti-root PATH]
                               [--solvers]
"""

from __future__ import annotations

import json
import multiprocessing as mp
import statistics
import sys
import tempfile
import time
from dataclasses import replace
from pathlib import Path

import cv2
import torch

from crfdepth.data.kitti import KittiValSelection
from crfdepth.data.synthetic import make_scene
from crfdepth.errors import InputError
from crfdepth.fill.ip_basic import ip_basic_fill
from crfdepth.model import CRFDepth

if str(Path(__file__).resolve().parent) not in sys.path:  # a load by the file's path (the tests) has not
    sys.path.append(str(Path(__file__).resolve().parent))

import script_args as sa  # noqa: E402  (benchmarks/script_args.py: one-line errors, checked option types)
from ip_basic_opencv import ip_basic_opencv_fill  # noqa: E402  (benchmarks/ip_basic_opencv.py: the original's OpenCV steps)

DEFAULT_ROOT = Path(__file__).resolve().parent.parent.parent / "shared" / "data" / "kitti"
CONFIGS = ("default", "pixel", "superpixel", "no-refine", "ip-basic", "ip-basic-opencv")
CLASSICAL = ("ip-basic", "ip-basic-opencv")  # no model, no std
REFERENCE = "ip-basic-opencv"  # the "x IP-Basic" ratios' denominator
# The default model's stage split: (key, label) in the order of a forward.
SPLIT = (("checks", "input checks"), ("evidence", "lidar evidence (fill and gate)"), ("potentials", "grid potentials"),
         ("system", "grid system"), ("cg", "CG solve"), ("output", "output"), ("rest", "rest"))
STAGES = ("fill", "slic", "graph", "normals", "potentials", "solve", "painting", "refine", "uncertainty")
TARGET_MS, MOONSHOT_MS, TARGET_VS_CLASSICAL = 100.0, 25.0, 20.0
TARGET_LARGE_GB, TARGET_GPU_FPS = 8.0, 100.0


def make_model(name: str, device: str) -> CRFDepth | None:
    """The configuration's model in eval mode on ``device`` (None for the classical fills)."""
    if name in CLASSICAL:
        return None
    model = {"default": lambda: CRFDepth.from_pretrained("kitti"), "pixel": lambda: CRFDepth(mode="pixel"),
             "superpixel": lambda: CRFDepth(), "no-refine": lambda: CRFDepth(refine=False)}[name]()
    return model.to(device).eval()


def load_frame(kind: str, root: Path, large: tuple[int, int]) -> dict:
    """(1, 3, H, W) image, (1, 1, H, W) sparse, (3, 3) K on the CPU, and the frame's name."""
    if kind == "kitti":
        try:
            s = KittiValSelection(root / "depth_selection" / "val_selection_cropped")[0]
            return dict(image=s.image[None], sparse=s.sparse[None], K=s.K, name=s.name)
        except (FileNotFoundError, InputError) as err:
            print(f"note: no KITTI frame under {root} ({err}); using the synthetic street make_scene(0)")
            scene = make_scene(0)
    else:
        scene = make_scene(0, height=large[0], width=large[1])
    t = scene.to_tensors()
    return dict(image=t["image"][None].float(), sparse=t["sparse"][None].float(), K=t["K"].float(), name=scene.name)


def sync(device: str) -> None:
    if device.startswith("cuda"):
        torch.cuda.synchronize()


def run_once(name: str, model: CRFDepth | None, frame: dict, std: bool, device: str) -> tuple[float, dict, list]:
    """Seconds of one forward (or one classical fill), its stage timings and CG iterations.

    ``ip-basic-opencv`` runs on the CPU whatever ``device`` is: its input is moved there before the clock starts.
    """
    sparse = frame["sparse"].cpu() if name == "ip-basic-opencv" else frame["sparse"]
    sync(device)
    start = time.perf_counter()
    with torch.no_grad():
        if model is None:
            (ip_basic_opencv_fill if name == "ip-basic-opencv" else ip_basic_fill)(sparse)
            out = None
        else:
            out = model(frame["image"], frame["sparse"], frame["K"], return_std=std)
    sync(device)
    seconds = time.perf_counter() - start
    if out is None:
        return seconds, {}, []
    return seconds, dict(out.timings), [int(i.iterations.max()) for i in out.info]


def on_device(frame: dict, device: str, batch: int = 1) -> dict:
    return dict(image=frame["image"].to(device).repeat(batch, 1, 1, 1),
                sparse=frame["sparse"].to(device).repeat(batch, 1, 1, 1), K=frame["K"].to(device), name=frame["name"])


def _status_bytes(key: str) -> int:
    """A size from ``/proc/self/status`` (Linux), bytes."""
    with open("/proc/self/status") as f:
        for line in f:
            if line.startswith(key + ":"):
                return int(line.split()[1]) * 1024
    raise RuntimeError(f"{key} not in /proc/self/status")


def _memory_child(name: str, path: str, std: bool, threads: int, queue) -> None:
    """In a fresh process: one forward, then the growth of the resident set over it (bytes)."""
    torch.set_num_threads(threads)
    cv2.setNumThreads(threads)
    frame = torch.load(path)
    model = make_model(name, "cpu")
    # A forward on a corner of the frame first: libraries and kernels load lazily on first use.
    corner = dict(frame, image=frame["image"][..., :96, :320], sparse=frame["sparse"][..., :96, :320].clone())
    corner["sparse"][..., 48, ::7] = 10.0  # returns in every corner
    run_once(name, model, corner, std, "cpu")
    before = _status_bytes("VmRSS")
    with open("/proc/self/clear_refs", "w") as f:
        f.write("5")  # reset the peak resident set (VmHWM) to the current one
    try:
        seconds, stages, iterations = run_once(name, model, frame, std, "cpu")
    except InputError as err:  # refused up front
        queue.put(dict(refused=str(err)))
        return
    peak = _status_bytes("VmHWM")
    queue.put(dict(peak_bytes=max(0, peak - before), seconds=seconds, stages=stages, iterations=iterations))


def cpu_memory(name: str, path: str, std: bool, threads: int) -> dict:
    ctx = mp.get_context("spawn")
    queue = ctx.Queue()
    child = ctx.Process(target=_memory_child, args=(name, path, std, threads, queue))
    child.start()
    child.join()
    if child.exitcode != 0:
        return dict(failed=f"exit status {child.exitcode} (killed for memory?)")
    return queue.get()


def cuda_memory(name: str, model: CRFDepth | None, frame: dict, std: bool, device: str) -> dict:
    torch.cuda.empty_cache()
    torch.cuda.reset_peak_memory_stats(device)
    base = torch.cuda.memory_allocated(device)
    try:
        seconds, stages, iterations = run_once(name, model, frame, std, device)
    except InputError as err:
        return dict(refused=str(err))
    except RuntimeError as err:  # out of memory, a CUDA library's error: reported in the row, the run goes on
        return dict(failed=f"{type(err).__name__}: {str(err).splitlines()[0]}")
    return dict(peak_bytes=torch.cuda.max_memory_allocated(device) - base, seconds=seconds, stages=stages,
                iterations=iterations)


def measure_small(frame: dict, device: str, repeats: int) -> list[dict]:
    """Round-robin timing of every (configuration, std) pair on the 1216 x 352 frame."""
    pairs = [(n, s) for n in CONFIGS for s in ((False,) if n in CLASSICAL else (False, True))]
    models = {n: make_model(n, device) for n in CONFIGS}
    f = on_device(frame, device)
    for n, s in pairs:
        run_once(n, models[n], f, s, device)  # warm-up
    runs = {p: [] for p in pairs}
    for _ in range(repeats):
        for n, s in pairs:
            runs[(n, s)].append(run_once(n, models[n], f, s, device))
    rows = []
    for (n, s), results in runs.items():
        seconds = statistics.median(r[0] for r in results)
        stages = {k: statistics.median(r[1].get(k, 0.0) for r in results) for k in STAGES}
        rows.append(dict(config=n, std=s, size=list(frame["image"].shape[-2:]), seconds=seconds,
                         spread=[min(r[0] for r in results), max(r[0] for r in results)], fps=1 / seconds,
                         stages={k: v for k, v in stages.items() if v > 0}, iterations=results[-1][2],
                         repeats=repeats))
    return rows


def add_memory(rows: list[dict], frame: dict, device: str, threads: int) -> None:
    """Peak memory of every row's (configuration, std) on ``frame`` (a fresh process each on the CPU)."""
    with tempfile.TemporaryDirectory() as tmp:
        path = str(Path(tmp) / "frame.pt")
        torch.save(frame, path)
        for row in rows:
            if device == "cpu" or row["config"] == "ip-basic-opencv":  # OpenCV's fill allocates on the CPU
                got = cpu_memory(row["config"], path, row["std"], threads)
            else:
                got = cuda_memory(row["config"], make_model(row["config"], device), on_device(frame, device),
                                  row["std"], device)
            pixels = frame["image"].shape[-1] * frame["image"].shape[-2]
            row["peak_bytes"] = got.get("peak_bytes")
            row["bytes_per_pixel"] = None if row["peak_bytes"] is None else row["peak_bytes"] / pixels
            for key in ("refused", "failed"):
                if key in got:
                    row[key] = got[key]
            if "seconds" not in row:  # the large frame: its one run is this one
                row.update(seconds=got.get("seconds"), stages={k: v for k, v in got.get("stages", {}).items() if v > 0},
                           iterations=got.get("iterations"), fps=1 / got["seconds"] if got.get("seconds") else None)


def add_ratios(rows: list[dict]) -> None:
    """Every row's time over the ``ip-basic-opencv`` row's at the same frame size (``vs_ip_basic``; None without it)."""
    reference = {tuple(r["size"]): r.get("seconds") for r in rows if r["config"] == REFERENCE}
    for row in rows:
        ref = reference.get(tuple(row["size"]))
        row["vs_ip_basic"] = row["seconds"] / ref if ref and row.get("seconds") else None


def stage_split(frame: dict, device: str, repeats: int) -> dict:
    """Seconds per stage of the default model's forward on ``frame`` (depth only), median over ``repeats``.

    The stages are the functions ``crfdepth.inference.pixel`` calls (``evidence``, ``grid_potentials``,
    ``grid_system``, ``solve_system``, ``pixel_count_uncertainty`` and ``CRFOutput``: output) and the model's
    ``_checked_inputs`` (checks), each wrapped with a clock (synchronised on CUDA) for these forwards only;
    ``rest`` is the forward's time outside them, ``total`` the forward's. One warm-up forward first.
    """
    import crfdepth.inference.pixel as pixel

    model, f = make_model("default", device), on_device(frame, device)
    wrapped = {"evidence": "evidence", "grid_potentials": "potentials", "grid_system": "system",
               "solve_system": "cg", "pixel_count_uncertainty": "output", "CRFOutput": "output"}
    spent: dict[str, float] = {}

    def timed(fn, key):
        def call(*args, **kwargs):
            sync(device)
            start = time.perf_counter()
            try:
                return fn(*args, **kwargs)
            finally:
                sync(device)
                spent[key] = spent.get(key, 0.0) + time.perf_counter() - start
        return call

    originals = {name: getattr(pixel, name) for name in wrapped}
    for name, key in wrapped.items():
        setattr(pixel, name, timed(originals[name], key))
    model._checked_inputs = timed(model._checked_inputs, "checks")  # the instance's, not the class's
    runs = []
    try:
        for k in range(repeats + 1):
            spent.clear()
            seconds = run_once("default", model, f, False, device)[0]
            if k:  # the first is the warm-up
                runs.append(dict(spent, total=seconds, rest=seconds - sum(spent.values())))
    finally:
        for name, fn in originals.items():
            setattr(pixel, name, fn)
    if not runs[-1].get("cg") or not runs[-1].get("evidence"):
        raise RuntimeError(f"the stage split timed {sorted(runs[-1])}: the default forward no longer calls "
                           "evidence and solve_system through crfdepth.inference.pixel")
    return {key: statistics.median(r.get(key, 0.0) for r in runs) for key, _ in SPLIT + (("total", ""),)}


def print_split(split: dict, frame: dict, repeats: int) -> None:
    h, w = frame["image"].shape[-2:]
    print(f"stage split of the default model, {w}x{h}, median of {repeats}: " + ", ".join(
        f"{label} {1000 * split[key]:.1f} ms ({100 * split[key] / split['total']:.0f}%)" for key, label in SPLIT)
        + f"; total {1000 * split['total']:.1f} ms")


def measure_solvers(frame: dict, device: str, repeats: int) -> list[dict]:
    """Iterations and time of each pixel-grid solve of the default and the superpixel model on
    ``frame`` (captured from a forward), with the Jacobi and multigrid preconditioners and "auto"."""
    import crfdepth.inference.pixel
    import crfdepth.inference.superpixel
    import crfdepth.layer
    from crfdepth.linalg import solve_system

    # The modules whose forwards call solve_system (each holds its own reference to it).
    callers = (crfdepth.inference.pixel, crfdepth.inference.superpixel, crfdepth.layer)
    captured = []

    def capture(system, x0, settings):
        if system.is_grid:
            captured.append((system, x0, settings))
        return solve_system(system, x0, settings)

    f = on_device(frame, device)
    for module in callers:
        module.solve_system = capture
    try:  # the default model's grid solves: the first pass and the round with geometry
        run_once("default", make_model("default", device), f, False, device)
        names = [f"default solve {k + 1}" for k in range(len(captured))]
        run_once("superpixel", make_model("superpixel", device), f, False, device)  # one grid solve: the refinement
        names.append("superpixel refinement")
    finally:
        for module in callers:
            module.solve_system = solve_system
    if len(names) == 1 or len(captured) != len(names):  # none from the default, or not one from the superpixel model
        raise RuntimeError(f"captured {len(captured)} grid solves for {names}: "
                           "a forward no longer calls solve_system through the patched modules")
    rows = []
    for name, (system, x0, settings) in zip(names, captured):
        row = dict(solve=name, size=list(system.diagonal.shape[-2:]))
        for pre in ("jacobi", "multigrid", "auto"):
            chosen = replace(settings, preconditioner=pre)
            times = []
            for _ in range(repeats):
                sync(device)
                start = time.perf_counter()
                _, info = solve_system(system, x0, chosen)
                sync(device)
                times.append(time.perf_counter() - start)
            row[pre] = dict(iterations=int(info.iterations.max()), seconds=min(times))
        rows.append(row)
    return rows


def print_solvers(rows: list[dict]) -> None:
    print(f"{'solve':>24}  {'size':>10}" + "".join(f"  {p + ' it':>12}  {p + ' ms':>12}" for p in ("jacobi", "multigrid", "auto")))
    for r in rows:
        cells = "".join(f"  {r[p]['iterations']:>12}  {1000 * r[p]['seconds']:>12.1f}" for p in ("jacobi", "multigrid", "auto"))
        print(f"{r['solve']:>24}  {r['size'][1]:>5}x{r['size'][0]:<4}" + cells)


def _cell(v, scale=1000.0, digits=0) -> str:
    return "-" if v is None else f"{v * scale:.{digits}f}"


def print_table(rows: list[dict]) -> None:
    stages = [s for s in STAGES if any(s in r.get("stages", {}) for r in rows)]
    head = (["size", "config", "std"] + [s[:8] for s in stages]
            + ["total ms", "x IP-Basic", "fps", "peak MB", "B/px", "iterations"])
    widths = [10, 15, 5] + [8] * len(stages) + [9, 10, 7, 8, 6, 14]
    print("  ".join(f"{h:>{w}}" for h, w in zip(head, widths)))
    for r in rows:
        cells = [f"{r['size'][1]}x{r['size'][0]}", r["config"], "yes" if r["std"] else "no"]
        cells += [_cell(r.get("stages", {}).get(s)) for s in stages]
        cells += [_cell(r.get("seconds"), digits=1), _cell(r.get("vs_ip_basic"), 1, 1), _cell(r.get("fps"), 1, 1),
                  _cell(r.get("peak_bytes"), 1e-6), _cell(r.get("bytes_per_pixel"), 1),
                  "refused" if r.get("refused") else "failed" if r.get("failed") else str(r.get("iterations") or "-")]
        print("  ".join(f"{c:>{w}}" for c, w in zip(cells, widths)))


def verdicts(rows: list[dict], batch_row: dict | None) -> dict:
    small = {(r["config"], r["std"]): r for r in rows if r["size"] == [352, 1216]}
    default = small.get(("default", False))
    # The classical fill is IP-Basic's OpenCV original; crfdepth's torch port (7x slower on the CPU) only without it.
    classical = small.get((REFERENCE, False)) or small.get(("ip-basic", False))
    out = {}
    if default and classical:
        ms, ratio = 1000 * default["seconds"], default["seconds"] / classical["seconds"]
        out["default_ms"] = dict(value=ms, target=TARGET_MS, met=ms <= TARGET_MS)
        out["default_vs_classical"] = dict(value=ratio, target=TARGET_VS_CLASSICAL, met=ratio <= TARGET_VS_CLASSICAL,
                                           classical=classical["config"])
        out["moonshot_ms"] = dict(value=ms, target=MOONSHOT_MS, met=ms <= MOONSHOT_MS)
    large = [r for r in rows if r["size"] != [352, 1216]]
    if large:
        worst = max((r.get("peak_bytes") or 0) for r in large) / 1e9
        bad = [f"{r['config']} std={r['std']}" for r in large
               if not r.get("refused") and (r.get("peak_bytes") is None or r["peak_bytes"] > TARGET_LARGE_GB * 1e9)]
        out["large_peak_gb"] = dict(value=worst, target=TARGET_LARGE_GB, met=not bad, over=bad)
    if batch_row is not None:
        out["gpu_fps_batch"] = dict(value=batch_row["fps"], target=TARGET_GPU_FPS, met=batch_row["fps"] >= TARGET_GPU_FPS)
    return out


def frame_size(text: str) -> tuple[int, int]:
    """``--large``: WIDTHxHEIGHT, each an integer in [8, 20000] pixels."""
    parts = text.lower().split("x")
    try:
        width, height = (int(v) for v in parts) if len(parts) == 2 else (0, 0)
    except ValueError:
        width = height = 0
    if not (8 <= width <= 20000 and 8 <= height <= 20000):
        raise sa.argparse.ArgumentTypeError(f"expected WIDTHxHEIGHT such as 4000x3000, each in [8, 20000] pixels, "
                                            f"got {text!r}")
    return width, height


def main(argv: list[str] | None = None) -> int:
    parser = sa.ScriptParser(prog="speed.py", description=__doc__.split("\n\n")[0])
    parser.add_argument("--device", type=sa.device, default="cpu", help="cpu or cuda[:k]")
    parser.add_argument("--threads", type=sa.count(1, sa.MAX_THREADS), default=2, help="torch CPU threads")
    parser.add_argument("--repeats", type=sa.count(1), default=5)
    parser.add_argument("--large", type=frame_size, default="4000x3000", help="WIDTHxHEIGHT of the large frame")
    parser.add_argument("--skip-large", action="store_true")
    parser.add_argument("--batch", type=sa.count(1, 1024), default=8, help="frames per forward for the CUDA throughput row")
    parser.add_argument("--kitti-root", type=sa.folder("the KITTI sample folder"), default=DEFAULT_ROOT)
    parser.add_argument("--solvers", action="store_true",
                        help="also time each pixel-grid solve with the Jacobi and multigrid preconditioners and 'auto'")
    args = parser.parse_args(argv)
    width, height = args.large
    args.large = f"{width}x{height}"
    torch.set_num_threads(args.threads)
    cv2.setNumThreads(args.threads)  # the OpenCV row's threads: the same as torch's
    frame = load_frame("kitti", args.kitti_root, (height, width))
    rows = measure_small(frame, args.device, args.repeats)
    add_memory(rows, frame, args.device, args.threads)
    batch_row = None
    if args.device.startswith("cuda"):
        model, f = make_model("default", args.device), on_device(frame, args.device, args.batch)
        run_once("default", model, f, False, args.device)
        seconds = statistics.median(run_once("default", model, f, False, args.device)[0] for _ in range(args.repeats))
        batch_row = dict(config="default", std=False, batch=args.batch, seconds=seconds, fps=args.batch / seconds)
    split = stage_split(frame, args.device, args.repeats)
    solvers = measure_solvers(frame, args.device, args.repeats) if args.solvers else []
    if not args.skip_large:
        large = load_frame("large", args.kitti_root, (height, width))
        big = [dict(config=n, std=s, size=[height, width])
               for n in CONFIGS for s in ((False,) if n in CLASSICAL else (False, True))]
        add_memory(big, large, args.device, args.threads)
        rows += big
        if args.solvers:
            solvers += measure_solvers(large, args.device, 1)
    add_ratios(rows)
    print(f"device {args.device}" + (f" ({torch.cuda.get_device_name(args.device)})" if batch_row else "")
          + f", {args.threads} threads, frame {frame['name']}")
    print_table(rows)
    print_split(split, frame, args.repeats)
    if solvers:
        print_solvers(solvers)
    if batch_row:
        print(f"default at batch {args.batch}: {batch_row['fps']:.1f} frames/s")
    v = verdicts(rows, batch_row)
    for key, item in v.items():
        against = f" against {item['classical']}" if "classical" in item else ""
        print(f"{key}: {item['value']:.3g}{against} (target {item['target']:g}): {'met' if item['met'] else 'MISSED'}")
    print(json.dumps(dict(device=args.device, threads=args.threads, frame=frame["name"], rows=rows, solvers=solvers, batch=batch_row,
                          stage_split=split, reference=REFERENCE, verdicts=v, torch=torch.__version__, opencv=cv2.__version__)))
    return 0


if __name__ == "__main__":
    sys.exit(sa.run_script(main, "speed.py"))
