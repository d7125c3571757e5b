"""Tests of ``crfdepth complete --depth`` and ``--input-dir`` on RGB-D pairs (crfdepth.cli.complete_rgbd,
crfdepth.cli.complete_rgbd_folder): an RGB-D depth image's holes filled, its measured pixels kept.

Known answers on the synthetic wall-and-box frame of tests/cli/rgbd_scenes.py (written to ``tmp_path``, so these
run without the shared data); real frames of NYU Depth v2 from ``../shared/data/nyu`` (the 160x120 ``tiny`` frame,
and the three 640x480 frames of ``official_test/basement`` for a folder).
"""

from __future__ import annotations

import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest

import crfdepth.cli.complete_rgbd_folder as rgbd_folder
from crfdepth.data.nyu.camera import nyu_intrinsics
from crfdepth.runs.resume import RUN_RECORD
from tests.cli.frames import files, run
from tests.cli.rgbd_scenes import BOX_BLOCK, WALL_BLOCK, codes, read_codes, scene, write_pair, write_sync_folder

FAST = ["--quiet"]
GATE_OFF = "occlusion gate off: registered depth has no see-through returns"


@pytest.fixture
def pair(tmp_path) -> dict:
    """The synthetic frame as ``rgb.png`` + ``depth.png`` (millimetres) in ``tmp_path/in``."""
    frame = scene(0)
    image, depth = write_pair(tmp_path / "in" / "rgb.png", tmp_path / "in" / "depth.png", frame)
    return {"frame": frame, "image": image, "depth": depth}


def _one(pair: dict, out: Path, *extra) -> list:
    return ["complete", "--image", pair["image"], "--depth", pair["depth"], "--known-camera", "nyu", "--out", out,
            *extra]


# --------------------------------------------------------------------------- one frame


def test_holes_are_filled_and_measured_pixels_kept(pair, tmp_path):
    out = tmp_path / "filled.png"
    code, stdout, err = run(_one(pair, out))
    assert code == 0, err
    assert GATE_OFF in stdout  # the model line says the gate is off for registered depth
    frame, filled = pair["frame"], read_codes(out)
    measured = codes(frame.measured)
    valid = measured > 0
    assert np.array_equal(filled[valid], measured[valid])  # every measured pixel, code for code
    assert filled.min() > 0  # no hole left
    truth = frame.depth * 1000.0
    relative = np.abs(filled - truth) / truth
    assert relative[WALL_BLOCK].max() < 0.01  # a 16x20 hole in the slanted wall, within 1%
    assert relative[BOX_BLOCK].max() < 0.01  # and in the box
    assert np.median(relative[frame.holes]) < 0.01  # holes at the box's edge included
    assert f"{int(frame.holes.sum())} hole pixel(s) filled" in stdout


@pytest.mark.parametrize("units", ["mm", "kitti", "m"])
def test_the_output_is_in_the_units_of_the_input(tmp_path, units):
    frame = scene(1)
    image, depth = write_pair(tmp_path / "rgb.png", tmp_path / f"depth_{units}.png", frame, units)
    out = tmp_path / "filled.png"
    code, _, err = run(["complete", "--image", image, "--depth", depth, "--depth-units", units, "--known-camera",
                        "nyu", "--out", out, *FAST])
    assert code == 0, err
    given, filled = read_codes(depth), read_codes(out)
    assert np.array_equal(filled[given > 0], given[given > 0])
    assert filled.min() >= 1
    per_metre = {"mm": 1000.0, "kitti": 256.0, "m": 1.0}[units]
    # the holes inside the wall: the true depth in the unit, within 1% (whole metres: within one code)
    truth = frame.depth[WALL_BLOCK] * per_metre
    tolerance = np.maximum(0.01 * truth, 1.0 if units == "m" else 0.0)
    assert np.all(np.abs(filled[WALL_BLOCK] - truth) <= tolerance + 0.5)


