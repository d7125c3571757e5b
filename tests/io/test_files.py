"""crfdepth.io.files: output-path checks and the atomic write."""

from __future__ import annotations

import os

import pytest

from crfdepth.errors import InputError
from crfdepth.io.files import atomic_write, atomic_write_bytes, check_input_file, check_output_file


def test_atomic_write_replaces_and_leaves_no_temporary(tmp_path):
    path = tmp_path / "out.txt"
    path.write_text("old")
    atomic_write_bytes(path, b"new")
    assert path.read_bytes() == b"new" and [p.name for p in tmp_path.iterdir()] == ["out.txt"]


def test_failed_write_keeps_the_old_file(tmp_path):
    path = tmp_path / "out.txt"
    path.write_text("old")

    def half(temporary):
        temporary.write_text("partial")
        raise RuntimeError("disk full")

    with pytest.raises(RuntimeError, match="disk full"):
        atomic_write(path, half)
    assert path.read_text() == "old" and [p.name for p in tmp_path.iterdir()] == ["out.txt"]


def test_output_path_checks_name_the_argument(tmp_path):
    assert check_output_file(tmp_path / "a.json") == tmp_path / "a.json"
    with pytest.raises(InputError, match="out: expected a file name, got a folder"):
        check_output_file(tmp_path, "out")
    with pytest.raises(FileNotFoundError, match="path: the folder of"):
        check_output_file(tmp_path / "missing" / "a.json")
    assert check_output_file(tmp_path / "a.PNG", "--out", suffix=".png") == tmp_path / "a.PNG"
    with pytest.raises(InputError, match=r"^--out: expected a file name ending in \.png, got .*a\.jpg$"):
        check_output_file(tmp_path / "a.jpg", "--out", suffix=".png")


def test_output_check_creates_nothing_and_refuses_a_folder_that_takes_no_files(tmp_path):
    check_output_file(tmp_path / "a.png", "--out")
    assert list(tmp_path.iterdir()) == []  # the probe file is gone
    if not os.path.isdir("/proc"):
        pytest.skip("no /proc on this system")
    with pytest.raises(PermissionError) as info:  # root passes os.access, yet /proc takes no new file
        check_output_file("/proc/o.png", "--out")
    assert str(info.value).startswith("--out: cannot create /proc/o.png: the folder /proc does not accept new files")


def test_input_check_names_the_argument(tmp_path):
    (tmp_path / "a.bin").write_bytes(b"")
    assert check_input_file(tmp_path / "a.bin", "--velodyne") == tmp_path / "a.bin"
    with pytest.raises(FileNotFoundError, match=r"^--velodyne: no such file: .*nope\.bin$"):
        check_input_file(tmp_path / "nope.bin", "--velodyne")
    with pytest.raises(IsADirectoryError, match=r"^--calib: expected a file, got a folder"):
        check_input_file(tmp_path, "--calib")
