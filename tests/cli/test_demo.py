"""crfdepth demo: the README's main command."""

import re

import cv2
import numpy as np
import pytest

import crfdepth.cli.demo as demo
from crfdepth.cli import main
from crfdepth.errors import InputError
from crfdepth.pictures.figures import depth_picture

PICTURES = ("input", "depth", "std", "points")


def _rmse(text: str, method: str) -> float:
    return float(re.search(rf"{method}\s+RMSE ([\d.]+) mm", text).group(1))


@pytest.fixture
def no_computation(monkeypatch):
    """Fail the test if the demo gets as far as loading the model."""

    def refuse(*args, **kwargs):
        raise AssertionError("the demo started computing before refusing its input")

    monkeypatch.setattr(demo, "load_pretrained", refuse)


def test_demo_on_the_builtin_scene(tmp_path, capsys):
    out = tmp_path / "new" / "demo"  # created, with its parents
    assert main(["demo", "--out-dir", str(out), "--vis-range", "5", "60"]) == 0
    text = capsys.readouterr().out
    crf, nn = _rmse(text, "crfdepth"), _rmse(text, "nearest-neighbour")
    assert crf < nn, text
    # The picture folder holds only the pictures; the uint16 depth lies in data/.
    name = "synthetic-seed0"
    assert sorted(p.name for p in out.iterdir()) == sorted([f"{name}_{k}.png" for k in PICTURES] + ["data"])
    assert [p.name for p in (out / "data").iterdir()] == [f"{name}_depth16.png"]
    depth16 = cv2.imread(str(out / "data" / f"{name}_depth16.png"), cv2.IMREAD_UNCHANGED)
    assert depth16.shape == (352, 1216) and depth16.dtype == np.uint16 and int((depth16 == 0).sum()) == 0
    pictures = {k: cv2.cvtColor(cv2.imread(str(out / f"{name}_{k}.png")), cv2.COLOR_BGR2RGB) for k in PICTURES}
    # every picture with a panel below the 352-row map: a colour bar, or the points picture's caption
    assert len({pictures[kind].shape for kind in PICTURES}) == 1
    caption = pictures["points"][352:]
    assert (caption == 255).all(-1).mean() > 0.9 and (caption < 128).all(-1).any()  # white, with dark text
    for kind in ("input", "depth", "std"):  # with a colour bar below the 352-row map
        assert pictures[kind].shape[0] > 352 + 30 and pictures[kind].shape[1] == 1216, kind
    for kind, picture in pictures.items():
        assert picture[:352].std() > 5, kind
    # --vis-range fixes the depth colours: the bar is the one of that range, the map its colours.
    bar = depth_picture(np.full((352, 1216), 10.0), vis_range=(5.0, 60.0))[352:]
    np.testing.assert_array_equal(pictures["depth"][352:], bar)
    np.testing.assert_array_equal(pictures["input"][352:], bar)
    colours = depth_picture(depth16 / 256.0, vis_range=(5.0, 60.0))[:352]
    assert (np.abs(pictures["depth"][:352].astype(int) - colours).max(-1) <= 8).mean() > 0.99
    # One line per file group and a last line saying what went where.
    lines = text.strip().splitlines()
    assert re.fullmatch(rf"  pictures: {re.escape(str(out / name))}_\{{input,depth,std,points\}}\.png .*", lines[-3])
    assert lines[-2].startswith(f"  data:     {out / 'data' / name}_depth16.png")
    assert lines[-1].startswith(f"wrote 4 pictures per frame for 1 frame(s) to {out.resolve()} and the depth "
                                f"data to {(out / 'data').resolve()}")


def test_demo_computes_through_complete_depth(tmp_path, monkeypatch, capsys):
    seen = []
    original = demo.complete_depth

    def spy(image, **kwargs):
        seen.append((tuple(image.shape), sorted(kwargs)))
        return original(image, **kwargs)

    monkeypatch.setattr(demo, "complete_depth", spy)
    monkeypatch.setattr(demo, "_pictures", lambda *args: {})  # skip the drawing, keep the rest
    assert main(["demo", "--out-dir", str(tmp_path), "--beams", "16"]) == 0
    assert seen == [((3, 352, 1216), ["K", "model", "return_std", "sparse"])]
    assert "crfdepth          RMSE" in capsys.readouterr().out