def test_std_and_pictures_are_written_with_the_depth(pair, tmp_path):
    out, std, vis = tmp_path / "filled.png", tmp_path / "std.png", tmp_path / "pictures"
    code, _, err = run(_one(pair, out, "--out-std", std, "--vis", vis, *FAST))
    assert code == 0, err
    spread = read_codes(std)  # millimetres, as the depth
    assert spread.shape == (120, 160) and spread.min() >= 1
    frame = pair["frame"]
    # less certain inside the large holes than on the measured pixels
    assert np.median(spread[WALL_BLOCK]) > np.median(spread[~frame.holes])
    assert sorted(p.name for p in vis.iterdir()) == ["filled_vis_depth.png", "filled_vis_std.png"]
    picture = cv2.imread(str(vis / "filled_vis_depth.png"))
    assert picture.ndim == 3 and picture.shape[0] > 120  # the map (scaled up when small) over its colour bar


def test_intrinsics_file_and_known_camera_give_the_same_depth(pair, tmp_path):
    K = tmp_path / "K.txt"
    K.write_text(" ".join(f"{v:.9g}" for v in nyu_intrinsics(160, 120).double().flatten().tolist()))
    known, given = tmp_path / "known.png", tmp_path / "given.png"
    assert run(_one(pair, known, *FAST))[0] == 0
    argv = ["complete", "--image", pair["image"], "--depth", pair["depth"], "--intrinsics", K, "--out", given, *FAST]
    assert run(argv)[0] == 0
    assert np.abs(read_codes(known).astype(int) - read_codes(given).astype(int)).max() <= 1


def test_real_nyu_frame_keeps_its_depth_and_fills_hidden_pixels(nyu_root, tmp_path):
    """The 160x120 NYU frame with a block and 20% of its measured pixels hidden: the hidden depth comes back within
    1% (median) and 2% (mean); the measured pixels are kept code for code."""
    image = nyu_root / "tiny" / "bookstore_0001d_00001.jpg"
    depth = read_codes(nyu_root / "tiny" / "bookstore_0001d_00001.png")
    rng = np.random.default_rng(0)
    hidden = (depth > 0) & (rng.random(depth.shape) < 0.2)
    hidden[40:60, 60:90] = depth[40:60, 60:90] > 0
    given = tmp_path / "depth.png"
    cv2.imwrite(str(given), np.where(hidden, 0, depth).astype(np.uint16))
    out = tmp_path / "filled.png"
    code, _, err = run(["complete", "--image", image, "--depth", given, "--known-camera", "nyu", "--out", out, *FAST])
    assert code == 0, err
    filled = read_codes(out).astype(np.float64)
    kept = (depth > 0) & ~hidden
    assert np.array_equal(filled[kept], depth[kept])
    relative = np.abs(filled[hidden] - depth[hidden]) / depth[hidden]
    assert np.median(relative) < 0.01 and relative.mean() < 0.02  # measured: 0.13% and 0.48%


# --------------------------------------------------------------------------- bad input


def _visualisation(path: Path, frame) -> None:  # an 8-bit picture of the depth stored as 16 bits
    scaled = frame.measured / frame.measured.max() * 255
    cv2.imwrite(str(path), np.rint(scaled).astype(np.uint16))


def _no_depth(path: Path, frame) -> None:
    cv2.imwrite(str(path), np.zeros(frame.measured.shape, np.uint16))


def _eight_bit(path: Path, frame) -> None:
    cv2.imwrite(str(path), np.rint(frame.measured / frame.measured.max() * 255).astype(np.uint8))


def _smaller(path: Path, frame) -> None:
    cv2.imwrite(str(path), codes(frame.measured)[:60, :80])


