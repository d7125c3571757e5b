"""OS errors from the command line: one line naming the user's flag, exit status 2, never a traceback.

A file name too long (ENAMETOOLONG), a read-only output location (EROFS / EACCES: real with
chmod where the tests do not run as root, simulated everywhere), a full disk (ENOSPC,
simulated), a folder where a file is expected; an OS error no command told is named by the
flag whose path it concerns (:func:`crfdepth.cli.file_errors.error_message`).
"""

from __future__ import annotations

import errno
import os
from pathlib import Path

import numpy as np
import pytest

from crfdepth import cli
from crfdepth.cli import complete, complete_one
from crfdepth.cli.file_errors import FileError, error_message, flagged
from crfdepth.errors import InputError
from crfdepth.io import files as io_files
from crfdepth.io.kitti import read_depth_png
from crfdepth.runs import outputs
from tests.cli.frames import FAST, files, run, write_folder
from tests.cli.test_complete import _synthetic_frame

LONG = "a" * 300  # longer than any file system's 255-byte limit on a name
PREFIX = "crfdepth complete: error: "


@pytest.fixture
def frame(tmp_path) -> dict[str, Path]:
    return _synthetic_frame(tmp_path / "in")


def _one(frame: dict, out, *extra) -> list:
    return ["complete", "--image", frame["image"], "--sparse", frame["sparse"], "--intrinsics", frame["intrinsics"],
            "--out", out, "--mode", "pixel", *FAST, *extra]


def _first_line(err: str) -> str:
    assert err.endswith("\n") and "Traceback" not in err
    return err.splitlines()[0]


def _no_temporaries(folder: Path) -> None:
    assert not [name for name in files(folder) if ".tmp" in name or name.startswith(".crfdepth-")]


# --------------------------------------------------------------------------- file name too long


@pytest.mark.parametrize("where", ["name", "folder"])
def test_out_name_too_long(frame, tmp_path, where):
    out = tmp_path / f"{LONG}.png" if where == "name" else tmp_path / LONG / "depth.png"
    code, _, err = run(_one(frame, out))
    assert code == 2
    assert _first_line(err) == f"{PREFIX}--out: cannot write {out}: File name too long"
    assert err.count("\n") == 1
    assert sorted(p.name for p in tmp_path.iterdir()) == ["in"]


@pytest.mark.parametrize("flag", ["--image", "--sparse", "--intrinsics"])
def test_input_name_too_long(frame, tmp_path, flag):
    key = flag[2:]
    bad = {**frame, key: tmp_path / f"{LONG}.png"}
    code, _, err = run(_one(bad, tmp_path / "depth.png"))
    assert code == 2
    assert _first_line(err) == f"{PREFIX}{flag}: cannot read {bad[key]}: File name too long"
    assert not (tmp_path / "depth.png").exists()


@pytest.mark.parametrize("flag", ["--out-dir", "--out-std-dir", "--vis"])
def test_folder_mode_output_folder_name_too_long(tmp_path, flag):
    data = write_folder(tmp_path / "val_selection_cropped", 1)
    targets = {"--out-dir": tmp_path / "out", flag: tmp_path / LONG / "x"}
    code, _, err = run(["complete", "--input-dir", data, *[a for kv in targets.items() for a in kv], *FAST])
    assert code == 2
    assert _first_line(err) == f"{PREFIX}{flag}: cannot write {tmp_path / LONG / 'x'}: File name too long"
    assert not (tmp_path / "out").exists()


def test_input_dir_name_too_long(tmp_path):
    code, _, err = run(["complete", "--input-dir", tmp_path / LONG, "--out-dir", tmp_path / "out", *FAST])
    assert code == 2
    assert _first_line(err) == f"{PREFIX}--input-dir: cannot read {tmp_path / LONG}: File name too long"


