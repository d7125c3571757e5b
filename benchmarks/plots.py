"""The documentation's figures, drawn from the benchmarks' JSON output (never by hand).

Inputs (the files the benchmarks write; the measured ones the pages show live in ``docs/results/``):

- ``--accuracy``: ``results.jsonl`` of ``benchmarks/accuracy.py`` (one JSON line per protocol and
  method; the methods ``ipbasic``, ``hand-set`` and ``learned`` are drawn, the std's figures from
  ``learned``);
- ``--speed``: the JSON line ``benchmarks/speed.py`` prints last (one row per configuration, with and
  without the std).

Outputs under ``--out-dir`` (default ``docs/results/plots``):

- ``accuracy.png``: RMSE per protocol of IP-Basic, the hand-set and the learned weights, with the
  learned / IP-Basic ratio written on each group;
- ``speed.png``: time per 1216 x 352 frame of every configuration, without and with the std;
- ``std.png``: how the learned model's std ranks and calibrates its errors per protocol: the share of
  errors within 1 and 2 std against a Gaussian's, and AUSE against a random order.

    python benchmarks/plots.py --accuracy accuracy_results/results.jsonl --speed speed.json [--out-dir DIR]
"""

from __future__ import annotations

import argparse
import json
import sys
from collections.abc import Sequence
from pathlib import Path

if str(Path(__file__).resolve().parent) not in sys.path:  # a load by the file's path (the tests) has not
    sys.path.append(str(Path(__file__).resolve().parent))

import script_args as sa  # noqa: E402  (benchmarks/script_args.py: one-line errors, checked option types)

METHODS = {"ipbasic": "IP-Basic", "hand-set": "hand-set weights", "learned": "learned weights (shipped)"}
GAUSSIAN = {1: 0.683, 2: 0.954}  # share of a Gaussian within 1 and 2 std


class PlotError(ValueError):
    """A JSON input that is missing, unreadable or lacks what a figure needs."""


def read_json_lines(path: Path, argument: str) -> list[dict]:
    """The JSON objects of ``path``, one per non-empty line (lines that are not JSON are skipped:
    a benchmark's printed output can be given as it is)."""
    try:
        text = path.read_text(encoding="utf-8")
    except OSError as err:
        raise PlotError(f"{argument}: cannot read {path}: {err.strerror or err}") from None
    records = []
    for line in text.splitlines():
        line = line.strip()
        if line.startswith("{"):
            try:
                records.append(json.loads(line))
            except json.JSONDecodeError:
                continue
    if not records:
        raise PlotError(f"{argument}: expected JSON lines of a benchmark in {path}, got none")
    return records


def accuracy_table(records: list[dict]) -> dict[str, dict[str, dict]]:
    """protocol -> method -> record, for the methods drawn."""
    table: dict[str, dict[str, dict]] = {}
    for r in records:
        if r.get("method") in METHODS and "protocol" in r and "rmse" in r:
            table.setdefault(r["protocol"], {})[r["method"]] = r
    complete = {p: m for p, m in table.items() if set(METHODS) <= set(m)}
    if not complete:
        raise PlotError(f"--accuracy: expected rows of the methods {', '.join(METHODS)} for one protocol at least, "
                        f"got protocols {sorted(table) or 'none'}")
    return complete


def speed_rows(records: list[dict]) -> list[dict]:
    """The 1216 x 352 rows of the last speed.py JSON line."""
    runs = [r for r in records if isinstance(r.get("rows"), list)]
    if not runs:
        raise PlotError("--speed: expected the JSON line of benchmarks/speed.py (with \"rows\"), got none")
    rows = [r for r in runs[-1]["rows"] if r.get("size") == [352, 1216]]
    if not rows:
        raise PlotError("--speed: expected rows of a 1216 x 352 frame, got none")
    return rows


