"""Nothing written before an error, and nothing on stderr before its one line.

- ``--vis-range`` is refused when the arguments are read, before any file is touched;
- a folder run whose write fails (a full disk, simulated) leaves nothing of the failed frame and, when
  it fails before its first frame, nothing at all: no PNG, no run record, no folder it created;
- decoders' C warnings (libpng's ``iCCP``, OpenCV's ``PNG input buffer is incomplete``) never precede
  the error line: run as ``python -m crfdepth`` in a subprocess, since what C code writes to file
  descriptor 2 does not pass through ``sys.stderr``.
"""

from __future__ import annotations

import errno
import os
import struct
import subprocess
import sys
import zlib
from pathlib import Path

import pytest

from crfdepth.cli.decoder_noise import quiet_decoders
from crfdepth.cli.file_errors import FileError
from crfdepth.io.files import LOCK_NAME
from crfdepth.runs import outputs
from crfdepth.runs.resume import RUN_RECORD
from crfdepth.runs.skip_bad import FAILED_CSV
from tests.cli.frames import FAST, files, png, run, same_pngs, stem, write_folder
from tests.cli.test_complete import _synthetic_frame

ROOT = Path(__file__).resolve().parents[2]
PREFIX = "crfdepth complete: error: "


# --------------------------------------------------------------------------- --vis-range


@pytest.mark.parametrize("values, message", [
    (["5", "2"], "--vis-range: expected MIN < MAX in metres, got 5 2"),
    (["5", "5"], "--vis-range: expected MIN < MAX in metres, got 5 5"),
    (["nan", "5"], "--vis-range: expected a finite number of metres > 0, got 'nan'"),
    (["2", "inf"], "--vis-range: expected a finite number of metres > 0, got 'inf'"),
    (["-1", "5"], "--vis-range: expected a finite number of metres > 0, got '-1'"),
    (["0", "5"], "--vis-range: expected a finite number of metres > 0, got '0'"),
])
@pytest.mark.parametrize("mode", ["one frame", "folder"])
def test_vis_range_is_refused_when_the_arguments_are_read(tmp_path, values, message, mode):
    """The inputs do not even exist: the range is refused first, as a usage error (exit status 2)."""
    where = (["--image", tmp_path / "no.png", "--sparse", tmp_path / "no.png", "--intrinsics", tmp_path / "k.txt",
              "--out", tmp_path / "d.png"] if mode == "one frame"
             else ["--input-dir", tmp_path / "missing", "--out-dir", tmp_path / "out"])
    code, out, err = run(["complete", *where, "--vis", tmp_path / "vis", "--vis-range", *values])
    assert code == 2 and out == ""
    assert err == f"{PREFIX}{message}\n"
    assert list(tmp_path.iterdir()) == []


def test_vis_range_without_vis_is_refused(tmp_path):
    """--vis-range only sets the scale of --vis pictures: without --vis it would be silently ignored."""
    code, out, err = run(["complete", "--input-dir", tmp_path / "missing", "--out-dir", tmp_path / "out",
                          "--vis-range", "2", "60"])
    assert code == 2 and out == ""
    assert err == f"{PREFIX}--vis-range 2 60: sets the colour scale of the pictures --vis writes; add --vis (or " \
                  f"leave --vis-range out)\n"
    assert list(tmp_path.iterdir()) == []


# --------------------------------------------------------------------------- a folder run that fails


def _full_disk_after(monkeypatch, pngs: int) -> None:
    """The disk fills up after ``pngs`` PNG files: the next is written in part, then ENOSPC."""
    real = outputs._write_new
    count = [0]

    def write(path: Path, data: bytes) -> None:
        if data.startswith(b"\x89PNG"):
            count[0] += 1
            if count[0] > pngs:
                with open(path, "xb") as handle:
                    handle.write(data[: len(data) // 2])
                raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC), str(path))
        real(path, data)

    monkeypatch.setattr(outputs, "_write_new", write)


@pytest.fixture
def folder(tmp_path) -> Path:
    return write_folder(tmp_path / "val_selection_cropped", 3)


