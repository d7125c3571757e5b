"""demo, complete and evaluate run the weights in their own structure and say so (issue 25):
the model line, the model actually built, --mode overriding it, --quiet, bare state dicts
refused through --checkpoint, and help texts that say the truth."""

from __future__ import annotations

import re
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch

import crfdepth.cli.demo as demo
import crfdepth.cli.model_options as model_options
from crfdepth import cli
from crfdepth.checkpoints import load_pretrained, save_model
from crfdepth.data.synthetic import make_scene
from crfdepth.io.kitti import write_depth_png
from crfdepth.model import CRFDepth
from crfdepth.weights import WEIGHTS

KITTI_LINE = "model: kitti weights, pixel grid, log depth, occlusion gate"
PAPER_LINE = "model: paper weights, superpixel graph (5500 segments) + pixel refinement, depth, no gate"
COMMANDS = ("crfdepth.cli.complete", "crfdepth.cli.evaluate", "crfdepth.cli.demo")


@pytest.fixture
def main(monkeypatch):
    """``crfdepth.cli.main`` with the three model commands registered only."""
    monkeypatch.setattr(cli, "_COMMANDS", COMMANDS)
    return lambda argv: cli.main([str(a) for a in argv])


@pytest.fixture
def built(monkeypatch) -> list[CRFDepth]:
    """Every model the commands build from a shipped set, in order (demo's and build_model's loader spied on)."""
    models = []

    def spy(*args, **kwargs):
        model = load_pretrained(*args, **kwargs)
        models.append(model)
        return model

    monkeypatch.setattr(model_options, "load_pretrained", spy)
    monkeypatch.setattr(demo, "load_pretrained", spy)
    return models


def _structure(model: CRFDepth) -> tuple:
    return model.settings.structure.mode, model.settings.structure.variable, model.settings.gate.enabled


@pytest.fixture(scope="module")
def frame(tmp_path_factory) -> dict[str, Path]:
    """A small synthetic street frame (176x608, 64 beams) as the files ``complete`` reads."""
    folder = tmp_path_factory.mktemp("frame")
    t = make_scene(0, height=176, width=608).to_tensors()
    rgb = (t["image"].permute(1, 2, 0).numpy() * 255).round().astype(np.uint8)
    cv2.imwrite(str(folder / "rgb.png"), cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR))
    write_depth_png(folder / "sparse.png", t["sparse"][0].double().numpy())
    np.savetxt(folder / "K.txt", t["K"].double().numpy())
    return {"image": folder / "rgb.png", "sparse": folder / "sparse.png", "intrinsics": folder / "K.txt"}


def _complete(frame: dict, out: Path, *extra) -> list:
    return ["complete", "--image", frame["image"], "--sparse", frame["sparse"], "--intrinsics", frame["intrinsics"],
            "--out", out, *extra]


def _evaluate(out_dir: Path, *extra) -> list:
    return ["evaluate", "--layout", "synthetic", "--limit", 1, "--out-dir", out_dir, *extra]


def _first_line(text: str) -> str:
    return text.splitlines()[0] if text else ""


# --------------------------------------------------------------------------- defaults: the weights' own structure


def test_complete_default_is_the_kitti_structure(main, built, frame, tmp_path, capsys):
    assert main(_complete(frame, tmp_path / "d.png")) == 0
    captured = capsys.readouterr()
    assert _first_line(captured.out) == KITTI_LINE
    assert captured.out.splitlines()[1].startswith(f"wrote {tmp_path / 'd.png'}")
    assert [_structure(m) for m in built] == [("pixel", "log", True)]
    assert (tmp_path / "d.png").is_file()


def test_evaluate_default_is_the_kitti_structure(main, built, tmp_path, capsys):
    assert main(_evaluate(tmp_path / "out")) == 0
    out = capsys.readouterr().out
    assert _first_line(out) == KITTI_LINE
    assert [_structure(m) for m in built] == [("pixel", "log", True)]
    # The report line names the same structure (it said "pixel mode" while --mode's help said superpixel).
    assert re.search(r"^crfdepth evaluate: kitti weights on synthetic, pixel grid, log depth, occlusion gate, "
                     r"float32$", out, re.MULTILINE), out


def test_demo_default_is_the_kitti_structure(main, built, monkeypatch, tmp_path, capsys):
    monkeypatch.setattr(demo, "_pictures", lambda *args: {})  # skip the drawing, keep the rest
    assert main(["demo", "--out-dir", tmp_path / "demo"]) == 0
    out = capsys.readouterr().out
    assert _first_line(out) == KITTI_LINE
    assert [_structure(m) for m in built] == [("pixel", "log", True)]
    assert re.search(r"crfdepth\s+RMSE [\d.]+ mm", out)


def test_paper_weights_keep_their_own_structure(main, built, frame, tmp_path, capsys):
    assert main(_complete(frame, tmp_path / "d.png", "--weights", "paper")) == 0
    assert _first_line(capsys.readouterr().out) == PAPER_LINE
    assert [(_structure(m), m.settings.structure.refine) for m in built] == [(("superpixel", "depth", False), True)]


# --------------------------------------------------------------------------- explicit options override


def test_mode_overrides_the_structure_and_says_so(main, built, frame, tmp_path, capsys):
    argv = _complete(frame, tmp_path / "d.png", "--mode", "superpixel", "--superpixels", 300, "--no-refine")
    assert main(argv) == 0
    assert _first_line(capsys.readouterr().out) == (
        "model: kitti weights, superpixel graph (300 segments), no refinement, log depth, occlusion gate "
        "(set by --mode superpixel --superpixels 300 --no-refine; the weights' own: pixel grid, log depth, "
        "occlusion gate)")
    structures = [(_structure(m), m.settings.structure.superpixels, m.settings.structure.refine) for m in built]
    assert structures == [(("superpixel", "log", True), 300, False)]