def plot_accuracy(table: dict[str, dict[str, dict]], path: Path) -> None:
    import matplotlib.pyplot as plt

    protocols = sorted(table)
    fig, ax = plt.subplots(figsize=(7, 3.6))
    width = 0.8 / len(METHODS)
    for i, (method, label) in enumerate(METHODS.items()):
        ax.bar([p + (i - 1) * width for p in range(len(protocols))], [table[p][method]["rmse"] for p in protocols],
               width, label=label)
    for x, p in enumerate(protocols):
        ratio = table[p]["learned"]["rmse"] / table[p]["ipbasic"]["rmse"]
        top = max(table[p][m]["rmse"] for m in METHODS)
        ax.text(x, top * 1.02, f"{ratio:.2f} x IP-Basic", ha="center", fontsize=8)
    ax.set_xticks(range(len(protocols)), [f"({p})" for p in protocols])
    ax.set_ylabel("RMSE (mm)")
    ax.set_title("RMSE per protocol (benchmarks/accuracy.py, one run)")
    ax.legend(fontsize=8, loc="upper left")
    ax.set_ylim(0, max(r["rmse"] for m in table.values() for r in m.values()) * 1.15)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def plot_speed(rows: list[dict], path: Path) -> None:
    import matplotlib.pyplot as plt

    configs = list(dict.fromkeys(r["config"] for r in rows))
    fig, ax = plt.subplots(figsize=(7, 3.2))
    for i, std in enumerate((False, True)):
        values = [next((1000 * r["seconds"] for r in rows if r["config"] == c and bool(r.get("std")) == std), 0.0)
                  for c in configs]
        ax.barh([y + (0.2 if std else -0.2) for y in range(len(configs))], values, 0.4,
                label="with the std" if std else "depth only")
    ax.set_yticks(range(len(configs)), configs)
    ax.invert_yaxis()
    ax.set_xlabel("ms per 1216 x 352 frame")
    ax.set_title("Speed per configuration (benchmarks/speed.py, one run)")
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def std_protocols(table: dict[str, dict[str, dict]]) -> list[str]:
    """The protocols whose learned row holds the std's figures."""
    protocols = [p for p in sorted(table) if "coverage_1_std" in table[p]["learned"]]
    if not protocols:
        raise PlotError("--accuracy: expected the learned model's std figures (coverage_1_std, ...), got none")
    return protocols


def plot_std(table: dict[str, dict[str, dict]], path: Path) -> None:
    import matplotlib.pyplot as plt

    protocols = std_protocols(table)
    fig, (left, right) = plt.subplots(1, 2, figsize=(8, 3.2))
    for i, k in enumerate((1, 2)):
        left.bar([x + (i - 0.5) * 0.4 for x in range(len(protocols))],
                 [table[p]["learned"][f"coverage_{k}_std"] for p in protocols], 0.4, label=f"within {k} std")
        left.axhline(GAUSSIAN[k], color=f"C{i}", linestyle="--", linewidth=1)
    left.set_xticks(range(len(protocols)), [f"({p})" for p in protocols])
    left.set_ylim(0, 1.05)
    left.set_ylabel("share of errors")
    left.set_title("calibration (dashed: a Gaussian's)", fontsize=9)
    left.legend(fontsize=8, loc="lower right")
    right.bar(range(len(protocols)), [table[p]["learned"]["ause_ratio_std"] for p in protocols], 0.5)
    right.axhline(1.0, color="grey", linestyle="--", linewidth=1)
    right.set_xticks(range(len(protocols)), [f"({p})" for p in protocols])
    right.set_ylabel("AUSE / random order")
    right.set_title("ranking (lower is better)", fontsize=9)
    fig.suptitle("The learned model's std against its errors (benchmarks/accuracy.py)", fontsize=10)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def parse_args(argv: Sequence[str] | None = None) -> argparse.Namespace:
    parser = sa.ScriptParser(prog="plots.py", description=__doc__.split("\n\n")[0])
    parser.add_argument("--accuracy", type=Path, required=True, help="results.jsonl of benchmarks/accuracy.py")
    parser.add_argument("--speed", type=Path, required=True, help="the output (or JSON line) of benchmarks/speed.py")
    parser.add_argument("--out-dir", type=sa.out_folder, default=Path("docs/results/plots"))
    return parser.parse_args(argv)


def main(argv: Sequence[str] | None = None) -> list[Path]:
    args = parse_args(argv)
    try:
        table = accuracy_table(read_json_lines(args.accuracy, "--accuracy"))
        rows = speed_rows(read_json_lines(args.speed, "--speed"))
        std_protocols(table)  # every input checked before a file is written
        args.out_dir.mkdir(parents=True, exist_ok=True)
    except (PlotError, OSError) as err:
        message = err if isinstance(err, PlotError) else f"--out-dir: cannot create {args.out_dir}: {err.strerror}"
        print(f"plots.py: error: {message}", file=sys.stderr)
        raise SystemExit(2) from None
    paths = [args.out_dir / name for name in ("accuracy.png", "speed.png", "std.png")]
    plot_accuracy(table, paths[0])
    plot_speed(rows, paths[1])
    plot_std(table, paths[2])
    for path in paths:
        print(f"plot: {path}")
    return paths


if __name__ == "__main__":
    sys.exit(sa.run_script(main, "plots.py"))
