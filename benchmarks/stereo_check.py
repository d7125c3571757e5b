"""Targets checked against stereo (issue 38 part 3, docs/design.md section 16).

Measures :func:`crfdepth.sequences.stereo.stereo_check`:

- **Synthetic, against the truth.** A drive of :func:`crfdepth.data.synthetic.make_sequence` with a
  right camera (``stereo_baseline``, KITTI's 0.54 m) and moving cars. The returns of the scans
  ``index - k .. index + k`` are accumulated into frame ``index``'s camera with the true poses
  (:func:`crfdepth.sequences.targets.accumulate`), one return per pixel drawn at random (seeded),
  and each is labelled by the camera's true depth ``t`` at its pixel:

  - *good*: ``|z - t| <= 3% t + 0.05 m``;
  - *bad*: ``|z - t| > 10% t + 0.3 m``, split into *see-through* (a static return behind the
    surface the camera sees: past a foreground edge, or from another scan hidden from the camera),
    *mover* (a return of a moving car, from another scan: the car at another position) and
    *nearer* (a static return in front of it: a return rounded across a depth edge);
  - in between: neither, not counted.

  Reported: the share of bad returns removed (all, per kind, and among the informative ones:
  those stereo can judge), the share of good returns kept, and the same on the camera-view
  targets of section 14 (``camera_view_targets``, the targets ``crfdepth targets`` writes).
- **Drive 0048** (``../shared/data/kitti/stereo``: three frames with both colour cameras). Per
  frame: the share of returns dropped from the whole projected scan, from the 20% hold-out
  targets of :class:`crfdepth.data.kitti.KittiRawScans` (see-through cleaned, uncropped), and
  from the camera-view targets (``k = 1``, LiDAR odometry over the three scans); with
  ``--pictures DIR``, a picture per frame of what it drops: the left image darkened, kept
  returns green, dropped returns red.

Prints a table and one JSON line.

    python benchmarks/stereo_check.py [--seeds 0 1 2] [--size 176 608] [--kitti ../shared/data/kitti]
        [--pictures docs/results/stereo_check] [--threads 2]
"""

from __future__ import annotations

import json
import sys
import time
from dataclasses import asdict, dataclass
from pathlib import Path

import cv2
import numpy as np
import torch

from crfdepth.data.kitti import KittiRawScans
from crfdepth.data.synthetic import make_sequence
from crfdepth.geometry import projection
from crfdepth.io.calibration import RigCalibration, read_raw_calibration
from crfdepth.io.kitti import read_rgb, read_velodyne
from crfdepth.sequences.odometry import lidar_odometry_with_fallback
from crfdepth.sequences.stereo import baseline_from_projections, stereo_check
from crfdepth.sequences.targets import accumulate, camera_view_targets

if str(Path(__file__).resolve().parent) not in sys.path:  # a load by the file's path (the tests) has not
    sys.path.append(str(Path(__file__).resolve().parent))

import script_args as sa  # noqa: E402  (benchmarks/script_args.py: one-line errors, checked option types)

REPO = Path(__file__).resolve().parents[1]
DEFAULT_KITTI = REPO.parent / "shared" / "data" / "kitti"
DRIVE = "2011_09_26_drive_0048_sync"
BASELINE_M = 0.54
GOOD, SEE_THROUGH, MOVER, NEARER = 1, 2, 3, 4  # labels of the synthetic returns; 0 = not counted
KINDS = {SEE_THROUGH: "see_through", MOVER: "mover", NEARER: "nearer"}


# --------------------------------------------------------------------------- synthetic


def label(z: np.ndarray, truth: np.ndarray, mover: np.ndarray) -> np.ndarray:
    """(N,) uint8 label of returns at depth ``z`` against the true depth ``truth`` at their pixels (0 =
    sky), ``mover``: the return hit a moving car (module docstring)."""
    out = np.zeros(len(z), np.uint8)
    seen = truth > 0
    out[seen & (np.abs(z - truth) <= 0.03 * truth + 0.05)] = GOOD
    bad = ~seen | (np.abs(z - truth) > 0.10 * truth + 0.3)
    out[bad & mover] = MOVER
    out[bad & ~mover & (~seen | (z > truth))] = SEE_THROUGH
    out[bad & ~mover & seen & (z < truth)] = NEARER
    return out


