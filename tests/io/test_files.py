"""crfdepth.io.files: output-path checks and the atomic write."""

from __future__ import annotations

import pytest

from crfdepth.errors import InputError
from crfdepth.io.files import atomic_write, atomic_write_bytes, check_output_file


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
