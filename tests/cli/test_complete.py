"""Tests of ``crfdepth complete`` (crfdepth.cli.complete).

Real frames: the two ``val_selection_cropped`` frames of the shared KITTI data. Bad-input
and checkpoint tests use a small synthetic frame written to ``tmp_path`` (fast, and
independent of the shared data).
"""

from __future__ import annotations

import datetime
import os
import pickle
import shutil
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch

from crfdepth import cli
from crfdepth.checkpoints import save_model
from crfdepth.fill.nearest import nearest_fill
from crfdepth.io.kitti import read_depth_png, write_depth_png
from crfdepth.metrics import depth_metrics
from crfdepth.model import CRFDepth
from crfdepth.runs.resume import RUN_RECORD
from crfdepth.weights import weights_path

STEM = "2011_09_26_drive_0001_sync_{kind}_0000000005_image_0{cam}"
# Cheap model options for tests about files and names rather than accuracy.
FAST = ["--no-refine", "--potentials", "colour", "--quiet"]


def test_complete_is_registered():
    assert "crfdepth.cli.complete" in cli._COMMANDS


@pytest.fixture
def main(monkeypatch):
    """``crfdepth.cli.main`` with only this sub-command registered (another sub-command's
    import cannot make these tests fail)."""
    monkeypatch.setattr(cli, "_COMMANDS", ("crfdepth.cli.complete",))
    return cli.main


@pytest.fixture
def val_dir(kitti_root) -> Path:
    return kitti_root / "depth_selection" / "val_selection_cropped"


def _val_frame(val_dir: Path, cam: int = 2) -> dict[str, Path]:
    return {
        "image": val_dir / "image" / f"{STEM.format(kind='image', cam=cam)}.png",
        "sparse": val_dir / "velodyne_raw" / f"{STEM.format(kind='velodyne_raw', cam=cam)}.png",
        "intrinsics": val_dir / "intrinsics" / f"{STEM.format(kind='image', cam=cam)}.txt",
        "target": val_dir / "groundtruth_depth" / f"{STEM.format(kind='groundtruth_depth', cam=cam)}.png",
    }


def _one(frame: dict, out, *extra) -> list[str]:
    return ["complete", "--image", str(frame["image"]), "--sparse", str(frame["sparse"]),
            "--intrinsics", str(frame["intrinsics"]), "--out", str(out), *map(str, extra)]


def _files(folder: Path) -> list[str]:
    """Every file under ``folder`` (hidden temporary files included), relative, sorted."""
    return sorted(str(p.relative_to(folder)) for p in folder.rglob("*") if p.is_file())


# --------------------------------------------------------------------------- real frames


@pytest.mark.kitti
def test_complete_real_frame_beats_nearest_fill(main, val_dir, tmp_path):
    frame = _val_frame(val_dir)
    out, out_std, vis = tmp_path / "depth.png", tmp_path / "std.png", tmp_path / "vis"
    assert main(_one(frame, out, "--out-std", out_std, "--vis", vis)) == 0

    raw = cv2.imread(str(out), cv2.IMREAD_UNCHANGED)
    assert raw.dtype == np.uint16 and raw.shape == (352, 1216)
    assert raw.min() > 0  # dense: every pixel has a depth
    depth = torch.from_numpy(read_depth_png(out))
    target = torch.from_numpy(read_depth_png(frame["target"]))
    sparse = torch.from_numpy(read_depth_png(frame["sparse"]))
    rmse = float(depth_metrics(depth, target)["rmse"][0])
    rmse_nn = float(depth_metrics(nearest_fill(sparse), target)["rmse"][0])
    assert rmse < rmse_nn  # measured: 1107 mm against 1324 mm
    assert rmse < 0.9 * rmse_nn
    # LiDAR pixels keep (close to) their measured depth.
    on_lidar = sparse > 0
    assert float((depth - sparse)[on_lidar].abs().median()) < 0.1

    raw_std = cv2.imread(str(out_std), cv2.IMREAD_UNCHANGED)
    assert raw_std.dtype == np.uint16 and raw_std.shape == (352, 1216) and raw_std.min() > 0
    std = read_depth_png(out_std)
    # Posterior std: small where LiDAR is, larger above the top LiDAR row (sky, trees).
    assert np.median(std[on_lidar.numpy()]) < np.median(std[:60])
    assert 0.01 < np.median(std) < 10.0

    assert _files(vis) == ["depth_vis_depth.png", "depth_vis_std.png"]
    for name in _files(vis):
        picture = cv2.imread(str(vis / name), cv2.IMREAD_UNCHANGED)
        # the map (352 x 1216) with a colour bar in metres below it
        assert picture.dtype == np.uint8 and picture.shape[1:] == (1216, 3) and 352 < picture.shape[0] < 500
    picture = cv2.cvtColor(cv2.imread(str(vis / "depth_vis_depth.png")), cv2.COLOR_BGR2RGB).astype(int)[:352]
    near, far = picture[-10:, 500:700].mean((0, 1)), picture[:60, 500:700].mean((0, 1))
    assert near[0] > near[2] and far[2] > far[0]  # road in front: warm; background: cold
    assert _files(tmp_path) == ["depth.png", "std.png", "vis/depth_vis_depth.png", "vis/depth_vis_std.png"]


