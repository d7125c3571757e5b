"""The protocols: which frames, inputs and targets each one builds.

Frames come from ``--kitti-root`` (default ``../shared/data/kitti`` next to this
repository), through :func:`crfdepth.data.factory.build_dataset`, all 1216 x 352:

- protocol **a**: official depth-completion input and semi-dense ground truth
  (``depth_selection/val_selection_cropped``, 2 frames: drive 0001 frame 5, cameras 2/3);
- protocol **b**: raw Velodyne scans (``raw/``: drives 0001 and 0060; ``object/training``)
  with a random 20% of the points held out as the target (``holdout="fraction"``);
- protocol **bu**: protocol b scored against the held-out points as they are
  (``clean_target=False``: see-through points kept);
- protocol **c**: the same scans keeping every 4th laser ring (16 beams) as the input,
  the other rings as the target (``holdout="rings", keep_every_ring=4``);
- protocol **s**: 12 built-in synthetic street scenes (seeds 1000-1011, no data folder),
  KITTI's 64-beam LiDAR mount with its see-through leaks, scored against the camera's
  true depth (``SyntheticScene.target()``): the one protocol besides (a) whose target is
  what the camera sees, and one the structure may be chosen on;
- protocol **q**: the reported block of the raw sequence ``sequences/`` (drive 0060 frames
  52-77; every recipe trains on frames 0-46 at most), the frame's own scan as input,
  scored against the camera-view targets that ``crfdepth targets`` accumulates from the
  scans around it (k = 5, poses from LiDAR odometry; made into ``--targets-root`` when
  missing, about 30 s): what the camera sees, on real frames, without annotation;
- protocols **a22** and **q22**: clean inputs. The frames of a and q with a random 22% of
  their target pixels (KITTI's annotation, the camera-view targets) as the input and the
  other 78% as the target: an input without see-through returns and off the laser rings
  (a LiDAR beside the camera, an input cleaned upstream).

- protocols **t500** and **t200**: the paper's Table 4 (after Sparse-to-Dense) on the raw scans of (b): the
  bottom-centre 912 x 228 of the frame, N = 500 or 200 pixels of the projected scan drawn at random as the
  input (:func:`crfdepth.data.sampling.kitti_table4`, seed 0 per frame name), the whole projected scan, as it
  is, as the target (the input's pixels included, as the paper scores it);
- protocols **n500** and **n200**: NYU Depth v2's protocol on the real frames of ``--nyu-root`` (default
  ``../shared/data/nyu``): resize to 320 x 240, centre crop 304 x 228, N samples of the depth as the input,
  all of it as the target (:func:`crfdepth.data.sampling.nyu_protocol`). The three ``official_test/basement``
  frames score against their Kinect depth with its holes, ``labeled_crop`` against the in-painted depth
  (``tiny`` is in neither layout and is left out).

Targets in b and c are raw LiDAR points (sparse, noisy), not KITTI's semi-dense
annotation, cleaned of see-through points against the whole scan
(``KittiRawScans(clean_target=True)``, the default); each frame's input and target pixels
are disjoint.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

import torch

from crfdepth.data.factory import build_dataset

REPORTED_BLOCK = (52, 77)  # protocol q: the frames of drive 0060 that no recipe trains on
TARGETS_DRIVE = "2011_09_26/2011_09_26_drive_0060_sync"  # under <kitti-root>/sequences
CLEAN_SHARE = 0.22  # protocols a22, q22: share of the target pixels given as the (clean) input
SYNTHETIC_SEED = 1000  # protocol s: scenes no recipe trains on (the trainer's synthetic validation seeds)
# protocol -> (title, [(group, layout, sub-folder (None: no data folder), dataset options)])
PROTOCOLS = {
    "a": ("(a) val_selection_cropped: official input, semi-dense ground truth",
          [("val", "val_selection", "depth_selection/val_selection_cropped", {})]),
    "b": ("(b) raw scans, 20% of the LiDAR points held out as target",
          [("raw", "raw", "raw", {"holdout": "fraction", "holdout_fraction": 0.2}),
           ("object", "object", "object/training", {"holdout": "fraction", "holdout_fraction": 0.2})]),
    "bu": ("(b) with uncleaned targets: the held-out points as they are, see-through points kept",
           [("raw", "raw", "raw", {"holdout": "fraction", "holdout_fraction": 0.2, "clean_target": False}),
            ("object", "object", "object/training",
             {"holdout": "fraction", "holdout_fraction": 0.2, "clean_target": False})]),
    "c": ("(c) raw scans, every 4th ring kept (16 beams), other rings as target",
          [("raw", "raw", "raw", {"holdout": "rings", "keep_every_ring": 4}),
           ("object", "object", "object/training", {"holdout": "rings", "keep_every_ring": 4})]),
    "s": ("(s) built-in synthetic street scenes (seeds 1000-1011): the camera's true depth as target",
          [("synthetic", "synthetic", None, {"count": 12, "seed": SYNTHETIC_SEED})]),
    "q": ("(q) drive 0060 frames 52-77: own scan in, its camera-view targets (crfdepth targets, k=5) as target",
          [("drive", "sequence", "sequences", {"frames": list(REPORTED_BLOCK)})]),
    "a22": ("(a22) the frames of (a), 22% of the ground truth as input, the other 78% as target",
            [("val", "val_selection", "depth_selection/val_selection_cropped", {"input_share": CLEAN_SHARE})]),
    "q22": ("(q22) the frames of (q), 22% of the camera-view targets as input, the other 78% as target",
            [("drive", "sequence", "sequences", {"frames": list(REPORTED_BLOCK), "input_share": CLEAN_SHARE})]),
}
for _n in (500, 200):
    PROTOCOLS[f"t{_n}"] = (
        f"(t{_n}) KITTI Table 4: bottom-centre 912x228, {_n} samples of the projected scan in, the whole scan as target",
        [(g, g, folder, {"holdout": "fraction", "holdout_fraction": 0.2, "clean_target": False, "table4": _n})
         for g, folder in (("raw", "raw"), ("object", "object/training"))])
    PROTOCOLS[f"n{_n}"] = (
        f"(n{_n}) NYU Depth v2: 320x240, centre 304x228, {_n} samples of the depth in, all of it as target",
        [("basement", "nyu_sync", "nyu:official_test", {"samples": _n}),
         ("dining", "nyu_raw", "nyu:labeled_crop", {"samples": _n})])
INDOOR_PROTOCOLS = ("n500", "n200")  # the default sends their frames to its indoor regime, fitted on them
# (protocol, evaluated group) -> training group of its learned weights ("shipped": the package's file)


def load_group(root: Path, layout: str, folder: str, options: dict, max_frames: int | None,
               keep_fraction: float = 1.0, targets_root: Path | None = None, nyu_root: Path | None = None) -> list:
    """Samples of one frame group, evenly spaced down to ``max_frames``; ``options["input_share"]``
    turns each into a clean-input sample (:func:`clean_input`), ``options["table4"]`` into the paper's
    Table 4 sample (:func:`table4_input`); a ``folder`` ``nyu:<sub-folder>`` is under ``nyu_root``."""
    options = dict(options)
    share = options.pop("input_share", None)
    table4 = options.pop("table4", None)
    if folder is not None and folder.startswith("nyu:"):
        root, folder = nyu_root, folder[len("nyu:"):]
    if layout in ("raw", "object"):
        options["keep_fraction"] = keep_fraction
    if layout == "sequence":
        options.update(targets_root=targets_root, offsets=[-1, 1])
    ds = build_dataset(layout, None if folder is None else root / folder, **options)
    idx = list(range(len(ds)))
    if max_frames is not None and len(idx) > max_frames:
        idx = sorted({round(i * (len(ds) - 1) / max(max_frames - 1, 1)) for i in range(max_frames)})
    if table4 is not None:
        return [table4_input(ds[i], table4) for i in idx]
    return [ds[i] if share is None else clean_input(ds[i], share, seed=i) for i in idx]


def table4_input(sample, samples: int):
    """A raw-scan sample (input and held-out points) as the paper's Table 4 scores it: the whole projected
    scan is the target, and ``samples`` of its pixels in the bottom-centre 912 x 228 are the input."""
    from crfdepth.data.sampling import kitti_table4

    whole = torch.where(sample.sparse > 0, sample.sparse, sample.target)
    return kitti_table4(samples, seed=0)(dataclasses.replace(sample, target=whole))


def clean_input(sample, share: float, seed: int):
    """``sample`` with a random ``share`` of its target pixels as the input and the rest as the target."""
    target = sample.target
    given = (target > 0) & (torch.rand(target.shape, generator=torch.Generator().manual_seed(seed)) < share)
    zero = torch.zeros_like(target)
    return dataclasses.replace(sample, sparse=torch.where(given, target, zero),
                               target=torch.where(given, zero, target), neighbours=None, poses=None)


def ensure_targets(args) -> Path:
    """The camera-view targets of the drive of protocol q under ``--targets-root``, made there by
    ``crfdepth targets`` (k = 5, LiDAR odometry) when missing."""
    drive = args.kitti_root / "sequences" / TARGETS_DRIVE
    if not (args.targets_root / drive.name / "poses.txt").is_file():
        from crfdepth.cli import main as cli

        code = cli(["targets", "--drive", str(drive), "--out-dir", str(args.targets_root), "--poses", "odometry",
                    "-k", "5", "--quiet"])
        if code:
            raise SystemExit(f"--targets-root: `crfdepth targets` failed on {drive} (exit {code})")
    return args.targets_root


def batch(s, device: str):
    return s.image[None].to(device), s.sparse[None].to(device), s.target[None].to(device), s.K.to(device)