def accumulated_returns(seq, index: int, k: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """(H, W) float32 depth holding one accumulated return per pixel (drawn at random) and (H, W) its label."""
    frame = seq[index]
    cam, _, window = accumulate([f.points for f in seq], seq.lidar_poses(), frame.T_cam_lidar, index, k=k)
    # A moving car's return counts as a mover's from any scan but the frame's own.
    mover = np.concatenate([(seq[s].mover_points >= 0) & (s != index) for s in window])
    h, w = frame.depth.shape
    K = frame.K
    z = cam[:, 2]
    front = z > 0.1
    zs = np.where(front, z, 1.0)
    u = np.rint(K[0, 0] * cam[:, 0] / zs + K[0, 2]).astype(np.int64)
    v = np.rint(K[1, 1] * cam[:, 1] / zs + K[1, 2]).astype(np.int64)
    inside = np.flatnonzero(front & (u >= 0) & (u < w) & (v >= 0) & (v < h))
    inside = inside[np.random.default_rng(seed).permutation(len(inside))]
    _, first = np.unique(v[inside] * w + u[inside], return_index=True)
    pick = inside[first]
    depth = np.zeros((h, w), np.float32)
    depth[v[pick], u[pick]] = z[pick]
    kinds = np.zeros((h, w), np.uint8)
    kinds[v[pick], u[pick]] = label(z[pick], frame.depth[v[pick], u[pick]], mover[pick])
    return depth, kinds


def _tensors(frame) -> tuple[torch.Tensor, torch.Tensor]:
    return (torch.from_numpy(np.ascontiguousarray(frame.image.transpose(2, 0, 1))),
            torch.from_numpy(np.ascontiguousarray(frame.right_image.transpose(2, 0, 1))))


@dataclass
class Scores:
    """What the check did to one labelled set of returns."""

    good: int
    bad: int
    good_kept: float
    bad_removed: float
    bad_informative: float  # share of the bad returns stereo could judge
    bad_removed_informative: float  # share of those it removed
    removed: dict  # per kind of bad return: share removed
    counts: dict  # per kind: returns


def scores(kinds: np.ndarray, dropped: np.ndarray, informative: np.ndarray) -> Scores:
    good, bad = kinds == GOOD, kinds >= SEE_THROUGH

    def share(mask, of):
        return float(mask[of].mean()) if of.any() else 0.0

    return Scores(good=int(good.sum()), bad=int(bad.sum()), good_kept=1.0 - share(dropped, good),
                  bad_removed=share(dropped, bad), bad_informative=share(informative, bad),
                  bad_removed_informative=share(dropped, bad & informative),
                  removed={name: share(dropped, kinds == code) for code, name in KINDS.items()},
                  counts={name: int((kinds == code).sum()) for code, name in KINDS.items()})


@dataclass
class SyntheticResult:
    seed: int
    accumulated: Scores  # one accumulated return per pixel
    targets: Scores  # camera-view targets (section 14)
    seconds: float  # the two checks


def measure_synthetic(seed: int, *, n_frames: int = 9, index: int = 4, k: int = 4, size=(176, 608), movers: int = 2,
                      seq=None, pictures: Path | None = None) -> SyntheticResult:
    """Both labelled sets of one synthetic drive (module docstring); ``seq``: a drive already made; ``pictures``:
    a folder for a picture of the accumulated set: good returns kept green, dropped magenta; bad returns
    dropped red, kept yellow."""
    if seq is None:
        seq = make_sequence(n_frames, seed, height=size[0], width=size[1], movers=movers, stereo_baseline=BASELINE_M)
    frame = seq[index]
    left, right = _tensors(frame)
    depth, kinds = accumulated_returns(seq, index, k, seed)
    start = time.perf_counter()
    check = stereo_check(torch.from_numpy(depth), left, right, frame.K, frame.baseline_m)
    dropped = check.dropped[0, 0].numpy()
    accumulated = scores(kinds, dropped, check.informative[0, 0].numpy())
    if pictures is not None:
        good, bad = kinds == GOOD, kinds >= SEE_THROUGH
        picture(np.round(frame.image * 255).astype(np.uint8),
                [(good & ~dropped, GREEN), (bad & ~dropped, YELLOW), (good & dropped, MAGENTA), (bad & dropped, RED)],
                pictures / f"synthetic_seed{seed}.png", scale=2, grow_last=False)
    targets = camera_view_targets([f.points for f in seq], seq.lidar_poses(), frame.T_cam_lidar, frame.K,
                                  frame.depth.shape, index, k=k).depth.astype(np.float32)
    has = targets > 0
    own_kinds = np.zeros(targets.shape, np.uint8)
    # A target's source scan is not kept: its bad pixels are see-through (behind) or nearer, no mover kind.
    own_kinds[has] = label(targets[has], frame.depth[has], np.zeros(int(has.sum()), bool))
    check = stereo_check(torch.from_numpy(targets), left, right, frame.K, frame.baseline_m)
    cleaned = scores(own_kinds, check.dropped[0, 0].numpy(), check.informative[0, 0].numpy())
    return SyntheticResult(seed, accumulated, cleaned, time.perf_counter() - start)


# --------------------------------------------------------------------------- drive 0048


@dataclass
class KittiFrame:
    frame: str
    scan_returns: int
    scan_dropped: float
    holdout_returns: int
    holdout_dropped: float
    targets_returns: int
    targets_dropped: float
    seconds: float  # the three checks


def picture(rgb: np.ndarray, layers: list[tuple[np.ndarray, tuple[int, int, int]]], path: Path, scale: int = 1,
            grow_last: bool = True) -> None:
    """The image darkened to grey (16 levels: a small PNG), with each (H, W) bool mask of ``layers`` painted in
    its RGB colour, in order (``grow_last``: the last layer's pixels grown to 3x3), then scaled by ``scale``."""
    grey = cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY)
    out = np.repeat((grey // 16 * 7 + 20).astype(np.uint8)[:, :, None], 3, axis=2)
    for k, (mask, colour) in enumerate(layers):
        if grow_last and k == len(layers) - 1:
            mask = cv2.dilate(mask.astype(np.uint8), np.ones((3, 3), np.uint8)) > 0
        out[mask] = colour
    if scale > 1:
        out = np.repeat(np.repeat(out, scale, axis=0), scale, axis=1)
    path.parent.mkdir(parents=True, exist_ok=True)
    cv2.imwrite(str(path), cv2.cvtColor(out, cv2.COLOR_RGB2BGR), [cv2.IMWRITE_PNG_COMPRESSION, 9])


GREEN, RED, YELLOW, MAGENTA = (0, 200, 0), (255, 0, 0), (255, 230, 0), (255, 0, 255)


def measure_kitti(root: Path, pictures: Path | None = None, frames: list[int] | None = None) -> list[KittiFrame]:
    """Drive 0048 of ``root/stereo`` (module docstring); ``frames``: indices of the frames measured (None: all)."""
    day = root / "stereo" / "2011_09_26"
    drive = day / DRIVE
    left_cal, right_cal = read_raw_calibration(day, 2), read_raw_calibration(day, 3)
    baseline = baseline_from_projections(left_cal.P_rect, right_cal.P_rect)
    stems = sorted(p.stem for p in (drive / "velodyne_points" / "data").glob("*.bin"))
    scans = [read_velodyne(drive / "velodyne_points" / "data" / f"{s}.bin") for s in stems]
    odometry, _ = lidar_odometry_with_fallback(scans, threads=1)
    rig = RigCalibration.from_kitti(left_cal)
    holdouts = KittiRawScans(root / "stereo", layout="raw", transform=None)
    rows = []
    for i, stem in enumerate(stems):
        if frames is not None and i not in frames:
            continue
        rgb = read_rgb(drive / "image_02" / "data" / f"{stem}.png")
        images = [torch.from_numpy(x).permute(2, 0, 1).float() / 255.0
                  for x in (rgb, read_rgb(drive / "image_03" / "data" / f"{stem}.png"))]
        scan = projection.project_velodyne(scans[i], left_cal, rgb.shape[:2])
        holdout = holdouts[i].target[0].numpy()
        targets = camera_view_targets(scans, odometry.poses, rig.T_cam_lidar, rig.K, rgb.shape[:2], i, k=1).depth
        start = time.perf_counter()
        result = []
        for name, depth in (("scan", scan), ("holdout", holdout), ("targets", targets.astype(np.float32))):
            dropped = stereo_check(torch.from_numpy(depth), images[0], images[1], left_cal.K,
                                   baseline).dropped[0, 0].numpy()
            result += [int((depth > 0).sum()), float(dropped.sum() / max(1, (depth > 0).sum()))]
            if pictures is not None and name != "holdout":  # kept green, dropped red
                picture(rgb, [((depth > 0) & ~dropped, GREEN), (dropped, RED)],
                        pictures / f"drive0048_{stem}_{name}.png")
        rows.append(KittiFrame(stem, *result, time.perf_counter() - start))
    return rows


# --------------------------------------------------------------------------- report


def main(argv: list[str] | None = None) -> int:
    parser = sa.ScriptParser(prog="stereo_check.py", description=__doc__.split("\n\n")[0])
    parser.add_argument("--seeds", type=sa.seed, nargs="*", default=[0, 1, 2])
    parser.add_argument("--size", type=sa.count(64, 4096, "pixels"), nargs=2, default=(176, 608), metavar=("HEIGHT", "WIDTH"))
    parser.add_argument("--kitti", type=Path, default=DEFAULT_KITTI, help="the KITTI sample root ('' to skip)")
    parser.add_argument("--pictures", type=sa.out_folder, default=None)
    parser.add_argument("--threads", type=sa.count(1, sa.MAX_THREADS), default=1)
    args = parser.parse_args(argv)
    kitti = args.kitti if str(args.kitti) not in ("", ".") else None
    if kitti is not None and not (kitti / "stereo" / "2011_09_26" / DRIVE).is_dir():
        parser.error(f"--kitti: expected the KITTI sample root holding stereo/2011_09_26/{DRIVE}, got {kitti}")
    torch.set_num_threads(args.threads)
    synthetic = [measure_synthetic(seed, size=tuple(args.size), pictures=args.pictures) for seed in args.seeds]
    real = measure_kitti(kitti, args.pictures) if kitti is not None else []

    print(f"synthetic {args.size[0]}x{args.size[1]}, frame 4 of 9, k = 4, 2 movers, baseline {BASELINE_M} m")
    print(f"{'seed':>4s} {'set':12s} {'good':>6s} {'bad':>5s} {'good kept':>9s} {'bad removed':>11s} "
          f"{'informative':>11s} {'of those':>8s} {'see-through':>11s} {'mover':>6s} {'nearer':>6s}")
    for r in synthetic:
        for name, s in (("accumulated", r.accumulated), ("targets", r.targets)):
            print(f"{r.seed:4d} {name:12s} {s.good:6d} {s.bad:5d} {s.good_kept:9.4f} {s.bad_removed:11.3f} "
                  f"{s.bad_informative:11.3f} {s.bad_removed_informative:8.3f} {s.removed['see_through']:11.3f} "
                  f"{s.removed['mover']:6.3f} {s.removed['nearer']:6.3f}")
    if real:
        print("drive 0048: share of returns dropped (returns)")
        print(f"{'frame':10s} {'scan':>14s} {'hold-out':>14s} {'targets k=1':>14s}")
        for r in real:
            print(f"{r.frame:10s} {r.scan_dropped:7.4f} ({r.scan_returns:5d}) {r.holdout_dropped:7.4f} "
                  f"({r.holdout_returns:5d}) {r.targets_dropped:7.4f} ({r.targets_returns:5d})")
    print(json.dumps(dict(size=list(args.size), synthetic=[asdict(r) for r in synthetic],
                          kitti=[asdict(r) for r in real])))
    return 0


if __name__ == "__main__":
    raise SystemExit(sa.run_script(main, "stereo_check.py"))
