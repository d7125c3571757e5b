"""Weight files side by side on the real KITTI frames: which set of weights to ship (issue 38, part 4).

Every model is the shipped structure's ``CRFDepth`` loaded from a weights file (or the hand-set
``"paper"`` weights, or IP-Basic), scored on the same samples in one run; RMSE is KITTI's per-image
mean in mm. The protocols are those of ``benchmarks/accuracy.py`` with drive 0048 added to the scans:

- ``a``: the two official val_selection frames (drive 0001 frame 5), official input;
- ``a22``: the same frames, 22% of the annotation as input, the other 78% the target;
- ``b``: the raw scans (drive 0060's 13 sample frames, the 11 object frames, drive 0048's 3
  frames), 20% of the LiDAR points held out as the target, see-through returns removed;
- ``c``: the same scans, every 4th ring kept (16 beams), the other rings the target.

Which frames each weight set trained on is the reader's to state (the weights README does):
a file trained on a protocol's frames is in-sample there.

    python benchmarks/weights_compare.py --weights shipped=crfdepth/weights/kitti.json new=/tmp/new.json

Prints a table (RMSE per protocol and ratio to the hand-set weights) and one JSON line.
"""

from __future__ import annotations

import argparse
import json
import sys
from collections.abc import Sequence
from pathlib import Path

import torch

ROOT = Path(__file__).resolve().parents[1]
for folder in (ROOT, ROOT / "benchmarks"):
    if str(folder) not in sys.path:
        sys.path.insert(0, str(folder))

from accuracy_parts.methods import method_config, predict  # noqa: E402
from accuracy_parts.protocols import CLEAN_SHARE, load_group  # noqa: E402

from crfdepth.checkpoints import load_model  # noqa: E402
from crfdepth.errors import InputError  # noqa: E402
from crfdepth.model import CRFDepth  # noqa: E402

if str(Path(__file__).resolve().parent) not in sys.path:  # a load by the file's path (the tests) has not
    sys.path.append(str(Path(__file__).resolve().parent))

import script_args as sa  # noqa: E402  (benchmarks/script_args.py: one-line errors, checked option types)

DEFAULT_ROOT = ROOT.parent / "shared" / "data" / "kitti"
SCANS = [("raw", "raw"), ("object", "object/training"), ("raw", "stereo")]
PROTOCOLS = {
    "a": [("val_selection", "depth_selection/val_selection_cropped", {})],
    "a22": [("val_selection", "depth_selection/val_selection_cropped", {"input_share": CLEAN_SHARE})],
    "b": [(layout, folder, {"holdout": "fraction", "holdout_fraction": 0.2, "seed": 0}) for layout, folder in SCANS],
    "c": [(layout, folder, {"holdout": "rings", "keep_every_ring": 4}) for layout, folder in SCANS],
}


def models(weights: dict[str, Path]) -> dict[str, CRFDepth | None]:
    # hand-set: the shipped recipe's structure with the constructor's weights, as benchmarks/accuracy.py builds it
    out: dict[str, CRFDepth | None] = {"ipbasic": None, "hand-set": CRFDepth(**method_config("hand-set"))}
    for name, path in weights.items():
        if not path.is_file():
            raise InputError(f"--weights: {name}={path}: no such file")
        out[name] = load_model(path)
    return {k: (m.eval() if m is not None else None) for k, m in out.items()}


def score(root: Path, protocols: Sequence[str], chosen: dict[str, CRFDepth | None], log=print) -> dict:
    result = {}
    for protocol in protocols:
        samples = [s for layout, folder, options in PROTOCOLS[protocol]
                   for s in load_group(root, layout, folder, options, None)]
        rmse = {name: [] for name in chosen}
        for s in samples:
            valid = s.target > 0
            for name, model in chosen.items():
                depth = predict("ipbasic" if model is None else name, model, s.image[None], s.sparse[None], s.K,
                                "cpu")[0][0]
                rmse[name].append(1000.0 * float(((depth[valid] - s.target[valid]) ** 2).mean().sqrt()))
        result[protocol] = {name: round(sum(v) / len(v), 1) for name, v in rmse.items()}
        result[protocol]["frames"] = len(samples)
        log(f"  {protocol}: {len(samples)} frames: " + ", ".join(f"{k} {v}" for k, v in result[protocol].items()))
    return result


def table(result: dict, names: Sequence[str]) -> list[str]:
    lines = ["| protocol | frames | " + " | ".join(names) + " | " + " | ".join(f"{n} / hand-set" for n in names
                                                                          if n != "hand-set") + " |",
             "|---" * (2 + 2 * len(names) - 1) + "|"]
    for protocol, row in result.items():
        ratios = [f"{row[n] / row['hand-set']:.3f}" for n in names if n != "hand-set"]
        lines.append(f"| {protocol} | {row['frames']} | " + " | ".join(f"{row[n]:.0f}" for n in names) + " | "
                     + " | ".join(ratios) + " |")
    return lines


def parse_args(argv: Sequence[str] | None = None) -> argparse.Namespace:
    parser = sa.ScriptParser(prog="weights_compare.py", description=__doc__.split("\n\n")[0])
    parser.add_argument("--weights", nargs="+", default=[f"shipped={ROOT / 'crfdepth/weights/kitti.json'}"],
                        metavar="NAME=FILE", help="weights files to compare, each named (default: the shipped file)")
    parser.add_argument("--protocols", nargs="+", default=list(PROTOCOLS), choices=list(PROTOCOLS))
    parser.add_argument("--kitti-root", type=Path, default=DEFAULT_ROOT)
    args = parser.parse_args(argv)
    weights = {}
    for item in args.weights:
        name, sep, path = item.partition("=")
        if not sep or not name or not path or name in ("hand-set", "ipbasic") or name in weights:
            parser.error(f"--weights: expected distinct NAME=FILE pairs (NAME not hand-set or ipbasic), got {item!r}")
        weights[name] = Path(path)
    args.weights = weights
    if not args.kitti_root.is_dir():
        parser.error(f"--kitti-root: expected the KITTI sample folder, got {args.kitti_root} (no such folder)")
    return args


def main(argv: Sequence[str] | None = None) -> dict:
    args = parse_args(argv)
    torch.manual_seed(0)
    try:
        chosen = models(args.weights)
        result = score(args.kitti_root, args.protocols, chosen, log=lambda m: print(m, flush=True))
    except InputError as e:
        print(f"weights_compare.py: error: {e}", file=sys.stderr)
        raise SystemExit(2) from None
    print("\n".join(table(result, list(chosen))))
    print(json.dumps({"benchmark": "weights_compare", "weights": {k: str(v) for k, v in args.weights.items()},
                      "protocols": result}))
    return result


if __name__ == "__main__":
    sys.exit(sa.run_script(main, "weights_compare.py"))