def test_demo_mode_overrides_the_structure(main, built, monkeypatch, tmp_path, capsys):
    monkeypatch.setattr(demo, "_pictures", lambda *args: {})
    monkeypatch.setattr(demo, "complete_depth", lambda image, **kw: (torch.ones(image.shape[-2:]),) * 2)
    assert main(["demo", "--out-dir", tmp_path / "demo", "--mode", "superpixel"]) == 0
    assert _first_line(capsys.readouterr().out).startswith(
        "model: kitti weights, superpixel graph (5500 segments) + pixel refinement, log depth, occlusion gate "
        "(set by --mode superpixel;")
    assert [_structure(m) for m in built] == [("superpixel", "log", True)]


def test_checkpoint_runs_in_its_stored_structure(main, frame, tmp_path, capsys):
    path = save_model(CRFDepth(mode="pixel", variable="inverse", gate=True, potentials=("colour", "normal")),
                      tmp_path / "mine.pt")
    assert main(_complete(frame, tmp_path / "d.png", "--checkpoint", path)) == 0
    assert _first_line(capsys.readouterr().out) == (
        f"model: checkpoint {path}, pixel grid, inverse depth, occlusion gate, potentials colour,normal")
    assert main(_complete(frame, tmp_path / "e.png", "--checkpoint", path, "--mode", "superpixel",
                          "--superpixels", 200, "--no-refine")) == 0
    assert _first_line(capsys.readouterr().out) == (
        f"model: checkpoint {path}, superpixel graph (200 segments), no refinement, inverse depth, occlusion gate, "
        f"potentials colour,normal (set by --mode superpixel --superpixels 200 --no-refine)")


# --------------------------------------------------------------------------- --quiet


def test_quiet_drops_the_model_line(main, built, frame, tmp_path, capsys):
    assert main(_complete(frame, tmp_path / "d.png", "--quiet")) == 0
    assert capsys.readouterr().out == ""
    assert main(_evaluate(tmp_path / "out", "--quiet")) == 0
    assert "model: " not in capsys.readouterr().out
    assert [_structure(m) for m in built] == [("pixel", "log", True)] * 2  # quiet, same model


# --------------------------------------------------------------------------- bare state dicts through --checkpoint


def _bare(tmp_path: Path) -> Path:
    path = tmp_path / "kitti_state.pt"
    torch.save(load_pretrained("kitti").state_dict(), path)
    return path


def _bare_line(command: str, path: Path) -> str:
    return (f"crfdepth {command}: error: --checkpoint: {path}: expected a complete model file, got a bare state "
            f"dict: it holds weights but not the model's structure (mode, variable, gate ...); load it into the "
            f"model it came from and save that with crfdepth.save_model(model, path), or give the "
            f"trainer's Lightning .ckpt as it is")


def test_complete_refuses_a_bare_state_dict(main, frame, tmp_path, capsys):
    path = _bare(tmp_path)
    out = tmp_path / "out" / "d.png"
    out.parent.mkdir()
    assert main(_complete(frame, out, "--checkpoint", path, "--vis", tmp_path / "vis")) == 2
    captured = capsys.readouterr()
    assert captured.err.splitlines() == [_bare_line("complete", path)]
    assert captured.out == "" and list(out.parent.iterdir()) == [] and not (tmp_path / "vis").exists()


def test_evaluate_refuses_a_bare_state_dict(main, tmp_path, capsys):
    path = _bare(tmp_path)
    assert main(_evaluate(tmp_path / "out", "--checkpoint", path)) == 2
    captured = capsys.readouterr()
    assert captured.err.splitlines() == [_bare_line("evaluate", path)]
    assert captured.out == "" and not (tmp_path / "out").exists()


def test_evaluate_refuses_its_out_dir_before_building_the_model(main, built, tmp_path, capsys):
    (tmp_path / "out").write_text("a file")
    assert main(_evaluate(tmp_path / "out")) == 2
    captured = capsys.readouterr()
    assert _first_line(captured.err).startswith("crfdepth evaluate: error: --out-dir: expected a folder, got a file")
    assert captured.out == "" and built == []


# --------------------------------------------------------------------------- help texts


def _help(main, capsys, command: str) -> str:
    with pytest.raises(SystemExit) as info:
        main([command, "--help"])
    assert info.value.code == 0
    return " ".join(capsys.readouterr().out.split())  # argparse wraps lines


@pytest.mark.parametrize("command", ["complete", "evaluate", "demo"])
def test_help_names_the_real_default_structure(main, capsys, command):
    text = _help(main, capsys, command)
    own = ", ".join(f"{name}: {load_pretrained(name).settings.structure.mode}" for name in WEIGHTS)
    assert own == "kitti: pixel, paper: superpixel, nyu: pixel"
    assert f"default: the weights' own structure ({own})" in text
    assert "else superpixel" not in text and "default: superpixel" not in text


@pytest.mark.parametrize("command", ["complete", "evaluate"])
def test_checkpoint_help_names_the_real_function(main, capsys, command):
    text = _help(main, capsys, command)
    assert "crfdepth.checkpoint" not in text
    assert "crfdepth.save_model(model, path)" in text and "a bare state_dict is refused" in text
    import crfdepth.weights

    assert callable(crfdepth.save_model)