@pytest.mark.kitti
def test_complete_val_folder_uses_velodyne_raw_names(main, val_dir, tmp_path):
    out_dir = tmp_path / "pred" / "depth"  # created by the command
    assert main(["complete", "--input-dir", str(val_dir), "--out-dir", str(out_dir), *FAST]) == 0
    names = sorted(p.name for p in (val_dir / "velodyne_raw").glob("*.png"))
    assert len(names) == 2 and all("_velodyne_raw_" in n for n in names)
    assert _files(out_dir) == sorted([*names, RUN_RECORD])
    for name in names:
        raw = cv2.imread(str(out_dir / name), cv2.IMREAD_UNCHANGED)
        assert raw.dtype == np.uint16 and raw.shape == (352, 1216) and raw.min() > 0


def _fake_test_layout(val_dir: Path, root: Path) -> Path:
    """``test_depth_completion_anonymous`` layout with the two val frames as 0000000000/1."""
    for sub in ("image", "velodyne_raw", "intrinsics"):
        (root / sub).mkdir(parents=True)
    for index, cam in enumerate((2, 3)):
        frame = _val_frame(val_dir, cam)
        name = f"{index:010d}"
        shutil.copy(frame["image"], root / "image" / f"{name}.png")
        shutil.copy(frame["sparse"], root / "velodyne_raw" / f"{name}.png")
        shutil.copy(frame["intrinsics"], root / "intrinsics" / f"{name}.txt")
    return root


@pytest.mark.kitti
def test_complete_test_layout_names(main, val_dir, tmp_path):
    root = _fake_test_layout(val_dir, tmp_path / "test_depth_completion_anonymous")
    out_dir = tmp_path / "submission"
    assert main(["complete", "--input-dir", str(root), "--out-dir", str(out_dir), *FAST]) == 0
    assert _files(out_dir) == sorted(["0000000000.png", "0000000001.png", RUN_RECORD])
    # Frame 0 is the image_02 frame: the same depth as completing that file alone.
    single = tmp_path / "single.png"
    assert main(_one(_val_frame(val_dir, 2), single, *FAST[:-1])) == 0
    np.testing.assert_array_equal(read_depth_png(single), read_depth_png(out_dir / "0000000000.png"))


@pytest.mark.kitti
def test_complete_folder_checks_every_frame_before_writing(main, val_dir, tmp_path, capsys):
    root = _fake_test_layout(val_dir, tmp_path / "test")
    write_depth_png(root / "velodyne_raw" / "0000000001.png", np.zeros((352, 1216)))
    out_dir = tmp_path / "out"
    assert main(["complete", "--input-dir", str(root), "--out-dir", str(out_dir), *FAST]) == 2
    err = capsys.readouterr().err
    assert "no LiDAR point" in err and "0000000001" in err and "1 of 2 frame(s)" in err and "nothing written" in err
    assert not out_dir.exists()  # the good frame before the bad one is not written either


def test_complete_folder_without_frames(main, tmp_path, capsys):
    for sub in ("image", "velodyne_raw", "intrinsics"):
        (tmp_path / "in" / sub).mkdir(parents=True)
    assert main(["complete", "--input-dir", str(tmp_path / "in"), "--out-dir", str(tmp_path / "out")]) == 2
    assert "found no frames" in capsys.readouterr().err
    assert not (tmp_path / "out").exists()