@pytest.mark.parametrize("case, words", [
    ("wrong unit", ["--depth", "that looks like millimetres: pass --depth-units mm"]),
    ("visualisation", ["--depth", "8-bit visualisation"]),
    ("8-bit png", ["--depth", "single-channel 16-bit depth PNG", "8-bit"]),
    ("no valid pixel", ["--depth", "at least one valid (non-zero) pixel"]),
    ("sizes differ", ["--depth", "expected the size of --image", "120x160", "60x80"]),
])
def test_bad_depth_images_are_refused_naming_the_argument(pair, tmp_path, case, words):
    depth = tmp_path / "bad.png"
    writers = {"visualisation": _visualisation, "no valid pixel": _no_depth, "8-bit png": _eight_bit,
               "sizes differ": _smaller}
    units = []
    if case == "wrong unit":
        shutil.copy(pair["depth"], depth)
        units = ["--depth-units", "m"]  # millimetres read as whole metres
    else:
        writers[case](depth, pair["frame"])
    out_dir = tmp_path / "out"
    out_dir.mkdir()
    code, stdout, err = run(["complete", "--image", pair["image"], "--depth", depth, *units, "--known-camera", "nyu",
                             "--out", out_dir / "filled.png", "--out-std", out_dir / "std.png", "--vis",
                             tmp_path / "vis"])
    assert code == 2
    assert err.startswith("crfdepth complete: error: --depth") and err.count("\n") == 1, err
    assert all(word in err for word in words), err
    assert "Traceback" not in err and stdout == ""  # refused before the model is built
    assert files(out_dir) == [] and not (tmp_path / "vis").exists()


@pytest.mark.parametrize("extra, words", [
    (["--sparse", "s.png", "--intrinsics", "K.txt"], ["--depth / --sparse: give one of them"]),
    (["--points", "c.bin", "--calib", "c.yaml"], ["--depth / --points: give one of them"]),
    (["--known-camera", "nyu", "--sparse-units", "mm"], ["--sparse-units", "applies to LiDAR input"]),
    (["--known-camera", "nyu", "--camera", "3"], ["--camera", "applies to LiDAR input"]),
    (["--known-camera", "nyu", "--intrinsics", "K.txt"], ["--intrinsics / --known-camera: give one of them"]),
    ([], ["--intrinsics / --known-camera", "--intrinsics K.txt", "--known-camera nyu", "missing both"]),
    (["--known-camera", "nyu", "--out-dir", "o"], ["--out-dir", "folder options need --input-dir"]),
])
def test_bad_option_combinations_are_refused(pair, tmp_path, extra, words):
    out = tmp_path / "filled.png"
    argv = ["complete", "--image", pair["image"], "--depth", pair["depth"], "--out", out, *extra]
    code, _, err = run(argv)
    assert code == 2 and err.count("\n") == 1, err
    assert all(word in err for word in words), err
    assert not out.exists()


def test_lidar_only_and_rgbd_only_options_name_the_other(pair, tmp_path):
    code, _, err = run(["complete", "--image", pair["image"], "--sparse", pair["depth"], "--intrinsics", "K.txt",
                        "--depth-units", "mm", "--out", tmp_path / "x.png"])
    assert code == 2 and "--depth-units mm: applies to an RGB-D depth image" in err and "--sparse-units" in err
    code, _, err = run(["complete", "--image", pair["image"], "--sparse", pair["depth"], "--intrinsics", "K.txt",
                        "--known-camera", "nyu", "--out", tmp_path / "x.png"])
    assert code == 2 and "--known-camera nyu: applies to an RGB-D depth image" in err


def test_a_known_camera_refuses_an_image_size_it_does_not_come_in(tmp_path):
    frame = scene(0)
    image, depth = tmp_path / "rgb.png", tmp_path / "depth.png"
    cv2.imwrite(str(image), frame.rgb[:, :100])
    cv2.imwrite(str(depth), codes(frame.measured)[:, :100])
    code, stdout, err = run(["complete", "--image", image, "--depth", depth, "--known-camera", "nyu", "--out",
                             tmp_path / "x.png"])
    assert code == 2 and err.startswith("crfdepth complete: error: --known-camera nyu (the image's size): expected "
                                        "a NYU v2 frame of 640x480"), err
    assert "got 100x120" in err and not (tmp_path / "x.png").exists()


