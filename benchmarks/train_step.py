"""Time of one training step of the shipped recipe: forward and backward of the shipped model on a training crop.

The model is the one ``configs/kitti_weights.yaml`` trains: ``CRFDepth.from_pretrained("kitti")`` (pixel grid,
log depth, occlusion gate) inside the trainer's :class:`train.module.CRFDepthModule` (``loss: l1``,
``nll_weight: 0``), so the parameters the trainer freezes are frozen here too, in train mode
(``model.train()``), autograd on. The frame is the recipe's crop, ``crop: [320, 896]``: the bottom-centre
``--crop`` (default 320 x 896) window of ``depth_selection/val_selection_cropped`` frame 0 (1216 x 352) under
``--kitti-root`` (default ``../shared/data/kitti`` next to the repository), ``K`` following the crop
(``cx - left``, ``cy - top``; :class:`crfdepth.data.transforms.BottomCenterCrop`); the built-in synthetic street
``make_scene(0)`` cropped the same way, with a note, when that is absent.

One step is what the trainer's ``training_step`` and Lightning's backward do:

- forward: ``out = model(image, sparse, K)``, then the loss of :func:`train.module.depth_loss` with the recipe's
  ``"l1"``, the mean of ``|depth - target|`` over the frame's ground-truth pixels (``target > 0``), metres.
  The solves that will be differentiated run to the tighter ``grad_rtol`` (1e-10) in float64
  (:mod:`crfdepth.linalg.adjoint`), not to the model's ``rtol``: this is the training path, not inference's;
- backward: ``loss.backward()``: one adjoint solve per forward solve (``SolveInfo.adjoint``, at the model's
  ``rtol``) and the potentials' gradients. The optimiser's step (Adam on about ten scalars) is not timed.

After one untimed warm-up step, ``--repeats`` (default 5) steps are timed; reported: the median forward,
backward and total (their sum per step) in ms, the total's spread, and the CG iterations of each forward solve
(``out.info[i].iterations``) and of its adjoint solve (``out.info[i].adjoint.iterations``), with their
tolerances, and the loss. CPU, ``--threads`` (default 2) torch threads. Prints a table, then one JSON line.

    python benchmarks/train_step.py [--threads 2] [--repeats 5] [--crop 320 896] [--kitti-root PATH]
"""

from __future__ import annotations

import json
import statistics
import sys
import time
from pathlib import Path

import torch

from crfdepth.data.kitti import KittiValSelection
from crfdepth.data.sample import Sample
from crfdepth.data.synthetic import make_scene
from crfdepth.data.transforms import BottomCenterCrop
from crfdepth.errors import InputError
from crfdepth.model import CRFDepth
from train.module import CRFDepthModule, depth_loss

if str(Path(__file__).resolve().parent) not in sys.path:  # a load by the file's path (the tests) has not
    sys.path.append(str(Path(__file__).resolve().parent))

import script_args as sa  # noqa: E402  (benchmarks/script_args.py: one-line errors, checked option types)

DEFAULT_ROOT = Path(__file__).resolve().parent.parent.parent / "shared" / "data" / "kitti"
RECIPE_CROP = (320, 896)  # configs/kitti_weights.yaml, data.crop: [height, width]
RECIPE_LOSS = "l1"  # configs/kitti_weights.yaml, model.loss
SYNTHETIC_SEED = 0


def load_samples(root: Path, crop: tuple[int, int] | None, count: int | None = 1) -> tuple[list[Sample], str | None]:
    """The first ``count`` frames (None: all) of ``root/depth_selection/val_selection_cropped``, each cropped to
    its bottom-centre ``crop = (height, width)`` window (None: whole), and None; or, when that folder is absent
    or unreadable, the synthetic street ``make_scene(0)`` cropped the same way and a note saying so.

    Each :class:`~crfdepth.data.sample.Sample` holds (3, H, W) RGB in [0, 1], (1, H, W) sparse LiDAR and target
    depth in metres (0 = none) and the (3, 3) ``K`` of the window (``cx - left``, ``cy - top``).

    Raises:
        InputError: ``crop`` larger than the frame (named ``--crop``).
    """
    note = None
    try:
        selection = KittiValSelection(root / "depth_selection" / "val_selection_cropped")
        samples = [selection[i] for i in range(len(selection) if count is None else min(count, len(selection)))]
    except (FileNotFoundError, InputError) as err:
        note = f"no KITTI frame under {root} ({err}); using the synthetic street make_scene({SYNTHETIC_SEED})"
        t = make_scene(SYNTHETIC_SEED).to_tensors()
        samples = [Sample(image=t["image"], sparse=t["sparse"], target=t["target"], K=t["K"],
                          name=f"synthetic_street_{SYNTHETIC_SEED}")]
    if crop is None:
        return samples, note
    height, width = samples[0].size
    if crop[0] > height or crop[1] > width:
        raise InputError(f"--crop: expected HEIGHT WIDTH within the frame's {height} x {width} (HxW), "
                         f"got {crop[0]} {crop[1]}")
    return [BottomCenterCrop(*crop)(s) for s in samples], note