# --------------------------------------------------------------------------- synthetic frame

H, W = 48, 64


def _synthetic_frame(folder: Path) -> dict[str, Path]:
    """A small valid frame: two coloured halves, a tilted plane sampled on a sparse grid."""
    folder.mkdir(parents=True, exist_ok=True)
    rows, cols = np.mgrid[0:H, 0:W]
    rgb = np.zeros((H, W, 3), np.uint8)
    rgb[:, : W // 2] = (200, 40, 40)
    rgb[:, W // 2:] = (40, 60, 200)
    rgb = np.clip(rgb + (rows[..., None] % 7) * 3, 0, 255).astype(np.uint8)
    depth = np.where(cols < W // 2, 8.0 + 0.05 * rows, 20.0 - 0.1 * rows)
    sparse = np.zeros((H, W))
    sparse[4::5, 2::4] = depth[4::5, 2::4]
    paths = {"image": folder / "rgb.png", "sparse": folder / "sparse.png", "intrinsics": folder / "K.txt"}
    cv2.imwrite(str(paths["image"]), cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR))
    write_depth_png(paths["sparse"], sparse)
    paths["intrinsics"].write_text("60 0 32\n0 60 24\n0 0 1\n")
    return paths


@pytest.fixture
def synth(tmp_path) -> dict[str, Path]:
    return _synthetic_frame(tmp_path / "in")


def test_complete_synthetic_frame(main, synth, tmp_path):
    out = tmp_path / "out" / "depth.png"
    out.parent.mkdir()
    assert main(_one(synth, out, "--mode", "pixel", "--dtype", "float64")) == 0
    depth = read_depth_png(out)
    assert depth.shape == (H, W) and depth.min() > 0
    sparse = read_depth_png(synth["sparse"])
    error = np.abs(depth - sparse)[sparse > 0]
    assert np.median(error) < 0.01 and error.max() < 0.1  # metres
    # Each half keeps its own plane: 8 + 0.05 row on the left, 20 - 0.1 row on the right.
    assert 7.9 < depth[:, :30].mean() < 9.3 and 15.0 < depth[:, 34:].mean() < 20.1


def _synthetic_folder(root: Path) -> Path:
    """Two synthetic frames in the test_depth_completion_anonymous layout."""
    for sub in ("image", "velodyne_raw", "intrinsics"):
        (root / sub).mkdir(parents=True)
    for name in ("0000000000", "0000000001"):
        frame = _synthetic_frame(root / "tmp")
        frame["image"].rename(root / "image" / f"{name}.png")
        frame["sparse"].rename(root / "velodyne_raw" / f"{name}.png")
        frame["intrinsics"].rename(root / "intrinsics" / f"{name}.txt")
    (root / "tmp").rmdir()
    return root


def test_complete_folder_std_and_default_vis(main, tmp_path, capsys):
    """--out-std-dir and a bare --vis (pictures in <out-dir>_vis) on a small test-layout folder."""
    root = _synthetic_folder(tmp_path / "anonymous")
    out_dir, std_dir = tmp_path / "submission", tmp_path / "std"
    assert main(["complete", "--input-dir", str(root), "--out-dir", str(out_dir), "--out-std-dir", str(std_dir),
                 "--vis", *FAST[:-1]]) == 0
    assert "2/2" not in capsys.readouterr().err  # no progress bar when stderr is not a terminal
    names = ["0000000000.png", "0000000001.png"]
    assert _files(out_dir) == sorted([*names, RUN_RECORD])  # nothing else in the submission folder but the
    # hidden run record (left out by zip *.png)
    assert _files(std_dir) == names
    assert _files(tmp_path / "submission_vis") == [
        "0000000000_vis_depth.png", "0000000000_vis_std.png", "0000000001_vis_depth.png", "0000000001_vis_std.png"]
    sparse = read_depth_png(root / "velodyne_raw" / names[0])
    std = read_depth_png(std_dir / names[0])
    assert std.shape == (H, W) and std.min() > 0
    # Superpixels holding LiDAR are more certain than the scene average.
    assert np.median(std[sparse > 0]) <= np.median(std)
    picture = cv2.imread(str(tmp_path / "submission_vis" / "0000000000_vis_std.png"), cv2.IMREAD_UNCHANGED)
    assert picture.shape[0] > H and picture.shape[2] == 3 and picture.dtype == np.uint8  # map + colour bar


def test_complete_greyscale_image_warns(main, synth, tmp_path, caplog):
    grey = tmp_path / "grey.png"
    cv2.imwrite(str(grey), cv2.imread(str(synth["image"]), cv2.IMREAD_GRAYSCALE))
    out = tmp_path / "depth.png"
    assert main(_one({**synth, "image": grey}, out, "--mode", "pixel")) == 0
    assert "grey.png is greyscale" in caplog.text
    assert read_depth_png(out).min() > 0


@pytest.mark.parametrize("quiet", [False, True])
def test_complete_progress_bar_on_a_terminal(main, tmp_path, capsys, monkeypatch, quiet):
    root = _synthetic_folder(tmp_path / "in")
    monkeypatch.setattr(sys.stderr, "isatty", lambda: True)  # capsys's stream stands in for a terminal
    argv = ["complete", "--input-dir", str(root), "--out-dir", str(tmp_path / "out"), "--mode", "pixel"]
    assert main(argv + (["--quiet"] if quiet else [])) == 0
    err = capsys.readouterr().err
    assert ("2/2" in err) != quiet


def _crop_image(paths, tmp):
    image = cv2.imread(str(paths["image"]))
    cv2.imwrite(str(tmp / "small.png"), image[:-8])
    return {**paths, "image": tmp / "small.png"}


def _sparse_8bit(paths, tmp):
    cv2.imwrite(str(tmp / "s8.png"), (cv2.imread(str(paths["sparse"]), cv2.IMREAD_UNCHANGED) // 256).astype(np.uint8))
    return {**paths, "sparse": tmp / "s8.png"}


def _k_text(text):
    def make(paths, tmp):
        (tmp / "badK.txt").write_text(text)
        return {**paths, "intrinsics": tmp / "badK.txt"}
    return make


def _zero_sparse(paths, tmp):
    write_depth_png(tmp / "zero.png", np.zeros((H, W)))
    return {**paths, "sparse": tmp / "zero.png"}


BAD_INPUTS = {
    "size mismatch": (_crop_image, ["sizes differ", "small.png", "40x64", "48x64"]),
    "8-bit sparse": (_sparse_8bit, ["16-bit single-channel", "uint8", "s8.png"]),
    "rgb as sparse": (lambda p, t: {**p, "sparse": p["image"]}, ["16-bit single-channel", "3 channel", "rgb.png"]),
    "depth as image": (lambda p, t: {**p, "image": p["sparse"]}, ["8-bit image", "uint16", "sparse.png"]),
    "K with 8 numbers": (_k_text("60 0 32 0 60 24 0 0"), ["9 numbers", "got 8", "badK.txt"]),
    "K not numbers": (_k_text("60 0 32 0 sixty 24 0 0 1"), ["9 numbers", "non-numeric", "badK.txt"]),
    "K fx <= 0": (_k_text("0 0 32 0 60 24 0 0 1"), ["fx = K[0][0] > 0", "fx=0", "badK.txt"]),
    "K fy < 0": (_k_text("60 0 32 0 -60 24 0 0 1"), ["fx = K[0][0] > 0", "fy=-60", "badK.txt"]),
    "K last row": (_k_text("60 0 32 0 60 24 0 1 0"), ["last row", "badK.txt"]),
    "K principal point far outside": (_k_text("60 0 600 0 60 150 0 0 1"),
                                      ["--intrinsics", "principal point", "far outside", "badK.txt"]),
    "all-zero sparse": (_zero_sparse, ["no LiDAR point", "zero.png"]),
    "missing image": (lambda p, t: {**p, "image": t / "nope.png"}, ["no such file", "nope.png"]),
    "missing sparse": (lambda p, t: {**p, "sparse": t / "nope.png"}, ["no such file", "nope.png"]),
    "missing intrinsics": (lambda p, t: {**p, "intrinsics": t / "nope.txt"}, ["no such file", "nope.txt"]),
}


@pytest.mark.parametrize("case", list(BAD_INPUTS))
def test_complete_bad_input(main, synth, tmp_path, capsys, case):
    make, words = BAD_INPUTS[case]
    work = tmp_path / "work"
    work.mkdir()
    paths = make(synth, work)
    out_dir = tmp_path / "out"
    out_dir.mkdir()
    status = main(_one(paths, out_dir / "depth.png", "--out-std", out_dir / "std.png", "--vis", tmp_path / "vis",
                       "--mode", "pixel"))
    err = capsys.readouterr().err
    assert status == 2
    assert err.startswith("crfdepth complete: error:") and err.count("\n") == 1  # one line
    for word in words:
        assert word in err
    assert _files(out_dir) == []  # nothing written, not even a temporary file
    assert not (tmp_path / "vis").exists()  # nor a folder created


def test_an_image_without_lidar_is_told_both_ways_to_give_it(main, synth, tmp_path, capsys):
    out = tmp_path / "depth.png"
    assert main(["complete", "--image", str(synth["image"]), "--out", str(out)]) == 2
    assert capsys.readouterr().err == (
        "crfdepth complete: error: one frame needs --image, --out and its LiDAR: --sparse DEPTH.png with "
        "--intrinsics K.txt, or --points CLOUD with --calib RIG.yaml (an RGB-D camera's depth image: --depth "
        "DEPTH.png with --intrinsics or --known-camera; many frames: --input-dir, --input-list or --bag); missing "
        "the LiDAR\n")
    assert main(["complete"]) == 2
    assert capsys.readouterr().err.endswith("; missing --image, --out, the LiDAR\n")
    assert not out.exists()


@pytest.mark.parametrize("case", ["missing folder", "not png", "out is the input", "out is a folder"])
def test_complete_bad_output(main, synth, tmp_path, capsys, case):
    (tmp_path / "folder.png").mkdir()
    out = {"missing folder": tmp_path / "missing" / "depth.png",
           "not png": tmp_path / "depth.tiff",
           "out is the input": synth["sparse"],
           "out is a folder": tmp_path / "folder.png"}[case]
    before = {p: p.stat().st_mtime_ns for p in tmp_path.rglob("*") if p.is_file()}
    assert main(_one(synth, out, "--mode", "pixel")) == 2
    err = capsys.readouterr().err
    expected = {"missing folder": f"--out: the folder of {out} does not exist", "not png": "ending in .png",
                "out is the input": "refusing to overwrite", "out is a folder": "got a folder"}[case]
    assert expected in err and "--out" in err
    assert {p: p.stat().st_mtime_ns for p in tmp_path.rglob("*") if p.is_file()} == before
    assert not (tmp_path / "missing").exists()


@pytest.mark.skipif(os.geteuid() == 0, reason="root can write into read-only folders")
def test_complete_unwritable_output(main, synth, tmp_path, capsys):
    locked = tmp_path / "locked"
    locked.mkdir(mode=0o555)
    assert main(_one(synth, locked / "depth.png", "--mode", "pixel")) == 2
    assert "not writable" in capsys.readouterr().err
    assert _files(locked) == []


@pytest.mark.skipif(torch.cuda.is_available(), reason="CUDA is available here")
def test_complete_cuda_unavailable(main, synth, tmp_path, capsys):
    assert main(_one(synth, tmp_path / "depth.png", "--device", "cuda")) == 2
    assert "--device cuda" in capsys.readouterr().err
    assert not (tmp_path / "depth.png").exists()


@pytest.mark.parametrize("argv, words", [
    (["--input-dir", "X"], ["--input-dir needs --out-dir"]),
    (["--image", "a.png"], ["one frame needs --image, --out and its LiDAR", "; missing --out, the LiDAR"]),
])
def test_complete_bad_option_combinations(main, argv, words, capsys):
    assert main(["complete", *argv]) == 2
    err = capsys.readouterr().err
    assert all(w in err for w in words)


def test_complete_bad_potentials_is_a_usage_error(main, synth, tmp_path, capsys):
    with pytest.raises(SystemExit) as info:
        main(_one(synth, tmp_path / "d.png", "--potentials", "normal,distance"))
    assert info.value.code == 2
    assert "includes colour" in capsys.readouterr().err


# --------------------------------------------------------------------------- checkpoints


def _modified_model() -> CRFDepth:
    model = CRFDepth()
    with torch.no_grad():
        model.raw_beta += 4.0  # much stronger colour smoothing
        model.log_sigma_d += 1.5  # across colour edges too
        model.log_confidence -= 3.0  # weaker data term
    return model


def _model_file(state: dict[str, torch.Tensor]):
    """Writes a crfdepth model file (crfdepth.save_model's layout) of the default configuration."""
    return lambda p: torch.save({"format": "crfdepth", "version": 1, "config": CRFDepth().config,
                                 "state_dict": state}, p)


def test_complete_checkpoint_loads(main, synth, tmp_path):
    def complete(*extra) -> np.ndarray:
        out = tmp_path / f"d{len(list(tmp_path.glob('d*.png')))}.png"
        assert main(_one(synth, out, "--mode", "pixel", *extra)) == 0
        return read_depth_png(out)

    default = complete("--weights", "paper")  # the hand-set weights of CRFDepth()
    save_model(CRFDepth(), tmp_path / "default.pt")
    np.testing.assert_array_equal(complete("--checkpoint", tmp_path / "default.pt"), default)
    shipped = complete()  # no --checkpoint, no --weights: the learned KITTI weights
    np.testing.assert_array_equal(complete("--weights", "kitti"), shipped)
    np.testing.assert_array_equal(complete("--checkpoint", weights_path("kitti")), shipped)
    assert np.abs(shipped - default).max() > 1e-3  # metres

    state = _modified_model().state_dict()
    save_model(_modified_model(), tmp_path / "modified.pt")
    modified = complete("--checkpoint", tmp_path / "modified.pt")
    assert np.abs(modified - default).max() > 0.1  # metres: the weights changed the result

    lightning = {"epoch": 3, "global_step": 120, "hyper_parameters": {"crf": CRFDepth().config},
                 "state_dict": {f"model.{k}": v for k, v in state.items()} | {"loss.scale": torch.ones(1)}}
    torch.save(lightning, tmp_path / "last.ckpt")
    np.testing.assert_array_equal(complete("--checkpoint", tmp_path / "last.ckpt"), modified)


def _write_pickle(path: Path) -> None:
    path.write_bytes(pickle.dumps({"when": datetime.datetime(2020, 1, 1)}))


BAD_CHECKPOINTS = {
    "text file": (lambda p: p.write_text("alpha = 0.5\n"), ["not a torch state dict"]),
    "random pickle": (_write_pickle, ["not a torch state dict"]),
    "a tensor": (lambda p: torch.save(torch.ones(3), p), ["does not hold a state dict", "Tensor"]),
    "wrong keys": (_model_file({"encoder.weight": torch.ones(3)}),
                   ["does not match CRFDepth", "missing keys (11)", "log_confidence",
                    "unexpected keys (1): encoder.weight"]),
    "wrong shape": (_model_file({**CRFDepth().state_dict(), "raw_alpha": torch.ones(2)}),
                    ["does not match CRFDepth", "wrong shapes (1): raw_alpha"]),
}


@pytest.mark.parametrize("case", list(BAD_CHECKPOINTS))
def test_complete_bad_checkpoint(main, synth, tmp_path, capsys, case):
    write, words = BAD_CHECKPOINTS[case]
    checkpoint = tmp_path / "weights.pt"
    write(checkpoint)
    out = tmp_path / "depth.png"
    assert main(_one(synth, out, "--mode", "pixel", "--checkpoint", checkpoint, "--vis", tmp_path / "vis")) == 2
    err = capsys.readouterr().err
    assert "--checkpoint" in err and str(checkpoint) in err
    assert all(w in err for w in words)
    assert not out.exists() and not (tmp_path / "vis").exists()


def test_complete_weights_and_checkpoint_exclude_each_other(main, synth, tmp_path, capsys):
    argv = _one(synth, tmp_path / "d.png", "--weights", "paper", "--checkpoint", weights_path("kitti"))
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert "--weights paper / --checkpoint" in err and "not both" in err and not (tmp_path / "d.png").exists()


def test_complete_missing_checkpoint(main, synth, tmp_path, capsys):
    assert main(_one(synth, tmp_path / "d.png", "--checkpoint", tmp_path / "none.pt")) == 2
    assert "none.pt" in capsys.readouterr().err and not (tmp_path / "d.png").exists()
