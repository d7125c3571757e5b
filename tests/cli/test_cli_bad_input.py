"""Bad input to every ``crfdepth`` command: one line on stderr and exit status 2 (or 0 with one warning line),
never a traceback, never an output written: integer options out of range, ``--device cuda`` without CUDA,
outputs that name an input or each other, options the mode run ignores, ``--input-list`` lines checked before
any input runs, a rig calibration named ``.txt`` or without a suffix, and ``std_samples`` named as the API's
keyword."""

from __future__ import annotations

import shutil
from pathlib import Path

import pytest
import torch

import crfdepth
from crfdepth.errors import InputError
from tests.cli.frames import FAST, run_main, write_folder

EXAMPLE = Path(__file__).resolve().parents[2] / "docs" / "example"
BIG = "99999999999999999999"  # 20 digits: no C integer holds it
INT_MAX = 2**31 - 1


@pytest.fixture(scope="module")
def folder(tmp_path_factory):
    return write_folder(tmp_path_factory.mktemp("sweep") / "val_selection_cropped", 2)


def _frame(folder: Path) -> dict[str, Path]:
    """The files of frame 0 of ``folder``."""
    pick = lambda sub: next(iter(sorted((folder / sub).iterdir())))  # noqa: E731
    return {"image": pick("image"), "sparse": pick("velodyne_raw"), "intrinsics": pick("intrinsics")}


def _one(frame: dict[str, Path], out, *extra) -> list:
    return ["complete", "--image", frame["image"], "--sparse", frame["sparse"], "--intrinsics", frame["intrinsics"],
            "--out", out, *extra, *FAST]


def _refused(code: int, err: str, command: str, message: str) -> None:
    """Exit status 2 and one line on stderr: ``crfdepth <command>: error: <message>``, no traceback."""
    assert code == 2, err
    assert err.splitlines() == [f"crfdepth {command}: error: {message}"], err
    assert "Traceback" not in err


# --------------------------------------------------------------------------- 1, 3: integer options