@pytest.mark.kitti
def test_demo_on_real_frames(tmp_path, capsys, kitti_root):
    assert main(["demo", "--kitti", str(kitti_root), "--out-dir", str(tmp_path)]) == 0
    text = capsys.readouterr().out
    assert len(re.findall(r"crfdepth\s+RMSE", text)) == 2
    assert len(list(tmp_path.glob("*_points.png"))) == 2
    assert len(list((tmp_path / "data").glob("*_depth16.png"))) == 2


def _refused(capsys, argv: list[str], name: str, tmp_path, before: set) -> str:
    """Run a refused demo: exit status 2, one line naming ``name``, nothing written."""
    assert main(argv) == 2
    captured = capsys.readouterr()
    lines = captured.err.strip().splitlines()
    assert len(lines) == 1 and name in lines[0] and captured.out == "", captured.err
    assert set(tmp_path.rglob("*")) == before
    return lines[0]


def test_demo_out_dir_that_is_a_file_is_refused_before_computing(tmp_path, capsys, no_computation):
    existing = tmp_path / "notes.txt"
    existing.write_text("keep me")
    before = set(tmp_path.rglob("*"))
    line = _refused(capsys, ["demo", "--out-dir", str(existing)], "--out-dir", tmp_path, before)
    assert line == f"crfdepth demo: error: --out-dir: expected a folder (existing or to create), got a file: {existing}"
    assert existing.read_text() == "keep me"
    _refused(capsys, ["demo", "--out-dir", str(existing / "sub")], "--out-dir: expected a folder", tmp_path, before)
    # A file where the data subfolder goes.
    (tmp_path / "out").mkdir()
    (tmp_path / "out" / "data").write_text("")
    before = set(tmp_path.rglob("*"))
    _refused(capsys, ["demo", "--out-dir", str(tmp_path / "out")], "--out-dir: expected a folder", tmp_path, before)


def test_demo_unwritable_out_dir_is_refused_before_computing(tmp_path, capsys, monkeypatch, no_computation):
    locked = tmp_path / "locked"
    locked.mkdir()
    real_access = demo.os.access
    # Tests may run as root, who may write anywhere: stand in for a read-only folder.
    monkeypatch.setattr(demo.os, "access", lambda path, mode: False if str(path) == str(locked) else
                        real_access(path, mode))
    before = set(tmp_path.rglob("*"))
    for out in (locked, locked / "new" / "folder"):
        line = _refused(capsys, ["demo", "--out-dir", str(out)], "--out-dir", tmp_path, before)
        assert line == f"crfdepth demo: error: --out-dir: expected a writable folder, got {locked} (not writable)"


@pytest.mark.parametrize(("flags", "message"), [
    (["--max-frames", "0"], "--max-frames: expected an integer in [1, 2147483647], got '0'"),
    (["--max-frames", "two"], "--max-frames: expected an integer in [1, 2147483647], got 'two'"),
    (["--beams", "0"], "--beams: expected an integer in [1, 128], got '0'"),
    (["--beams", "129"], "--beams: expected an integer in [1, 128], got '129'"),
    (["--seed", "-1"], "--seed: expected an integer in [0, 4294967295], got '-1'"),
    (["--vis-range", "60", "5"], "--vis-range: expected MIN < MAX in metres, got 60 5"),
    (["--vis-range", "0", "5"], "--vis-range: expected a finite number of metres > 0, got '0'"),
    (["--vis-range", "5", "inf"], "--vis-range: expected a finite number of metres > 0, got 'inf'"),
])
def test_demo_bad_flags_are_refused_when_parsed(tmp_path, capsys, no_computation, flags, message):
    out = tmp_path / "out"
    with pytest.raises(SystemExit) as info:
        main(["demo", "--out-dir", str(out), *flags])
    assert info.value.code == 2
    assert capsys.readouterr().err == f"crfdepth demo: error: {message}\n"  # one line
    assert not out.exists()


def test_demo_bad_kitti_folder(tmp_path, capsys, no_computation):
    before = set(tmp_path.rglob("*"))
    line = _refused(capsys, ["demo", "--kitti", str(tmp_path), "--out-dir", str(tmp_path / "out")], "--kitti",
                    tmp_path, before)
    assert "--kitti: expected a folder with depth_selection/val_selection_cropped" in line


def test_demo_creates_nothing_when_the_model_cannot_be_loaded(tmp_path, capsys, monkeypatch):
    def broken(*args, **kwargs):
        raise InputError("--weights: expected a readable weight file, got a broken one")

    monkeypatch.setattr(demo, "load_pretrained", broken)
    _refused(capsys, ["demo", "--out-dir", str(tmp_path / "out")], "--weights", tmp_path, set())
