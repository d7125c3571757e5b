"""SequenceFrames (layout "sequence"): a synthetic drive written in KITTI's raw layout with its
camera-view targets made by ``crfdepth targets`` from the true poses; the pose chain checked against
the true poses and by warping the neighbours with the true depth; the density augmentation; bad input."""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pytest
import torch

from crfdepth.data import HorizontalFlip, RandomCrop, build_dataset, collate_samples
from crfdepth.data.sequences import SequenceFrames, colour_camera_poses
from crfdepth.data.synthetic import make_sequence
from crfdepth.errors import InputError
from crfdepth.io.calibration import Calibration
from crfdepth.io.kitti import read_depth_png
from crfdepth.sequences.photometric import photometric_loss
from tests.sequence_drive import DRIVE, make_targets, stem, write_drive

N_FRAMES = 6


@pytest.fixture(scope="module")
def sequence():
    return make_sequence(N_FRAMES, 0, height=176, width=608, movers=0, image_noise_std=0.0)


@pytest.fixture(scope="module")
def drive_and_targets(tmp_path_factory, sequence) -> tuple[Path, Path]:
    root = tmp_path_factory.mktemp("seq")
    drive = write_drive(root / "raw", sequence)
    return drive, make_targets(drive, root / "targets", k=2)


def dataset(drive_and_targets, **options) -> SequenceFrames:
    drive, targets = drive_and_targets
    return build_dataset("sequence", drive.parent.parent, targets_root=targets, transform=None, **options)


def name(i: int) -> str:
    return f"{DRIVE}_{stem(i)}_image_02"


def test_frames_neighbours_and_true_poses(drive_and_targets, sequence):
    ds = dataset(drive_and_targets)
    # the ends have no neighbour on one side: dropped
    assert ds.names == [name(i) for i in range(1, N_FRAMES - 1)]
    assert ds.dropped == [name(0), name(N_FRAMES - 1)]
    _, targets = drive_and_targets
    for j, t in enumerate(range(1, N_FRAMES - 1)):
        s = ds[j]
        f = sequence[t]
        assert s.neighbours.shape == (2, 3, 176, 608) and s.poses.shape == (2, 4, 4)
        # the image, the neighbours' images (8-bit PNGs: within half a level)
        assert float((s.image - torch.from_numpy(f.image).permute(2, 0, 1)).abs().max()) < 0.6 / 255
        for k, o in enumerate((-1, 1)):
            truth = torch.from_numpy(sequence[t + o].image).permute(2, 0, 1).float()
            assert float((s.neighbours[k] - truth).abs().max()) < 0.6 / 255
            # T_cam(s)<-cam(t) from poses.txt = the true relative pose (1 m along z per frame at 10 m/s, 10 Hz)
            true = np.linalg.inv(sequence[t + o].T_w_cam) @ f.T_w_cam
            np.testing.assert_allclose(s.poses[k].numpy(), true, atol=1e-5)
        assert abs(float(s.poses[0, 2, 3]) - 1.0) < 1e-5 and abs(float(s.poses[1, 2, 3]) + 1.0) < 1e-5
        # target = the camera-view target written by crfdepth targets; sparse = the frame's own scan
        target = read_depth_png(targets / DRIVE / "proj_depth" / "groundtruth" / "image_02" / f"{stem(t)}.png")
        np.testing.assert_array_equal(s.target[0].numpy(), target)
        assert abs(float((s.sparse > 0).float().mean()) - float((f.sparse > 0).mean())) < 0.01
        assert torch.allclose(s.K, torch.from_numpy(f.K).float())