@pytest.mark.parametrize("argv, message", [
    (["demo", "--seed", "-5"], "--seed: expected an integer in [0, 4294967295], got '-5'"),
    (["demo", "--seed", BIG], f"--seed: expected an integer in [0, 4294967295], got '{BIG}'"),
    (["demo", "--seed", str(2**32)], f"--seed: expected an integer in [0, 4294967295], got '{2**32}'"),
    (["demo", "--max-frames", "0"], f"--max-frames: expected an integer in [1, {INT_MAX}], got '0'"),
    (["demo", "--max-frames", "-2"], f"--max-frames: expected an integer in [1, {INT_MAX}], got '-2'"),
    (["demo", "--beams", BIG], f"--beams: expected an integer in [1, 128], got '{BIG}'"),
    (["project", "--velodyne", "a.bin", "--calib", "c", "--image", "i.png", "--out", "o.png",
      "--keep-every-ring", BIG],
     f"--keep-every-ring: expected an integer in [1, 128] (keep one laser ring in K), got '{BIG}'"),
    (["project", "--velodyne", "a.bin", "--calib", "c", "--image", "i.png", "--out", "o.png", "--seed", "-5"],
     "--seed: expected an integer in [0, 4294967295], got '-5'"),
    (["evaluate", "--layout", "raw", "--keep-every-ring", BIG],
     f"--keep-every-ring: expected an integer in [2, 128], got '{BIG}'"),
    (["evaluate", "--layout", "synthetic", "--seed", BIG], f"--seed: expected an integer in [0, 4294967295], got '{BIG}'"),
    (["evaluate", "--layout", "synthetic", "--limit", BIG], f"--limit: expected an integer in [1, {INT_MAX}], got '{BIG}'"),
    (["complete", "--batch-size", BIG], f"--batch-size: expected an integer in [1, 1024], got '{BIG}'"),
    (["complete", "--devices", "0"], "--devices: expected an integer in [1, 64], got '0'"),
    (["complete", "--num-nodes", BIG], f"--num-nodes: expected an integer in [1, {INT_MAX}], got '{BIG}'"),
    (["complete", "--superpixels", BIG], f"--superpixels: expected an integer in [1, 428032], got '{BIG}'"),
    (["evaluate", "--layout", "synthetic", "--workers", "-1"], "--workers: expected an integer in [0, 64], got '-1'"),
    (["targets", "--drive", "d", "--out-dir", "o", "-k", BIG],
     f"-k/--window: expected an integer in [0, {INT_MAX}], got '{BIG}'"),
    (["targets", "--drive", "d", "--out-dir", "o", "--frames", f"0:{BIG}"],
     f"--frames: expected A:B, frame numbers in [0, {INT_MAX}], got '0:{BIG}'"),
])
def test_an_integer_out_of_range_is_refused_when_parsed(argv, message, capsys, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    code, out, err = run_main(argv, capsys)
    _refused(code, err, argv[0], message)
    assert out == "" and list(tmp_path.iterdir()) == []


# --------------------------------------------------------------------------- 2: --device


def test_device_cuda_without_cuda_is_refused_before_any_work(folder, tmp_path, capsys, monkeypatch):
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    for argv in (["complete", "--input-dir", folder, "--out-dir", tmp_path / "o", "--device", "cuda", *FAST],
                 ["evaluate", "--layout", "synthetic", "--out-dir", tmp_path / "e", "--device", "cuda", *FAST]):
        code, _, err = run_main(argv, capsys)
        _refused(code, err, argv[0], "--device cuda: CUDA is not available in this PyTorch installation/machine "
                                     "(devices here: cpu); use --device cpu")
    assert list(tmp_path.iterdir()) == []
    code, _, err = run_main(["complete", "--device", "tpu"], capsys)
    assert code == 2 and err.startswith("crfdepth complete: error: --device: ") and len(err.splitlines()) == 1


# --------------------------------------------------------------------------- 4, 5, 6: outputs


def test_an_output_folder_equal_to_or_inside_the_input_is_refused(folder, capsys):
    before = sorted(p for p in folder.rglob("*"))
    code, _, err = run_main(["complete", "--input-dir", folder, "--out-dir", folder, *FAST], capsys)
    _refused(code, err, "complete", f"--out-dir: {folder} is an input folder of {folder}; refusing to write there")
    code, _, err = run_main(["complete", "--input-dir", folder, "--out-dir", folder / "pred", *FAST], capsys)
    _refused(code, err, "complete", f"--out-dir: {folder / 'pred'} is inside an input folder of {folder} ({folder}); "
                                    f"refusing to write among the inputs, choose a folder outside it")
    code, _, err = run_main(["complete", "--input-dir", folder, "--out-dir", folder.parent / "o", "--vis",
                             folder / "image", *FAST], capsys)
    assert code == 2 and err.startswith(f"crfdepth complete: error: --vis: {folder / 'image'} is an input folder")
    code, _, err = run_main(["evaluate", "--layout", "val_selection", "--data", folder, "--out-dir", folder / "ev",
                             *FAST], capsys)
    _refused(code, err, "evaluate", f"--out-dir: {folder / 'ev'} is or lies inside the --data folder {folder}; "
                                    f"refusing to write among the inputs, choose a folder outside it")
    assert sorted(p for p in folder.rglob("*")) == before


def test_demo_refuses_to_write_into_its_kitti_folder(folder, capsys):
    code, _, err = run_main(["demo", "--kitti", folder, "--out-dir", folder], capsys)
    _refused(code, err, "demo", f"--out-dir: {folder} is or lies inside the --kitti frames {folder}; refusing to "
                                f"write among the inputs, choose a folder outside it")
    assert not (folder / "data").exists()


def test_an_output_folder_that_is_a_file_is_refused(folder, tmp_path, capsys):
    a_file = tmp_path / "a_file"
    a_file.write_text("x")
    for argv, flag in ((["complete", "--input-dir", folder, "--out-dir", a_file, *FAST], "--out-dir"),
                       (["evaluate", "--layout", "synthetic", "--out-dir", a_file, *FAST], "--out-dir"),
                       (["demo", "--out-dir", a_file], "--out-dir")):
        code, _, err = run_main(argv, capsys)
        assert code == 2 and err.startswith(f"crfdepth {argv[0]}: error: {flag}: expected a folder"), err
        assert len(err.splitlines()) == 1
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a_file"]


@pytest.mark.parametrize("extra, message", [
    (["--out", "{t}/d.png", "--vis", "{t}/d.png"], "--vis: expected a folder for the pictures, got {t}/d.png, the "
                                                   "--out file"),
    (["--out", "{t}/d.png", "--out-std", "{t}/d.png"], "--out-std: must differ from --out, got {t}/d.png for both"),
    (["--out", "{t}/d.png", "--out-std", "{t}/d_vis_std.png", "--vis"],
     "--vis (std picture): {t}/d_vis_std.png is also the --out-std output; expected different files"),
    (["--out", "{t}/d.png", "--vis", "{image}"], "--vis: expected a folder for the pictures, got {image}, the "
                                                 "--image file"),
])
def test_two_outputs_naming_one_file_are_refused_before_any_work(folder, tmp_path, capsys, extra, message):
    frame = _frame(folder)
    fill = {"t": tmp_path, "image": frame["image"]}
    argv = ["complete", "--image", frame["image"], "--sparse", frame["sparse"], "--intrinsics", frame["intrinsics"],
            *[a.format(**fill) for a in extra], *FAST]
    code, _, err = run_main(argv, capsys)
    _refused(code, err, "complete", message.format(**fill))
    assert list(tmp_path.iterdir()) == []


# --------------------------------------------------------------------------- 7: options a mode ignores


def _warned(code: int, err: str, caplog, warning: str) -> None:
    """Exit status 0 and ``warning`` logged as one line (``crfdepth.cli.main`` shows it as ``crfdepth <command>:
    warning: <warning>``; under pytest the records go to ``caplog``)."""
    assert code == 0, err
    assert warning in [r.getMessage() for r in caplog.records if r.levelname == "WARNING"], caplog.text
    assert "Traceback" not in err


def test_an_option_the_mode_ignores_is_warned_about(folder, tmp_path, capsys, caplog):
    frame = _frame(folder)
    code, _, err = run_main(_one(frame, tmp_path / "d.png", "--camera", "3", "--trust-transform"), capsys)
    _warned(code, err, caplog, "--camera is ignored with --sparse (the depth map is already in its camera's "
                                   "image; --camera picks the camera of a KITTI --calib or raw drive)")
    _warned(code, err, caplog, "--trust-transform is ignored with --sparse (it applies to a point cloud "
                                   "projected with a rig transform: --points with --calib, or --bag)")


def test_demo_warns_about_the_synthetic_options_with_kitti(folder, tmp_path, capsys, monkeypatch, caplog):
    from crfdepth.cli import demo

    monkeypatch.setattr(demo, "_demo", lambda args, out_dir, recorder: 0)  # the options' checks alone
    code, _, err = run_main(["demo", "--kitti", folder, "--beams", "16", "--out-dir", tmp_path / "o"], capsys)
    _warned(code, err, caplog, "--beams is ignored with --kitti (it sets the synthetic scene; the KITTI frames "
                               "have their own LiDAR)")
    code, _, err = run_main(["demo", "--max-frames", "3", "--out-dir", tmp_path / "o"], capsys)
    _warned(code, err, caplog, "--max-frames is ignored without --kitti (the synthetic scene is one frame)")


# --------------------------------------------------------------------------- 8: --input-list


def test_input_list_checks_every_line_before_completing_any(folder, tmp_path, capsys):
    empty = tmp_path / "empty" / "val_selection_cropped"
    for sub in ("image", "velodyne_raw", "intrinsics"):
        (empty / sub).mkdir(parents=True)
    listing = tmp_path / "inputs.txt"
    listing.write_text(f"{folder}\n{empty}\n")
    code, _, err = run_main(["complete", "--input-list", listing, "--out-dir", tmp_path / "o", *FAST], capsys)
    assert code == 2 and len(err.splitlines()) == 1
    assert err.startswith(f"crfdepth complete: error: --input-list line 2 ({empty}): ")
    assert err.rstrip().endswith("[every line is checked before any input is completed; nothing written]")
    assert not (tmp_path / "o").exists()
    # an output subfolder that is an input of the list: <out-dir>/val_selection_cropped is line 1's folder
    listing.write_text(f"{folder}\n")
    code, _, err = run_main(["complete", "--input-list", listing, "--out-dir", folder.parent, *FAST], capsys)
    assert code == 2 and err.startswith(f"crfdepth complete: error: --input-list line 1 ({folder}): --out-dir: ")


# --------------------------------------------------------------------------- 9: messages in the user's names


@pytest.mark.parametrize("build", [
    lambda n: crfdepth.CRFDepth(std_samples=n),
    lambda n: crfdepth.CRFRefine(3, std_samples=n),
    lambda n: crfdepth.crf_refine(torch.ones(1, 1, 4, 4), torch.ones(1, 1, 4, 4), torch.zeros(1, 3, 4, 4),
                                  torch.zeros(2, 3), return_std=True, std_samples=n),
], ids=["CRFDepth", "CRFRefine", "crf_refine"])
def test_std_samples_is_named_by_the_api_keyword_before_any_solve(build):
    """Named std_samples (the keyword the user gave), not the std function's samples; a 20-digit count is refused
    rather than run for ever."""
    for value, got in ((0, "0"), (2.5, "float 2.5"), (10**20, str(10**20))):
        with pytest.raises(InputError) as info:
            build(value)
        assert str(info.value).splitlines()[0] == f"std_samples: expected an integer in [1, 4096], got {got}"


# --------------------------------------------------------------------------- 10: a rig file by its content


@pytest.mark.parametrize("name", ["rig.txt", "rig"])
def test_a_rig_calibration_is_recognised_by_its_content(tmp_path, capsys, name):
    calib = tmp_path / name
    shutil.copy(EXAMPLE / "rig.yaml", calib)
    out = tmp_path / "depth.png"
    code, _, err = run_main(["complete", "--image", EXAMPLE / "image.png", "--points", EXAMPLE / "scan.pcd",
                             "--calib", calib, "--out", out, *FAST], capsys)
    assert code == 0, err
    assert out.is_file()


def test_a_kitti_calibration_txt_is_still_read_as_kitti(kitti_root):
    from crfdepth.io.calibration import is_rig_file, load_any_calibration

    day = kitti_root / "raw" / "2011_09_26"
    assert not is_rig_file(day / "calib_cam_to_cam.txt")
    rig = load_any_calibration(day / "calib_cam_to_cam.txt")
    assert rig.kitti is not None and rig.image_size == (375, 1242)