# --------------------------------------------------------------------------- folders


def test_a_sync_folder_is_completed_as_frame_by_frame(tmp_path):
    folder = tmp_path / "scene"
    frames = write_sync_folder(folder, 3)
    out, std = tmp_path / "out", tmp_path / "std"
    code, stdout, err = run(["complete", "--input-dir", folder, "--known-camera", "nyu", "--out-dir", out,
                             "--out-std-dir", std])
    assert code == 0, err
    assert "wrote 3 depth PNG(s)" in stdout and GATE_OFF in stdout
    names = [f"sync_depth_{i:05d}.png" for i in range(3)]
    assert files(out) == sorted([RUN_RECORD, *names]) and files(std) == names  # no temporary file left
    for index, frame in enumerate(frames):
        filled, measured = read_codes(out / names[index]), codes(frame.measured)
        assert np.array_equal(filled[measured > 0], measured[measured > 0]) and filled.min() > 0
    # the folder's PNGs are the one-frame command's, byte for byte
    one = tmp_path / "one.png"
    assert run(["complete", "--image", folder / "rgb_00001.jpg", "--depth", folder / "sync_depth_00001.png",
                "--known-camera", "nyu", "--out", one, *FAST])[0] == 0
    assert one.read_bytes() == (out / names[1]).read_bytes()


def test_an_image_and_depth_folder_with_intrinsics_and_units(tmp_path):
    folder = tmp_path / "pairs"
    for stem, seed in (("a", 0), ("b", 1)):
        write_pair(folder / "image" / f"{stem}.png", folder / "depth" / f"{stem}.png", scene(seed), "kitti")
    K = tmp_path / "K.txt"
    K.write_text(" ".join(map(str, nyu_intrinsics(160, 120).double().flatten().tolist())))
    out = tmp_path / "out"
    code, _, err = run(["complete", "--input-dir", folder, "--depth-units", "kitti", "--intrinsics", K, "--out-dir",
                        out, "--vis", *FAST])
    assert code == 0, err
    assert files(out) == [RUN_RECORD, "a.png", "b.png"]
    assert sorted(p.name for p in (tmp_path / "out_vis").iterdir()) == [
        "a_vis_depth.png", "a_vis_std.png", "b_vis_depth.png", "b_vis_std.png"]
    given, filled = read_codes(folder / "depth" / "b.png"), read_codes(out / "b.png")
    assert np.array_equal(filled[given > 0], given[given > 0])  # KITTI codes in, KITTI codes out


def test_a_bad_frame_stops_the_folder_before_anything_is_written_unless_skipped(tmp_path):
    folder = tmp_path / "scene"
    write_sync_folder(folder, 3)
    _visualisation(folder / "sync_depth_00001.png", scene(1))
    (folder / "rgb_00002.jpg").unlink()  # a depth image without its colour image
    out = tmp_path / "out"
    code, _, err = run(["complete", "--input-dir", folder, "--known-camera", "nyu", "--out-dir", out, *FAST])
    assert code == 2 and "Traceback" not in err
    assert err.startswith("crfdepth complete: error: frame 2/3 sync_depth_00001 (sync_depth_00001.png): "
                          "expected 16-bit depth codes"), err
    assert "[2 of 3 frame(s)" in err and "frame 3/3 sync_depth_00002: no colour image" in err
    assert "expected rgb_00002.jpg" in err
    assert not out.exists()  # nothing written, the folder not even created
    code, stdout, err = run(["complete", "--input-dir", folder, "--known-camera", "nyu", "--out-dir", out,
                             "--skip-bad"])
    assert code == 0, err
    assert files(out) == sorted([RUN_RECORD, "skipped.csv", "sync_depth_00000.png"])
    listed = (out / "skipped.csv").read_text().splitlines()
    assert listed[0] == "frame,reason" and [line.split(",")[0] for line in listed[1:]] == [
        "sync_depth_00001", "sync_depth_00002"]


