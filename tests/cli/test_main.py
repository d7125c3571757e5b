"""Tests of ``crfdepth.cli.main``: --version, Ctrl-C, one-line usage errors, ``python -m crfdepth``."""

from __future__ import annotations

import argparse
import importlib.metadata
import subprocess
import sys
import tomllib
from pathlib import Path

import pytest

import crfdepth
from crfdepth import _version, cli

PYPROJECT = Path(__file__).resolve().parents[2] / "pyproject.toml"


@pytest.fixture
def main(monkeypatch):
    """``crfdepth.cli.main`` with only ``project`` registered (another sub-command's import
    cannot make these tests fail; those are tested in their own files)."""
    monkeypatch.setattr(cli, "_COMMANDS", ("crfdepth.cli.project",))
    return cli.main


def _pyproject_version() -> str:
    return tomllib.loads(PYPROJECT.read_text())["project"]["version"]


def test_version_is_the_package_metadata_and_pyproject(main, capsys):
    assert crfdepth.__version__ == importlib.metadata.version("crfdepth") == _pyproject_version()
    with pytest.raises(SystemExit) as info:
        main(["--version"])
    assert info.value.code == 0
    assert capsys.readouterr().out == f"crfdepth {crfdepth.__version__}\n"


def test_version_falls_back_to_pyproject_when_not_installed(monkeypatch, tmp_path):
    def not_installed(name):
        raise importlib.metadata.PackageNotFoundError(name)

    monkeypatch.setattr(_version.metadata, "version", not_installed)
    assert _version.package_version() == _pyproject_version()
    monkeypatch.setattr(_version, "_PYPROJECT", tmp_path / "pyproject.toml")  # no source tree either
    assert _version.package_version() == "0+unknown"
    (tmp_path / "pyproject.toml").write_text('[project]\nname = "other"\nversion = "9.9"\n')
    assert _version.package_version() == "0+unknown"


def test_ctrl_c_exits_130_with_one_line(main, monkeypatch, capsys, tmp_path):
    import crfdepth.cli.project as project

    def interrupted(args: argparse.Namespace) -> int:
        raise KeyboardInterrupt

    monkeypatch.setattr(project, "run", interrupted)
    argv = ["project", "--velodyne", "x.bin", "--calib", "c", "--image", "i.png", "--out", str(tmp_path / "o.png")]
    assert main(argv) == 130
    captured = capsys.readouterr()
    assert captured.err == "crfdepth project: interrupted\n" and captured.out == ""
    assert list(tmp_path.iterdir()) == []


def test_ctrl_c_while_building_the_parser(monkeypatch, capsys):
    def interrupted(*commands):
        raise KeyboardInterrupt

    monkeypatch.setattr(cli, "build_parser", interrupted)
    assert cli.main(["project"]) == 130
    assert capsys.readouterr().err == "crfdepth: interrupted\n"


def test_usage_errors_are_one_line_naming_the_option(main, capsys):
    with pytest.raises(SystemExit) as info:
        main(["project", "--velodyne", "x.bin"])
    assert info.value.code == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "usage:" not in err
    assert err.startswith("crfdepth project: error: the following arguments are required: --calib")
    with pytest.raises(SystemExit):
        main(["project", "--camera", "7"])
    assert capsys.readouterr().err.startswith("crfdepth project: error: --camera: expected one of ")


def test_an_unknown_option_is_refused_by_its_command_naming_the_closest(main, capsys):
    """argparse alone blames ``crfdepth`` for an option its sub-command does not know, and suggests nothing."""
    given = ["project", "--velodyne", "x.bin", "--image", "i.png", "--out", "o.png", "--calib", "c.txt"]
    for argv, expected in (
        ([*given, "--seeed", "3"], "crfdepth project: error: unrecognized arguments: --seeed 3 (did you mean --seed?)\n"),
        ([*given, "--seeed=3"], "crfdepth project: error: unrecognized arguments: --seeed=3 (did you mean --seed?)\n"),
        ([*given, "--zzz"], "crfdepth project: error: unrecognized arguments: --zzz\n"),
        (["--bogus"], "crfdepth: error: unrecognized arguments: --bogus\n"),
    ):
        with pytest.raises(SystemExit) as info:
            main(argv)
        assert info.value.code == 2
        assert capsys.readouterr().err == expected, argv


def test_no_command_prints_help_and_exits_2(main, capsys):
    assert main([]) == 2
    assert "project" in capsys.readouterr().out


def test_python_dash_m_runs_the_command():
    result = subprocess.run([sys.executable, "-m", "crfdepth", "--version"], capture_output=True, text=True,
                            cwd=PYPROJECT.parent, timeout=300)
    assert result.returncode == 0 and result.stdout == f"crfdepth {crfdepth.__version__}\n"


_PROJECT_ARGV = ["project", "--velodyne", "x.bin", "--calib", "c", "--image", "i.png", "--out", "out.png"]


@pytest.mark.parametrize("exc, first", [
    (crfdepth.errors.ConvergenceError("solve (cg) did not reach rtol=1e-05 for 1 of 1 graph(s)\nmore"),
     "crfdepth project: error: solve (cg) did not reach rtol=1e-05 for 1 of 1 graph(s)"),
    (MemoryError("could not allocate 9 GB"),
     "crfdepth project: error: out of memory (could not allocate 9 GB): give fewer or smaller frames at once"),
    (RuntimeError("something crfdepth did not expect"),
     "crfdepth project: error: internal error, RuntimeError: something crfdepth did not expect (a bug in crfdepth"),
])
def test_a_failure_on_good_input_is_one_line_with_exit_status_1(main, monkeypatch, capsys, exc, first):
    from crfdepth.cli import project

    def run(args):
        raise exc

    monkeypatch.setattr(project, "run", run)
    assert main(_PROJECT_ARGV) == 1
    err = capsys.readouterr().err
    assert err.startswith(first) and err.count("\n") == 1 and "Traceback" not in err, err


def test_verbose_shows_the_traceback_of_a_bug(main, monkeypatch):
    from crfdepth.cli import project

    def run(args):
        raise RuntimeError("a bug")

    monkeypatch.setattr(project, "run", run)
    with pytest.raises(RuntimeError, match="^a bug$"):
        main(["--verbose", *_PROJECT_ARGV])
