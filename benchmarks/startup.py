"""Start-up time of the ``crfdepth`` command (issue 48): what a user waits for before any work.

Each row is the median wall time (seconds) of ``--repeats`` fresh interpreters: ``import torch`` (the floor:
the CRF needs torch), ``import crfdepth``, ``import crfdepth.cli``, ``crfdepth --version``, ``crfdepth --help``
and ``crfdepth complete`` on the one example frame (docs/example/), written to a temporary folder. The last
rows are the differences that matter: ``complete`` minus ``import torch``, and the import of ``crfdepth.cli``.
Prints a table, then one JSON line. Which modules start-up imports is tested in tests/test_startup.py.

    python benchmarks/startup.py --repeats 5
"""

from __future__ import annotations

import json
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

if str(Path(__file__).resolve().parent) not in sys.path:  # a load by the file's path (the tests) has not
    sys.path.append(str(Path(__file__).resolve().parent))

import script_args as sa  # noqa: E402  (benchmarks/script_args.py: one-line errors, checked option types)

EXAMPLE = Path(__file__).resolve().parent.parent / "docs" / "example"


def _median_wall_s(command: list[str], repeats: int) -> float:
    """The median wall time (s) of ``command`` run ``repeats`` times; refuses one that fails."""
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        done = subprocess.run(command, capture_output=True, text=True)
        times.append(time.perf_counter() - start)
        if done.returncode != 0:
            raise RuntimeError(f"{' '.join(command)} failed ({done.returncode}): {done.stderr.strip()[-300:]}")
    return statistics.median(times)


def main(argv=None) -> int:
    parser = sa.ScriptParser(prog="startup.py", description=__doc__.split("\n\n")[0])
    parser.add_argument("--repeats", type=sa.count(1, 100), default=5, help="runs per row (median; default 5)")
    args = parser.parse_args(argv)
    python = [sys.executable]
    cli = python + ["-m", "crfdepth"]
    with tempfile.TemporaryDirectory() as tmp:
        rows = {
            "import torch": python + ["-c", "import torch"],
            "import crfdepth": python + ["-c", "import crfdepth"],
            "import crfdepth.cli": python + ["-c", "import crfdepth.cli"],
            "crfdepth --version": cli + ["--version"],
            "crfdepth --help": cli + ["--help"],
            "crfdepth complete (1 frame)": cli + ["complete", "--image", str(EXAMPLE / "image.png"), "--points",
                                                  str(EXAMPLE / "scan.pcd"), "--calib", str(EXAMPLE / "rig.yaml"),
                                                  "--out", str(Path(tmp) / "depth.png")],
        }
        result = {name: _median_wall_s(command, args.repeats) for name, command in rows.items()}
    result["complete minus import torch"] = result["crfdepth complete (1 frame)"] - result["import torch"]
    width = max(map(len, result))
    print(f"{'start-up (median of ' + str(args.repeats) + ')':<{width}}  wall s")
    for name, seconds in result.items():
        print(f"{name:<{width}}  {seconds:6.3f}")
    print(json.dumps({"benchmark": "startup", "repeats": args.repeats, "wall_s": result}))
    return 0


if __name__ == "__main__":
    sys.exit(sa.run_script(main, "startup.py"))