def test_an_interrupted_folder_keeps_its_frames_and_resumes_to_the_same_files(tmp_path, monkeypatch):
    folder = tmp_path / "scene"
    write_sync_folder(folder, 3)
    whole, part = tmp_path / "whole", tmp_path / "part"
    assert run(["complete", "--input-dir", folder, "--known-camera", "nyu", "--out-dir", whole, *FAST])[0] == 0
    calls = {"n": 0}
    real = rgbd_folder.complete_holes

    def interrupted(*args, **kwargs):
        calls["n"] += 1
        if calls["n"] == 2:
            raise KeyboardInterrupt
        return real(*args, **kwargs)

    with monkeypatch.context() as patch:
        patch.setattr(rgbd_folder, "complete_holes", interrupted)
        code, _, err = run(["complete", "--input-dir", folder, "--known-camera", "nyu", "--out-dir", part, *FAST])
    assert code == 130
    assert "interrupted after 1 of 3 frame(s) written to" in err and "--resume completes the others" in err
    assert files(part) == [RUN_RECORD, "sync_depth_00000.png"]  # the frame written stays; no partial file
    code, _, err = run(["complete", "--input-dir", folder, "--known-camera", "nyu", "--out-dir", part, "--resume",
                        *FAST])
    assert code == 0, err
    assert files(part) == files(whole)
    for name in files(whole):
        assert (part / name).read_bytes() == (whole / name).read_bytes(), name
    # another unit would write other bytes: a resume with it is refused
    code, _, err = run(["complete", "--input-dir", folder, "--known-camera", "nyu", "--depth-units", "kitti",
                        "--out-dir", part, "--resume", *FAST])
    assert code == 2 and "--resume" in err


def test_folder_layouts_and_options_that_do_not_apply(tmp_path):
    scenes = tmp_path / "official_test"
    write_sync_folder(scenes / "basement", 1)
    code, _, err = run(["complete", "--input-dir", scenes, "--known-camera", "nyu", "--out-dir", tmp_path / "o"])
    assert code == 2 and "a folder of 1 scene folder(s) (basement); give each scene as --input-dir" in err
    empty = tmp_path / "empty"
    empty.mkdir()
    code, _, err = run(["complete", "--input-dir", empty, "--depth-units", "mm", "--out-dir", tmp_path / "o"])
    assert code == 2 and "--depth-units mm: applies to RGB-D pairs" in err
    code, _, err = run(["complete", "--input-dir", scenes / "basement", "--out-dir", tmp_path / "o"])
    assert code == 2 and "--intrinsics / --known-camera" in err
    code, _, err = run(["complete", "--input-dir", scenes / "basement", "--known-camera", "nyu", "--out-dir",
                        tmp_path / "o", "--batch-size", "2"])
    assert code == 2 and "--batch-size 2: applies to LiDAR folders" in err
    code, _, err = run(["complete", "--input-dir", scenes / "basement", "--known-camera", "nyu", "--out-dir",
                        scenes / "basement" / "out"])
    assert code == 2 and "refusing to write among the inputs" in err
    assert not (tmp_path / "o").exists()


def test_real_nyu_sync_folder(nyu_root, tmp_path):
    folder = nyu_root / "official_test" / "basement"
    out = tmp_path / "out"
    code, stdout, err = run(["complete", "--input-dir", folder, "--known-camera", "nyu", "--out-dir", out])
    assert code == 0, err
    assert "wrote 3 depth PNG(s)" in stdout
    for number in ("00000", "00050", "00100"):
        given, filled = read_codes(folder / f"sync_depth_{number}.png"), read_codes(out / f"sync_depth_{number}.png")
        assert filled.shape == (480, 640) and filled.min() > 0
        assert np.array_equal(filled[given > 0], given[given > 0])
        # the holes' depth lies within the frame's measured range, widened by 20%
        holes = filled[given == 0]
        assert holes.min() >= 0.8 * given[given > 0].min() and holes.max() <= 1.2 * given.max()