def test_vis_folder_name_too_long_is_refused_before_the_work(frame, tmp_path, monkeypatch):
    monkeypatch.setattr(complete_one, "build_model", None)  # must not be reached
    vis = tmp_path / LONG
    code, _, err = run(_one(frame, tmp_path / "depth.png", "--vis", vis))
    assert code == 2 and _first_line(err) == f"{PREFIX}--vis: cannot write {vis}: File name too long"
    assert not (tmp_path / "depth.png").exists()


# --------------------------------------------------------------------------- read-only output location


@pytest.mark.skipif(os.geteuid() == 0, reason="root writes into a chmod 0o555 folder; the simulated tests below "
                                              "cover this case there")
def test_read_only_out_folder(frame, tmp_path):
    locked = tmp_path / "locked"
    locked.mkdir(mode=0o555)
    code, _, err = run(_one(frame, locked / "depth.png"))
    assert code == 2
    assert _first_line(err) == (f"{PREFIX}--out: cannot create {locked / 'depth.png'}: the folder {locked} does not "
                                f"accept new files (Permission denied)")
    assert files(locked) == []


def test_read_only_out_folder_simulated_up_front(frame, tmp_path, monkeypatch):
    """A read-only mount refuses the probe file: refused before any work, naming --out."""
    monkeypatch.setattr(io_files, "probe_folder", lambda folder: os.strerror(errno.EROFS))
    monkeypatch.setattr(complete_one, "build_model", None)  # must not be reached
    out = tmp_path / "depth.png"
    code, _, err = run(_one(frame, out))
    assert code == 2
    assert _first_line(err) == (f"{PREFIX}--out: cannot create {out}: the folder {tmp_path} does not accept new "
                                f"files (Read-only file system)")
    assert not out.exists()


@pytest.mark.parametrize("code_", [errno.EROFS, errno.EACCES, errno.ENOSPC])
def test_write_fails_when_the_file_is_written(frame, tmp_path, monkeypatch, code_):
    """The folder turned read-only (or the disk full) between the check and the write: the temporary file's
    error is told as the output's, naming --out; the old output is left as it was, no temporary file stays."""
    out_dir = tmp_path / "out"
    out_dir.mkdir()
    out = out_dir / "depth.png"
    out.write_bytes(b"an earlier result")

    def fail(path: Path, data: bytes) -> None:
        with open(path, "xb") as handle:  # part of the file is written first, as on a full disk
            handle.write(data[: len(data) // 2])
        raise OSError(code_, os.strerror(code_), str(path))

    monkeypatch.setattr(outputs, "_write_new", fail)
    code, _, err = run(_one(frame, out))
    assert code == 2
    assert _first_line(err) == f"{PREFIX}--out: cannot write {out}: {os.strerror(code_)}"
    assert err.count("\n") == 1 and ".tmp" not in err and ".crfdepth-" not in err
    assert files(out_dir) == ["depth.png"] and out.read_bytes() == b"an earlier result"


def test_rename_fails(frame, tmp_path, monkeypatch):
    """The rename of the temporary file over --out is refused: the message names --out, not the temporary."""
    real = os.replace

    def refuse(source, target):
        if Path(target).parent == tmp_path:
            raise PermissionError(errno.EACCES, os.strerror(errno.EACCES), str(source), None, str(target))
        real(source, target)

    monkeypatch.setattr(outputs.os, "replace", refuse)
    out = tmp_path / "depth.png"
    code, _, err = run(_one(frame, out))
    assert code == 2 and _first_line(err) == f"{PREFIX}--out: cannot write {out}: Permission denied"
    _no_temporaries(tmp_path)
    assert not out.exists()


def test_full_disk_on_the_std_leaves_neither_file(frame, tmp_path, monkeypatch):
    """--out and --out-std are written together: the std's ENOSPC leaves no depth PNG either."""
    real = outputs._write_new
    written = []

    def second_fails(path: Path, data: bytes) -> None:
        written.append(path)
        if len(written) == 2:
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC), str(path))
        real(path, data)

    monkeypatch.setattr(outputs, "_write_new", second_fails)
    out, std = tmp_path / "o" / "depth.png", tmp_path / "o" / "std.png"
    out.parent.mkdir()
    code, _, err = run(_one(frame, out, "--out-std", std))
    assert code == 2 and _first_line(err) == f"{PREFIX}--out-std: cannot write {std}: No space left on device"
    assert files(out.parent) == []