def _argv(folder: Path, tmp_path: Path, *extra) -> list:
    return ["complete", "--input-dir", folder, "--out-dir", tmp_path / "out", "--out-std-dir", tmp_path / "std",
            "--vis", tmp_path / "vis", *FAST, *extra]


@pytest.mark.parametrize("skip_bad", [False, True])
def test_a_run_that_fails_on_its_first_frame_leaves_nothing(folder, tmp_path, monkeypatch, skip_bad):
    """No PNG, no run record, no failed.csv, no lock, and the folders the run created removed; --skip-bad does
    not skip a frame that cannot be written (every later frame would fail the same way)."""
    _full_disk_after(monkeypatch, 1)  # frame 1's std PNG: its depth PNG was written to a temporary file
    code, _, err = run(_argv(folder, tmp_path, *(["--skip-bad"] if skip_bad else [])))
    assert code == 2 and err.count("\n") == 1
    assert err.startswith(f"{PREFIX}--out-std-dir: cannot write {tmp_path / 'std' / png(0)}: No space left on "
                          f"device [stopped at frame 1/3 {stem('velodyne_raw', 0)}; 0 of 3 frame(s) written to ")
    assert ".tmp" not in err and ".crfdepth-" not in err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["val_selection_cropped"]


def test_a_run_that_fails_midway_keeps_the_whole_frames_only(folder, tmp_path, monkeypatch):
    """Frame 1's four files stay, nothing of frame 2; the failure is listed for --resume, which then writes what
    an uninterrupted run writes."""
    _full_disk_after(monkeypatch, 4 + 2)  # frame 2: depth and std PNGs staged, its first picture fails
    code, _, err = run(_argv(folder, tmp_path))
    assert code == 2 and err.count("\n") == 1
    assert err.startswith(f"{PREFIX}--vis: cannot write {tmp_path / 'vis' / stem('velodyne_raw', 1)}_vis_depth.png: "
                          f"No space left on device [stopped at frame 2/3 {stem('velodyne_raw', 1)}; 1 of 3 frame(s) "
                          f"written to {tmp_path / 'out'}; --resume completes the others]")
    assert files(tmp_path / "out") == sorted([png(0), RUN_RECORD, FAILED_CSV])
    assert files(tmp_path / "std") == [png(0)]
    assert files(tmp_path / "vis") == [f"{stem('velodyne_raw', 0)}_vis_{kind}.png" for kind in ("depth", "std")]
    assert not (tmp_path / "out" / LOCK_NAME).exists()

    monkeypatch.undo()
    assert run(_argv(folder, tmp_path, "--resume"))[0] == 0
    whole = tmp_path / "whole"
    assert run(_argv(folder, whole))[0] == 0
    for sub in ("out", "std"):
        same_pngs(tmp_path / sub, whole / sub)
    assert files(tmp_path / "vis") == files(whole / "vis")


def test_a_batch_that_fails_on_its_second_frame_keeps_and_counts_the_first(folder, tmp_path, monkeypatch):
    """--batch-size 2: frame 1 is written before frame 2's write fails; it is counted, kept, and not listed as
    failed (and the run record stays with it, for --resume)."""
    _full_disk_after(monkeypatch, 1)
    code, _, err = run(["complete", "--input-dir", folder, "--out-dir", tmp_path / "out", "--batch-size", 2, *FAST])
    assert code == 2
    assert err.startswith(f"{PREFIX}--out-dir: cannot write {tmp_path / 'out' / png(1)}: No space left on device "
                          f"[stopped at frames 1-2/3 ({stem('velodyne_raw', 0)}, {stem('velodyne_raw', 1)}); 1 of 3 "
                          f"frame(s) written to {tmp_path / 'out'}; ")
    assert files(tmp_path / "out") == sorted([png(0), RUN_RECORD, FAILED_CSV])
    failed = (tmp_path / "out" / FAILED_CSV).read_text().splitlines()
    assert len(failed) == 2 and failed[1].startswith(stem("velodyne_raw", 1))


