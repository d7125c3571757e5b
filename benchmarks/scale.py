"""Memory of a folder run against its length (issue: beyond one machine; docs/design.md section 10).

``crfdepth complete --input-dir`` over synthetic folders of 10 and of 1,000 frames (the
street of :func:`crfdepth.data.synthetic.make_scene`, ``--size`` pixels, 16 beams, written in the
``val_selection_cropped`` layout), each run in a fresh process. The peak resident set of that
process (``ru_maxrss`` of the finished child) must not grow with the number of frames: the run
holds one batch and a list of frame names, not the frames. Prints a table and one JSON line per
case, with the ratio of each peak to the shortest run's; optionally the same with ``--devices``.

    python benchmarks/scale.py [--frames 10 1000] [--size 64 208] [--devices 1] [--workers 0]
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from crfdepth.data.synthetic import make_scene, write_selection_folder  # noqa: E402

if str(Path(__file__).resolve().parent) not in sys.path:  # a load by the file's path (the tests) has not
    sys.path.append(str(Path(__file__).resolve().parent))

import script_args as sa  # noqa: E402  (benchmarks/script_args.py: one-line errors, checked option types)


def write_frames(root: Path, count: int, size: tuple[int, int], distinct: int = 20) -> Path:
    """``count`` frames in the val_selection_cropped layout; ``distinct`` scenes repeated (rendering is the slow
    part and the run's memory does not depend on the pixels)."""
    scenes = [make_scene(seed, *size, beams=16) for seed in range(min(count, distinct))]
    return write_selection_folder(root, (scenes[index % len(scenes)] for index in range(count)))


# Runs a command and prints the peak resident set (KiB) of the largest process below it: a fresh parent per
# run, so that each run's peak is its own.
_MEASURE = ("import resource, subprocess, sys; subprocess.run(sys.argv[1:], check=True); "
            "print(resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss)")


def peak_rss_of_run(folder: Path, out: Path, devices: int, workers: int) -> tuple[float, float]:
    """(peak resident set in MB of the run's largest process, seconds) of ``crfdepth complete --input-dir``."""
    start = time.perf_counter()
    done = subprocess.run([sys.executable, "-c", _MEASURE, sys.executable, "-m", "crfdepth", "complete",
                           "--input-dir", str(folder), "--out-dir", str(out), "--devices", str(devices),
                           "--workers", str(workers), "--quiet"], check=True, cwd=ROOT, capture_output=True, text=True)
    seconds = time.perf_counter() - start
    return int(done.stdout.strip().splitlines()[-1]) / 1024.0, seconds


def main(argv: list[str] | None = None) -> int:
    parser = sa.ScriptParser(prog="scale.py", description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--frames", type=sa.count(1, 10**6), nargs="+", default=[10, 1000])
    parser.add_argument("--size", type=sa.count(8, 8192, "pixels"), nargs=2, default=[64, 208], metavar=("H", "W"))
    parser.add_argument("--devices", type=sa.count(1, 64), default=1)
    parser.add_argument("--workers", type=sa.count(0, sa.MAX_WORKERS), default=0)
    args = parser.parse_args(argv)
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for count in sorted(args.frames):
            folder = write_frames(Path(tmp) / f"f{count}" / "val_selection_cropped", count, tuple(args.size))
            peak, seconds = peak_rss_of_run(folder, Path(tmp) / f"out{count}", args.devices, args.workers)
            rows.append({"frames": count, "size": args.size, "devices": args.devices, "workers": args.workers,
                         "peak_rss_mb": round(peak, 1), "seconds": round(seconds, 1),
                         "frames_per_s": round(count / seconds, 2)})
    base = rows[0]["peak_rss_mb"]
    for row in rows:
        row["peak_over_shortest"] = round(row["peak_rss_mb"] / base, 3)
    print(f"folder run memory ({args.size[1]}x{args.size[0]} synthetic frames, --devices {args.devices}, "
          f"--workers {args.workers}; the peak of the run's own process, target: within 10% of the shortest)")
    print(f"{'frames':>8} | {'peak RSS MB':>12} | {'x shortest':>10} | {'seconds':>8} | {'frames/s':>8}")
    for row in rows:
        print(f"{row['frames']:>8} | {row['peak_rss_mb']:>12.1f} | {row['peak_over_shortest']:>10.3f} | "
              f"{row['seconds']:>8.1f} | {row['frames_per_s']:>8.2f}")
    for row in rows:
        print(json.dumps(row))
    return 0


if __name__ == "__main__":
    sys.exit(sa.run_script(main, "scale.py"))