# --------------------------------------------------------------------------- a folder where a file is expected


@pytest.mark.parametrize("flag", ["--image", "--sparse", "--intrinsics"])
def test_input_is_a_folder(frame, tmp_path, flag):
    bad = {**frame, flag[2:]: tmp_path}
    code, _, err = run(_one(bad, tmp_path / "depth.png"))
    assert code == 2 and _first_line(err) == f"{PREFIX}{flag}: expected a file, got a folder: {tmp_path}"


@pytest.mark.parametrize("flag", ["--points", "--calib"])
def test_point_cloud_inputs_name_their_flag(frame, tmp_path, flag):
    cloud = tmp_path / "cloud.npy"
    np.save(cloud, np.array([[5.0, 0.0, 0.0]]))
    given = {"--points": cloud, "--calib": tmp_path / "missing.yaml", flag: tmp_path / "nope.ply"}
    code, _, err = run(["complete", "--image", frame["image"], "--points", given["--points"], "--calib",
                        given["--calib"], "--out", tmp_path / "d.png", *FAST])
    assert code == 2 and _first_line(err).startswith(f"{PREFIX}{flag}: ") and "nope.ply" in err


def test_output_is_a_folder(frame, tmp_path):
    (tmp_path / "std.png").mkdir()
    code, _, err = run(_one(frame, tmp_path / "depth.png", "--out-std", tmp_path / "std.png"))
    assert code == 2
    assert _first_line(err) == f"{PREFIX}--out-std: expected a file name, got a folder: {tmp_path / 'std.png'}"


def test_out_dir_under_a_file_is_refused_before_the_work(tmp_path):
    data = write_folder(tmp_path / "val_selection_cropped", 1)
    blocker = tmp_path / "file"
    blocker.write_text("x")
    code, _, err = run(["complete", "--input-dir", data, "--out-dir", blocker / "out", *FAST])
    assert code == 2
    assert _first_line(err) == f"{PREFIX}--out-dir: expected a folder, got a path under the file {blocker}: " \
                               f"{blocker / 'out'}"


# --------------------------------------------------------------------------- the last resort


def _raising(exc: BaseException):
    def run_one(args):
        raise exc
    return run_one


@pytest.mark.parametrize("make, expected", [
    (lambda t: OSError(errno.EIO, os.strerror(errno.EIO), str(t / "in" / "sparse.png")),
     "--sparse: cannot use {t}/in/sparse.png: Input/output error"),
    (lambda t: OSError(errno.ENOSPC, os.strerror(errno.ENOSPC), str(t / ".depth.png.a1b2.tmp")),
     "--out: cannot write {t}/depth.png: No space left on device"),
    (lambda t: PermissionError(errno.EACCES, os.strerror(errno.EACCES), str(t / "in" / "K.txt")),
     "--intrinsics: cannot use {t}/in/K.txt: Permission denied"),
    (lambda t: OSError(errno.EIO, os.strerror(errno.EIO), "/elsewhere/x"),
     "cannot use /elsewhere/x: Input/output error"),
    (lambda t: OSError(errno.EIO, os.strerror(errno.EIO)), "Input/output error"),
])
def test_an_os_error_no_command_told_names_the_flag(frame, tmp_path, monkeypatch, make, expected):
    monkeypatch.setattr(complete, "read_one", _raising(make(tmp_path)))
    code, _, err = run(_one(frame, tmp_path / "depth.png"))
    assert code == 2 and err == f"{PREFIX}{expected.format(t=tmp_path)}\n"