def test_a_non_finite_first_frame_leaves_nothing(folder, tmp_path, monkeypatch):
    from crfdepth.runs import folder_frames as complete_folder

    real = complete_folder.complete_checked
    monkeypatch.setattr(complete_folder, "complete_checked",
                        lambda *args, **kwargs: (lambda d, s: (d * float("nan"), s))(*real(*args, **kwargs)))
    code, _, err = run(["complete", "--input-dir", folder, "--out-dir", tmp_path / "out", *FAST])
    assert code == 2
    assert err.startswith(f"{PREFIX}--out-dir {tmp_path / 'out' / png(0)}: the model returned ")
    assert not (tmp_path / "out").exists()


def test_an_earlier_unfinished_run_keeps_its_record(folder, tmp_path, monkeypatch):
    """--resume into the folder of a stopped run that then fails again before writing: the earlier run's record,
    frames and failed.csv stay as they were, so that a later --resume still continues it."""
    _full_disk_after(monkeypatch, 1)
    argv = ["complete", "--input-dir", folder, "--out-dir", tmp_path / "out", *FAST]
    assert run(argv)[0] == 2 and files(tmp_path / "out") == sorted([png(0), RUN_RECORD, FAILED_CSV])
    before = {name: (tmp_path / "out" / name).read_bytes() for name in files(tmp_path / "out")}
    _full_disk_after(monkeypatch, 0)
    assert run([*argv, "--resume"])[0] == 2
    assert {name: (tmp_path / "out" / name).read_bytes() for name in files(tmp_path / "out")} == before


def test_write_files_removes_what_it_renamed(tmp_path, monkeypatch):
    """The second file's rename fails: the first one, already renamed into place, is removed again."""
    real = os.replace

    def refuse_second(source, target):
        if Path(target).name == "b.png":
            raise OSError(errno.EROFS, os.strerror(errno.EROFS), str(source))
        real(source, target)

    monkeypatch.setattr(outputs.os, "replace", refuse_second)
    with pytest.raises(FileError) as info:
        outputs.write_files([("--out", tmp_path / "a.png", b"a"), ("--out-std", tmp_path / "b.png", b"b")])
    assert str(info.value) == f"--out-std: cannot write {tmp_path / 'b.png'}: Read-only file system"
    assert list(tmp_path.iterdir()) == []


# --------------------------------------------------------------------------- decoder noise


def _chunk(kind: bytes, body: bytes) -> bytes:
    return struct.pack(">I", len(body)) + kind + body + struct.pack(">I", zlib.crc32(kind + body) & 0xFFFFFFFF)


def _with_bad_iccp(png_bytes: bytes) -> bytes:
    """The PNG with an iCCP chunk whose profile is too short, after IHDR: libpng warns, the image decodes."""
    header = 8 + 4 + 4 + 13 + 4  # signature, IHDR
    return png_bytes[:header] + _chunk(b"iCCP", b"bad\x00\x00" + zlib.compress(b"\x00" * 64)) + png_bytes[header:]


def _crfdepth(*argv) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "crfdepth", *map(str, argv)], capture_output=True, text=True,
                          cwd=ROOT, timeout=600, env={**os.environ, "OPENCV_LOG_LEVEL": "INFO"})