def test_neighbours_warp_into_the_frame_with_the_true_depth(drive_and_targets, sequence):
    ds = dataset(drive_and_targets)
    batch = collate_samples([ds[j] for j in range(len(ds))])
    assert batch.neighbours.shape == (len(ds), 2, 3, 176, 608) and batch.poses.shape == (len(ds), 2, 4, 4)
    depth = torch.from_numpy(np.stack([sequence[t].depth for t in range(1, N_FRAMES - 1)]))[:, None].float()
    mask = torch.isfinite(depth) & (depth > 0)  # the sky has no depth
    depth = torch.where(mask, depth, torch.full_like(depth, 100.0))

    def loss(d, poses):
        return photometric_loss(batch.image, batch.neighbours, d, batch.K, poses, mask=mask, reduction="frame")

    true = loss(depth, batch.poses)
    # measured 0.0069-0.0075 per frame (bilinear resampling and 8-bit PNGs of the rendered textures)
    assert float(true.max()) < 0.01, true
    # a wrong chain (the poses inverted: neighbours warped the wrong way; measured 0.037-0.038) or a wrong
    # depth (x 1.3; measured 0.017-0.019) is far worse
    inverted = torch.linalg.inv(batch.poses)
    assert bool((loss(depth, inverted) > 3 * true).all()), (loss(depth, inverted), true)
    assert bool((loss(depth * 1.3, batch.poses) > 2 * true).all()), (loss(depth * 1.3, batch.poses), true)


def test_colour_camera_chain_with_a_baseline():
    K = np.array([[700.0, 0, 600], [0, 700.0, 180], [0, 0, 1]])
    t2 = np.array([0.06, -0.001, 0.0027])  # camera 2 sits 6 cm left of camera 0 (KITTI: P_rect_02[0, 3] = 44.9)
    calib = Calibration(P_rect=np.hstack([K, (K @ t2)[:, None]]), R_rect=np.eye(4), T_velo_to_cam=np.eye(4))
    yaw = np.deg2rad(5)
    P1 = np.eye(4)
    P1[:3, :3] = [[np.cos(yaw), 0, np.sin(yaw)], [0, 1, 0], [-np.sin(yaw), 0, np.cos(yaw)]]
    P1[:3, 3] = [0.2, 0.0, 1.0]
    C = colour_camera_poses(np.stack([np.eye(4), P1]), calib)
    rel = np.linalg.inv(C[0]) @ C[1]  # T_cam2(0)<-cam2(1)
    # a point fixed in the world: seen from camera 2 at time 1, moved into camera 2 at time 0 by hand
    x_cam2_1 = np.array([1.0, 0.5, 10.0, 1.0])
    x_rect0_1 = x_cam2_1 - np.r_[t2, 0]
    x_rect0_0 = P1 @ x_rect0_1
    x_cam2_0 = x_rect0_0 + np.r_[t2, 0]
    np.testing.assert_allclose(rel @ x_cam2_1, x_cam2_0, atol=1e-12)
    assert np.abs(rel[:3, 3] - P1[:3, 3]).max() > 1e-3  # the baseline matters once the camera turns


def test_flip_and_crop_keep_the_pose_chain(drive_and_targets, sequence):
    ds = dataset(drive_and_targets)
    s = ds[1]
    flipped = HorizontalFlip(p=1.0)(s)
    cropped = RandomCrop(128, 480, generator=torch.Generator().manual_seed(0))(s)
    assert cropped.neighbours.shape == (2, 3, 128, 480)
    t = 2
    depth = torch.from_numpy(sequence[t].depth)[None, None].float()
    mask = torch.isfinite(depth) & (depth > 0)
    depth = torch.where(mask, depth, torch.full_like(depth, 100.0))

    def loss(x, d, m):
        return float(photometric_loss(x.image[None], x.neighbours[None], d, x.K, x.poses[None], mask=m))

    base = loss(s, depth, mask)
    # the same error after a flip (mirrored images, mirrored poses; measured 0.00707 both) and in a crop
    assert base < 0.01 and abs(loss(flipped, depth.flip(-1), mask.flip(-1)) - base) < 0.01 * base
    top = int(round(float(s.K[1, 2] - cropped.K[1, 2])))
    left = int(round(float(s.K[0, 2] - cropped.K[0, 2])))
    window = (..., slice(top, top + 128), slice(left, left + 480))
    assert loss(cropped, depth[window], mask[window]) < 1.5 * base


