"""Small synthetic folders for the folder-mode CLI tests (output lock, check-first, interrupt).

:func:`write_folder` writes synthetic street scenes (:func:`crfdepth.data.synthetic.make_scene`,
16 beams) in the ``val_selection_cropped`` layout, so that ``complete --input-dir`` and
``evaluate --layout val_selection`` read them; chosen frames can be made bad. :func:`same_pngs` and
:func:`same_report` compare the outputs of two runs.
"""

from __future__ import annotations

import contextlib
import io
from pathlib import Path

import numpy as np
import pytest

from crfdepth import cli
from crfdepth.data.synthetic import make_scene, selection_stem, write_selection_folder
from crfdepth.io.kitti import read_depth_png, write_depth_png

DRIVE = "2011_09_26_drive_0001_sync"
SIZE = (48, 160)  # (H, W): small, so that a frame completes in well under a second
# Cheap model options for tests about files rather than accuracy.
FAST = ["--potentials", "colour", "--quiet"]
COMMANDS = ("crfdepth.cli.complete", "crfdepth.cli.evaluate")


def stem(kind: str, index: int) -> str:
    return selection_stem(kind, index, DRIVE)


def png(index: int) -> str:
    """The output PNG name of frame ``index`` (its velodyne_raw file name)."""
    return f"{stem('velodyne_raw', index)}.png"


def write_folder(root: Path, count: int, bad: dict[int, str] | None = None) -> Path:
    """``count`` frames; ``bad`` maps a frame index to "zero sparse" (no LiDAR point) or "unreadable image"."""
    bad = bad or {}
    write_selection_folder(root, (make_scene(index, *SIZE, beams=16) for index in range(count)), DRIVE)
    for index, kind in bad.items():
        if kind == "zero sparse":
            write_depth_png(root / "velodyne_raw" / png(index), np.zeros(SIZE))
        elif kind == "unreadable image":
            (root / "image" / f"{stem('image', index)}.png").write_bytes(b"not a png")
    return root


def files(folder: Path) -> list[str]:
    """Every file under ``folder`` (hidden ones included: temporary files, the lock), relative, sorted."""
    return sorted(str(p.relative_to(folder)) for p in folder.rglob("*") if p.is_file())


def run(argv: list) -> tuple[int, str, str]:
    """(exit status, stdout, stderr) of ``crfdepth`` with ``argv`` in this process, argparse's SystemExit caught,
    with only complete and evaluate registered."""
    out, err = io.StringIO(), io.StringIO()
    with pytest.MonkeyPatch.context() as mp, contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        mp.setattr(cli, "_COMMANDS", COMMANDS)
        try:
            code = cli.main([str(a) for a in argv])
        except SystemExit as exc:
            code = exc.code
    return code, out.getvalue(), err.getvalue()


def run_main(argv: list, capsys) -> tuple[int, str, str]:
    """(exit status, stdout, stderr) of ``crfdepth`` with ``argv`` in this process, every command registered,
    argparse's SystemExit caught; the output read through pytest's ``capsys``."""
    try:
        code = cli.main([str(a) for a in argv])
    except SystemExit as exc:
        code = exc.code
    captured = capsys.readouterr()
    return code, captured.out, captured.err


def same_pngs(a: Path, b: Path) -> None:
    """The folders hold the same files; depths (and stds) within one PNG code, 1/256 m (a batch's or another
    process's CPU threads may sum in another order)."""
    assert files(a) == files(b)
    for name in files(a):
        if name.endswith(".png"):
            assert np.abs(read_depth_png(a / name) - read_depth_png(b / name)).max() <= 1 / 256 + 1e-9, name


def same_report(a, b) -> bool:
    """Two ``summary.json`` values (or parts) equal, numbers within float tolerance, the run's time aside."""
    if isinstance(a, dict):
        return a.keys() == b.keys() and all(same_report(a[k], b[k]) for k in a if k != "seconds")
    if isinstance(a, float):
        return b == pytest.approx(a, rel=1e-6, abs=1e-9)
    return a == b