def test_error_message_of_flagged_and_bad_input():
    assert error_message(FileError("--out: cannot write d.png: Read-only file system"), []) == \
        "--out: cannot write d.png: Read-only file system"
    assert error_message(InputError("--image: expected ...\n  second line"), []) == \
        "--image: expected ...\n  second line"  # a listing of bad frames keeps its lines
    argv = ["complete", "--out=out/d.png", "--vis", "pics"]
    assert error_message(OSError(errno.EROFS, "Read-only file system", "pics/a.png"), argv) == \
        "--vis: cannot write pics/a.png: Read-only file system"
    assert error_message(OSError(errno.EROFS, "Read-only file system", "out/.x.tmp"), argv) == \
        "--out: cannot write out/d.png: Read-only file system"
    # a temporary file of crfdepth.io.files.atomic_write in an output folder: the file it stands for
    assert error_message(OSError(errno.ENOSPC, "No space left on device", "ev/png/.f1.png.0123456789ab.tmp"),
                         ["evaluate", "--out-dir", "ev"]) == "--out-dir: cannot write ev/png/f1.png: No space left on device"


def test_flagged_relabels_and_tells_system_errors(tmp_path):
    with pytest.raises(FileNotFoundError, match=r"^--sparse: no such file: x.png$"):
        with flagged("--sparse", "x.png", labels=("depth png",)):
            raise FileNotFoundError("depth png: no such file: x.png")
    with pytest.raises(InputError, match=r"^--points: PLY x.ply: malformed header$"):
        with flagged("--points", "x.ply"):
            raise InputError("PLY x.ply: malformed header")
    with pytest.raises(FileError, match=r"^--calib: cannot read day/calib_cam_to_cam.txt: Permission denied$"):
        with flagged("--calib", "day"):
            raise PermissionError(errno.EACCES, "Permission denied", "day/calib_cam_to_cam.txt")
    with pytest.raises(FileError, match=r"^--out: cannot write o.png: No space left on device$"):
        with flagged("--out", "o.png", "write"):
            raise OSError(errno.ENOSPC, "No space left on device", ".o.png.123.tmp")


def test_main_turns_every_os_error_into_one_line(monkeypatch, capsys):
    """main itself, with a command whose run raises an OSError of the system: one line, exit status 2."""
    import crfdepth.cli.project as project

    monkeypatch.setattr(cli, "_COMMANDS", ("crfdepth.cli.project",))
    monkeypatch.setattr(project, "run", _raising(IsADirectoryError(errno.EISDIR, "Is a directory", "out.png")))
    code = cli.main(["project", "--velodyne", "x.bin", "--calib", "c", "--image", "i.png", "--out", "out.png"])
    assert code == 2
    assert capsys.readouterr().err == "crfdepth project: error: --out: cannot use out.png: Is a directory\n"


def test_depth_png_bytes_are_the_kitti_writer_s(tmp_path):
    """outputs encodes depth PNGs itself (to stage a frame's files): the bytes of crfdepth.io.kitti's writer."""
    from crfdepth.io.kitti import write_depth_png

    depth = np.array([[0.0, 1 / 512, 1.0], [12.34567, 300.0, 80.0]], np.float32)
    write_depth_png(tmp_path / "kitti.png", depth)
    assert outputs._depth_png(depth, "--out", tmp_path / "x.png") == (tmp_path / "kitti.png").read_bytes()
    outputs.write_files([("--out", tmp_path / "mine.png", outputs._depth_png(depth, "--out", tmp_path))])
    np.testing.assert_array_equal(read_depth_png(tmp_path / "mine.png"), read_depth_png(tmp_path / "kitti.png"))


def test_one_frame_outputs_are_whole(frame, tmp_path):
    """A successful run leaves exactly its files: no temporary file, the PNG readable."""
    out = tmp_path / "o" / "depth.png"
    out.parent.mkdir()
    code, _, err = run(_one(frame, out, "--out-std", out.parent / "std.png", "--vis"))
    assert code == 0, err
    assert files(out.parent) == ["depth.png", "depth_vis_depth.png", "depth_vis_std.png", "std.png"]
    assert read_depth_png(out).min() > 0