def test_density_augmentation(drive_and_targets):
    full = dataset(drive_and_targets, seed=0)[0].sparse
    n_full = int((full > 0).sum())
    sixteen = dataset(drive_and_targets, beams=[16], seed=0)[0].sparse
    half = dataset(drive_and_targets, keep_fraction=[0.5, 0.5], seed=0)[0].sparse
    # every 4th ring: about a quarter of the pixels; half of the points: about half (measured 0.25, 0.50)
    assert 0.18 < int((sixteen > 0).sum()) / n_full < 0.32, (int((sixteen > 0).sum()), n_full)
    assert 0.45 < int((half > 0).sum()) / n_full < 0.55
    # input pixels are a subset of the full scan's, with the same depths
    kept = sixteen > 0
    assert torch.equal(sixteen[kept], full[kept])
    # a fixed seed repeats the draw; None draws from torch's RNG
    again = dataset(drive_and_targets, beams=[16, 32, 64], keep_fraction=[0.3, 1.0], seed=3)
    assert torch.equal(again[0].sparse, again[0].sparse)
    free = dataset(drive_and_targets, beams=[16, 32, 64], keep_fraction=[0.3, 1.0])
    torch.manual_seed(0)
    counts = {int((free[0].sparse > 0).sum()) for _ in range(4)}
    assert len(counts) > 1


def test_clean_input_from_the_camera_view_target(drive_and_targets):
    whole = dataset(drive_and_targets, seed=0)[0].target
    item = dataset(drive_and_targets, target_input=1.0, target_input_fraction=[0.25, 0.25], seed=0)[0]
    n = int((whole > 0).sum())
    given, left = item.sparse > 0, item.target > 0
    # a quarter of the target pixels become the input, with their target depths; the rest stay the target
    assert abs(int(given.sum()) - 0.25 * n) <= 1, (int(given.sum()), n)
    assert not bool((given & left).any())
    assert torch.equal(given | left, whole > 0)
    assert torch.equal(item.sparse[given], whole[given]) and torch.equal(item.target[left], whole[left])
    # probability 0.5: both kinds of input occur over the frames' draws
    mixed = dataset(drive_and_targets, target_input=0.5, seed=0)
    kinds = {bool(((mixed[i].sparse > 0) & (mixed[i].target > 0)).any()) for i in range(len(mixed))}
    assert kinds == {True, False}


# --------------------------------------------------------------------------- bad input


def test_frame_without_its_target(drive_and_targets, tmp_path):
    drive, targets = drive_and_targets
    copy = tmp_path / "targets"
    shutil.copytree(targets, copy)
    (copy / DRIVE / "proj_depth" / "groundtruth" / "image_02" / f"{stem(2)}.png").unlink()
    with pytest.raises(InputError) as info:
        SequenceFrames(drive.parent.parent, targets_root=copy, transform=None)
    missing = copy / DRIVE / "proj_depth" / "groundtruth" / "image_02" / f"{stem(2)}.png"
    assert str(info.value) == (
        f"targets_root: expected the camera-view target of frame {stem(2)} of {DRIVE}, got no {missing}; make it "
        f"with `crfdepth targets --drive {drive} --out-dir {copy}`")


def test_drive_without_targets(drive_and_targets, tmp_path):
    drive, _ = drive_and_targets
    (tmp_path / "empty").mkdir()
    with pytest.raises(InputError) as info:
        SequenceFrames(drive.parent.parent, targets_root=tmp_path / "empty")
    assert str(info.value) == (
        f"targets_root: expected the camera-view targets of {DRIVE} in {tmp_path / 'empty' / DRIVE} (with poses.txt), "
        f"got no {tmp_path / 'empty' / DRIVE / 'poses.txt'}; make them with `crfdepth targets --drive {drive} "
        f"--out-dir {tmp_path / 'empty'}`")
    with pytest.raises(InputError, match=r"^targets_root: expected the --out-dir folder of `crfdepth targets`"):
        build_dataset("sequence", drive.parent.parent)