def training_model() -> torch.nn.Module:
    """The shipped model as the recipe's trainer holds it: ``CRFDepthModule(crf=<shipped config>, loss="l1",
    nll_weight=0)`` with the shipped weights loaded (its frozen parameters frozen), the CRF in train mode."""
    shipped = CRFDepth.from_pretrained("kitti")
    module = CRFDepthModule(crf=shipped.config, loss=RECIPE_LOSS, nll_weight=0.0, lr=0.02)
    module.model.load_state_dict(shipped.state_dict())
    return module.model.train()


def train_step(model: torch.nn.Module, sample: Sample) -> dict:
    """One forward and backward of ``model`` on ``sample`` (its batch of one): seconds of each, the L1 loss (m),
    and the CG iterations (max over the batch's graphs) and tolerances of every forward solve and its adjoint."""
    image, sparse, target = sample.image[None], sample.sparse[None], sample.target[None]
    model.zero_grad(set_to_none=True)
    with torch.enable_grad():
        start = time.perf_counter()
        out = model(image, sparse, sample.K)
        loss = depth_loss(out.depth, target, RECIPE_LOSS).mean()  # the trainer's objective at batch size 1
        forward = time.perf_counter() - start
        start = time.perf_counter()
        loss.backward()
        backward = time.perf_counter() - start
    missing = [i for i, info in enumerate(out.info) if info.adjoint is None]
    if missing:  # a solve the loss does not reach: the benchmark would time less than a training step
        raise RuntimeError(f"solves {missing} of the forward got no adjoint solve in backward")
    return dict(forward_s=forward, backward_s=backward, loss=float(loss.detach()),
                forward_iterations=[int(i.iterations.max()) for i in out.info],
                adjoint_iterations=[int(i.adjoint.iterations.max()) for i in out.info],
                forward_rtol=[i.rtol for i in out.info], adjoint_rtol=[i.adjoint.rtol for i in out.info],
                converged=all(bool(i.converged.all()) and bool(i.adjoint.converged.all()) for i in out.info))


def measure(model: torch.nn.Module, sample: Sample, repeats: int) -> dict:
    """One untimed warm-up step, then the medians (ms) of ``repeats`` timed steps and the last step's solves."""
    if not bool((sample.target > 0).any()):
        raise InputError(f"frame {sample.name!r}: expected ground-truth pixels (> 0) in the crop, got none")
    train_step(model, sample)
    steps = [train_step(model, sample) for _ in range(repeats)]
    totals = [s["forward_s"] + s["backward_s"] for s in steps]
    last = steps[-1]
    return dict(forward_ms=1e3 * statistics.median(s["forward_s"] for s in steps),
                backward_ms=1e3 * statistics.median(s["backward_s"] for s in steps),
                total_ms=1e3 * statistics.median(totals), total_spread_ms=[1e3 * min(totals), 1e3 * max(totals)],
                iterations=dict(forward=last["forward_iterations"], adjoint=last["adjoint_iterations"]),
                rtol=dict(forward=last["forward_rtol"], adjoint=last["adjoint_rtol"]),
                converged=last["converged"], loss_m=last["loss"], repeats=repeats)


def print_table(result: dict) -> None:
    print(f"{'step part':<10} {'median ms':>10}   CG iterations per solve (rtol)")
    print(f"{'forward':<10} {result['forward_ms']:>10.1f}   {result['iterations']['forward']} "
          f"({', '.join(f'{r:g}' for r in result['rtol']['forward'])})")
    print(f"{'backward':<10} {result['backward_ms']:>10.1f}   {result['iterations']['adjoint']} "
          f"({', '.join(f'{r:g}' for r in result['rtol']['adjoint'])}, adjoint)")
    low, high = result["total_spread_ms"]
    print(f"{'total':<10} {result['total_ms']:>10.1f}   spread {low:.1f}-{high:.1f} ms over {result['repeats']} steps; "
          f"L1 loss {result['loss_m']:.4f} m; all solves converged: {result['converged']}")


def main(argv: list[str] | None = None) -> int:
    parser = sa.ScriptParser(prog="train_step.py", description=__doc__.split("\n\n")[0])
    parser.add_argument("--threads", type=sa.count(1, sa.MAX_THREADS), default=2, help="torch CPU threads")
    parser.add_argument("--repeats", type=sa.count(1), default=5, help="timed steps after one warm-up")
    parser.add_argument("--crop", type=sa.count(8, 4096, "pixels"), nargs=2, default=RECIPE_CROP,
                        metavar=("HEIGHT", "WIDTH"), help="the bottom-centre training crop (the recipe's: 320 896)")
    parser.add_argument("--kitti-root", type=sa.folder("the KITTI sample folder"), default=DEFAULT_ROOT)
    args = parser.parse_args(argv)
    torch.set_num_threads(args.threads)
    crop = (int(args.crop[0]), int(args.crop[1]))
    samples, note = load_samples(args.kitti_root, crop)
    if note:
        print(f"note: {note}")
    sample = samples[0]
    result = measure(training_model(), sample, args.repeats)
    print(f"one training step of the shipped recipe (CRFDepthModule, loss {RECIPE_LOSS}, train mode), "
          f"{args.threads} threads, frame {sample.name}, crop {crop[0]} x {crop[1]} (HxW)")
    print_table(result)
    print(json.dumps(dict(frame=sample.name, synthetic=note is not None, crop=list(crop), threads=args.threads,
                          K=sample.K.tolist(), **result, torch=torch.__version__)))
    return 0


if __name__ == "__main__":
    sys.exit(sa.run_script(main, "train_step.py"))