@pytest.fixture
def damaged(tmp_path) -> dict[str, Path]:
    """A frame, with a truncated copy of its image and sparse map and a copy of its image with a bad iCCP chunk."""
    frame = _synthetic_frame(tmp_path / "in")
    image, sparse = frame["image"].read_bytes(), frame["sparse"].read_bytes()
    (tmp_path / "truncated.png").write_bytes(image[: len(image) // 2])
    (tmp_path / "truncated_sparse.png").write_bytes(sparse[: len(sparse) // 2])
    (tmp_path / "iccp.png").write_bytes(_with_bad_iccp(image))
    return {**frame, "truncated": tmp_path / "truncated.png", "truncated sparse": tmp_path / "truncated_sparse.png",
            "iccp": tmp_path / "iccp.png"}


def test_the_damaged_pngs_make_decoder_noise(damaged):
    """The files of these tests make the decoder print something on stderr (else the tests below would prove
    nothing). What it prints is the decoder's business and changes between releases: only that it prints is
    asserted, and that the truncated files do not decode."""
    probe = ("import cv2, numpy, sys\n"
             "for path in sys.argv[1:]:\n"
             "    image = cv2.imdecode(numpy.fromfile(path, numpy.uint8), cv2.IMREAD_UNCHANGED)\n"
             "    print(path, image is not None)\n")
    result = subprocess.run([sys.executable, "-c", probe, damaged["truncated"], damaged["truncated sparse"],
                             damaged["iccp"]], capture_output=True, text=True, timeout=300)
    assert result.stderr.strip() != ""
    assert result.stdout.split() == [str(damaged["truncated"]), "False", str(damaged["truncated sparse"]), "False",
                                     str(damaged["iccp"]), "True"]


@pytest.mark.parametrize("case, expected", [
    ("truncated image", "--image: {truncated} is not a readable image"),
    ("truncated sparse", "--sparse: {truncated sparse} is not a readable image"),
    ("iccp image, truncated sparse", "--sparse: {truncated sparse} is not a readable image"),
    ("iccp image, missing intrinsics", "--intrinsics: no such file: {missing}"),
])
def test_decoder_noise_never_precedes_the_error(damaged, tmp_path, case, expected):
    image = damaged["iccp"] if case.startswith("iccp") else damaged["truncated"] if case == "truncated image" \
        else damaged["image"]
    sparse = damaged["truncated sparse"] if "sparse" in case else damaged["sparse"]
    intrinsics = tmp_path / "missing.txt" if "missing" in case else damaged["intrinsics"]
    result = _crfdepth("complete", "--image", image, "--sparse", sparse, "--intrinsics", intrinsics,
                       "--out", tmp_path / "d.png", "--mode", "pixel", *FAST)
    assert result.returncode == 2
    line = f"{PREFIX}{expected.format(missing=intrinsics, **{k: v for k, v in damaged.items()})}"
    assert result.stderr.splitlines()[0].startswith(line), result.stderr
    assert result.stderr.count("\n") == 1 and not (tmp_path / "d.png").exists()


def test_a_warning_png_that_decodes_completes_quietly(damaged, tmp_path):
    result = _crfdepth("complete", "--image", damaged["iccp"], "--sparse", damaged["sparse"], "--intrinsics",
                       damaged["intrinsics"], "--out", tmp_path / "d.png", "--mode", "pixel", *FAST)
    assert result.returncode == 0 and result.stderr == "", result.stderr
    assert (tmp_path / "d.png").is_file()


def test_folder_mode_decoder_noise_never_precedes_the_error(tmp_path):
    data = write_folder(tmp_path / "val_selection_cropped", 2)
    image = data / "image" / f"{stem('image', 1)}.png"
    image.write_bytes(image.read_bytes()[:200])
    result = _crfdepth("complete", "--input-dir", data, "--out-dir", tmp_path / "out", *FAST)
    assert result.returncode == 2
    first = result.stderr.splitlines()[0]
    assert first.startswith(f"{PREFIX}frame 2/2 {stem('velodyne_raw', 1)}") and "not a readable image" in first, \
        result.stderr
    assert result.stderr.count("\n") == 1 and not (tmp_path / "out").exists()


def test_quiet_decoders_keeps_other_lines(capfd):
    with quiet_decoders():
        os.write(2, b"libpng warning: iCCP: known incorrect sRGB profile\n")
        os.write(2, b"[ WARN:0@0.016] global grfmt_png.cpp:793 readFromStreamOrBuffer PNG input buffer is incomplete\n")
        os.write(2, b"crfdepth complete: warning: something the user should see\n")
    assert capfd.readouterr().err == "crfdepth complete: warning: something the user should see\n"


def test_quiet_decoders_when_the_decode_fails(capfd):
    with pytest.raises(ValueError):
        with quiet_decoders():
            os.write(2, b"libpng error: Read Error\nsomething else\n")
            raise ValueError("not a readable image")
    assert capfd.readouterr().err == "something else\n"