def test_poses_with_the_wrong_count(drive_and_targets, tmp_path):
    drive, targets = drive_and_targets
    copy = tmp_path / "targets"
    shutil.copytree(targets, copy)
    poses = copy / DRIVE / "poses.txt"
    poses.write_text("".join(poses.read_text().splitlines(keepends=True)[:-1]))
    with pytest.raises(InputError) as info:
        SequenceFrames(drive.parent.parent, targets_root=copy)
    assert str(info.value) == (
        f"targets_root: expected {N_FRAMES} poses in {poses} (frames 0 to {N_FRAMES - 1}, one per line), got "
        f"{N_FRAMES - 1}; rerun `crfdepth targets --drive {drive} --out-dir {copy}`")


def test_frames_block_and_ends(drive_and_targets):
    ds = dataset(drive_and_targets, frames=[0, 3])
    assert ds.names == [name(1), name(2)]  # frame 3's neighbour 4 is outside the block
    assert dataset(drive_and_targets, offsets=[-2, -1]).names == [name(i) for i in range(2, N_FRAMES)]
    with pytest.raises(InputError, match=r"^offsets: no frame under .* has all its neighbours \[-1, 1\] within "
                                         r"frames \(2, 3\) \(2 frame\(s\) dropped at the ends\)$"):
        dataset(drive_and_targets, frames=[2, 3])
    for options, message in (
        ({"offsets": [0, 1]}, r"^offsets: expected distinct non-zero integers \(frames from t\), got \[0, 1\]$"),
        ({"beams": [24]}, r"^beams: expected a list of ring counts dividing 64 \(e.g. \[16, 32, 64\]\), got \[24\]$"),
        ({"keep_fraction": [0.8, 0.2]}, r"^keep_fraction: expected \[low, high\] with 0 < low <= high <= 1, got"),
        ({"frames": [3, 1]}, r"^frames: expected \[first, last\] frame numbers with 0 <= first <= last, got"),
        ({"target_input": 1.5}, r"^target_input: expected a probability in \[0, 1\], got 1.5$"),
        ({"target_input_fraction": [0.2, 1.0]}, r"^target_input_fraction: expected \[low, high\] with 0 < low <= "
                                                r"high < 1, got \[0.2, 1.0\]$"),
    ):
        with pytest.raises(InputError, match=message):
            dataset(drive_and_targets, **options)


def test_collate_refuses_mixed_samples(drive_and_targets):
    s = dataset(drive_and_targets)[0]
    import dataclasses

    plain = dataclasses.replace(s, neighbours=None, poses=None)
    batch = collate_samples([plain])
    assert batch.neighbours is None and batch.poses is None
    with pytest.raises(InputError, match="expected the same number of neighbours in every sample"):
        collate_samples([s, plain])
    with pytest.raises(InputError, match=r"^Sample.poses: expected poses exactly when neighbours are given"):
        dataclasses.replace(s, poses=None)
    moved = collate_samples([s]).to(torch.float64)
    assert moved.neighbours.dtype == torch.float64 and moved.poses.shape == (1, 2, 4, 4)


@pytest.mark.slow
def test_evaluate_scores_a_checkpoint_against_the_camera_view_targets(tmp_path, capsys):
    """crfdepth evaluate --layout sequence: the targets of crfdepth targets are the ground truth (at the
    KITTI size, which the layout's benchmark crop needs)."""
    import json

    from crfdepth.cli import main

    drive = write_drive(tmp_path / "raw", make_sequence(4, 0, movers=0))
    targets = make_targets(drive, tmp_path / "targets", k=1)
    argv = ["evaluate", "--layout", "sequence", "--data", str(drive.parent.parent), "--out-dir", str(tmp_path / "ev"),
            "--quiet"]
    assert main(argv) == 2
    assert capsys.readouterr().err.splitlines()[0] == (
        "crfdepth evaluate: error: --targets-root: required with --layout sequence (the --out-dir of 'crfdepth "
        "targets', whose camera-view targets are scored)")
    assert main([*argv, "--targets-root", str(targets)]) == 0
    summary = json.loads(next((tmp_path / "ev").glob("*.json")).read_text())
    assert summary["frames"] == 2  # frames 1 and 2: the ends lack a neighbour
    assert 0 < summary["metrics"]["rmse"] < 5000  # mm: the synthetic street completed against its targets
