"""Bad input to ``python -m train`` and ``python -m train.export``: one line on stderr, exit status 2, no
traceback, nothing written (an export never replaces its input)."""

from __future__ import annotations

import os
import sys

import pytest

from tests.train.test_cli_errors import BASE, no_log_folder, refused
from tests.train.test_export import _checkpoint

pytestmark = pytest.mark.filterwarnings("ignore::DeprecationWarning:lightning.pytorch.cli")


@pytest.fixture
def workdir(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    monkeypatch.setattr(sys, "argv", ["python -m train"])
    return tmp_path


# ----------------------------------------------------------------------------- train.export


def _export(args, capsys) -> tuple[int, list[str]]:
    from train.export import main

    try:
        status = main([str(a) for a in args])
    except SystemExit as exc:  # the parser's usage errors
        status = exc.code
    return status, capsys.readouterr().err.splitlines()


@pytest.mark.parametrize("spelling", ["same", "dotted", "symlink", "hardlink"])
def test_export_refuses_to_replace_its_checkpoint(workdir, capsys, spelling):
    ckpt = workdir / "last.ckpt"
    _checkpoint(ckpt)
    before = ckpt.read_bytes()
    (workdir / "sub").mkdir()
    out = {"same": ckpt, "dotted": workdir / "sub" / ".." / "." / "last.ckpt", "symlink": workdir / "link.json",
           "hardlink": workdir / "hard.json"}[spelling]
    if spelling == "symlink":
        os.symlink(ckpt, out)
    if spelling == "hardlink":
        os.link(ckpt, out)
    status, err = _export([ckpt, "--out", out], capsys)
    assert status == 2 and len(err) == 1
    assert err[0].startswith(f"train.export: error: --out: expected a file other than the checkpoint it is written "
                             f"from, got {out}, which is checkpoint {ckpt}")
    assert ckpt.read_bytes() == before


def test_export_refuses_to_replace_its_config(workdir, capsys):
    _checkpoint(workdir / "last.ckpt")
    config = workdir / "recipe.yaml"
    config.write_text("model:\n  loss: l1\n")
    status, err = _export([workdir / "last.ckpt", "--out", "./recipe.yaml", "--config", config], capsys)
    assert status == 2 and err[0].startswith(
        "train.export: error: --out: expected a file other than the --config it is written from, got recipe.yaml")
    assert config.read_text() == "model:\n  loss: l1\n"


def test_export_refuses_a_folder_as_out(workdir, capsys):
    _checkpoint(workdir / "last.ckpt")
    status, err = _export([workdir / "last.ckpt", "--out", workdir], capsys)
    assert status == 2 and err == [f"train.export: error: --out: expected the path of a .json file to write, got "
                                   f"{workdir}, which is a folder"]


def test_export_usage_errors_are_one_line(workdir, capsys):
    status, err = _export([workdir / "last.ckpt"], capsys)
    assert status == 2 and len(err) == 1 and err[0].startswith("train.export: error: ")
    status, err = _export([workdir / "last.ckpt", "--out", "w.json", "--uncertainty", "wide"], capsys)
    assert status == 2 and len(err) == 1 and err[0].startswith("train.export: error: --uncertainty: ")


# ----------------------------------------------------------------------------- python -m train


BIG = "99999999999999999999"


@pytest.mark.parametrize("args, first_line", [
    (["--seed_everything", "-1"],
     "--seed_everything: expected true (a random seed), false (none) or an integer in [0, 4294967295], got -1"),
    (["--seed_everything", BIG],
     f"--seed_everything: expected true (a random seed), false (none) or an integer in [0, 4294967295], got {BIG}"),
    (["--trainer.max_epochs", "0"],
     "--trainer.max_epochs: expected an integer >= 1 (or -1: no limit) for fit, got 0 (a fit of 0 epochs trains nothing)"),
    (["--trainer.max_steps", "0"], "--trainer.max_steps: expected an integer >= 1 (or -1: no limit) for fit, got 0"),
    (["--trainer.max_steps", "-5"], "--trainer.max_steps: expected an integer >= -1 (-1: no limit), got -5"),
    (["--data.batch_size", "0"], "--data.batch_size: expected an integer in [1, 1024], got 0"),
    (["--data.batch_size", "-2"], "--data.batch_size: expected an integer in [1, 1024], got -2"),
    (["--data.val_batch_size", BIG], f"--data.val_batch_size: expected an integer in [1, 1024], got {BIG}"),
    (["--data.num_workers", "-1"], "--data.num_workers: expected an integer in [0, 64]"),
    (["--data.num_workers", BIG], "--data.num_workers: expected an integer in [0, 64]"),
    (["--data.seed", "-1"], "--data.seed: expected an integer in [0, 4611686018427387904] or null, got -1"),
    (["--data.seed", BIG], f"--data.seed: expected an integer in [0, 4611686018427387904] or null, got {BIG}"),
    (["--data.crop", "[0, 64]"], "--data.crop: expected [height, width], two integers > 0, got [0, 64]"),
    (["--data.crop", "[-32, 64]"], "--data.crop: expected [height, width], two integers > 0, got [-32, 64]"),
    (["--data.crop", f"[32, {BIG}]"], f"--data.crop: expected [height, width] of at most 65536 pixels each, got [32, {BIG}]"),
    (["--data.crop", "[128, 64]"],  # the synthetic frames are 64 x 192
     "--data.crop: expected [height, width] within the training frames, got [128, 64] for frame "),
    (["--model.lr", "0"], "--model.lr: expected a learning rate > 0, got 0"),
])
def test_out_of_range_values_are_one_line(workdir, capfd, caplog, args, first_line):
    lines = refused(["fit", *BASE, *args], capfd, caplog)
    assert len(lines) == 1 and lines[0].startswith(f"train: error: {first_line}"), lines
    assert no_log_folder(workdir)


@pytest.mark.parametrize("option", ["--data.flip", "--data.val_fraction", "--model.lr", "--model.nll_weight",
                                    "--model.photometric_weight", "--model.huber_delta", "--model.head_lr"])
@pytest.mark.parametrize("value", ["nan", "inf", "-inf"])
def test_non_finite_numbers_are_one_line(workdir, capfd, caplog, option, value):
    lines = refused(["fit", *BASE, option, value], capfd, caplog)  # the parser's words or ours: not asserted
    assert len(lines) == 1 and lines[0].startswith(f"train: error: {option}: expected "), lines
    assert no_log_folder(workdir)


@pytest.mark.parametrize("cls, name, first_line", [
    ("module", "lr", "lr: expected a learning rate > 0, got nan"),
    ("module", "head_lr", "head_lr: expected a learning rate > 0, got inf"),
    ("module", "nll_weight", "nll_weight: expected a number >= 0, got nan"),
    ("module", "photometric_weight", "photometric_weight: expected a number >= 0, got inf"),
    ("module", "huber_delta", "huber_delta: expected a number of metres > 0, got inf"),
    ("data", "flip", "flip: expected a probability in [0, 1], got nan"),
    ("data", "val_fraction", "val_fraction: expected a value in (0, 1), got nan"),
])
def test_constructors_refuse_non_finite_numbers(cls, name, first_line):
    from crfdepth.errors import InputError
    from train.data import CRFDataModule
    from train.module import CRFDepthModule

    value = float("inf") if "inf" in first_line else float("nan")
    with pytest.raises(InputError) as e:
        (CRFDepthModule if cls == "module" else CRFDataModule)(**{name: value})
    assert str(e.value).startswith(first_line)


@pytest.mark.parametrize("subcommand", ["test", "predict"])
def test_test_and_predict_are_refused_naming_the_subcommands(workdir, capfd, caplog, subcommand):
    lines = refused([subcommand, *BASE], capfd, caplog)
    assert lines == [f"train: error: subcommand: expected one of 'fit', 'validate', got {subcommand!r} (python -m "
                     "train has no test or predict: validate scores a checkpoint on a data set, --data.val_layout / "
                     "--data.val_root name it)"]
    assert no_log_folder(workdir)


def test_validate_with_max_epochs_0_is_not_refused():
    from train.messages import check_fit_length

    check_fit_length({"max_epochs": -1, "max_steps": -1})  # no limit
    check_fit_length({"max_epochs": 3, "max_steps": None})


@pytest.mark.parametrize("option", ["--trainer.default_root_dir", "--checkpoint.dirpath",
                                    "--trainer.logger.init_args.save_dir"])
def test_an_output_folder_that_is_a_file_is_refused(workdir, capfd, caplog, option):
    a_file = workdir / "model.ckpt"
    a_file.write_bytes(b"not a folder")
    lines = refused(["fit", *BASE, option, str(a_file)], capfd, caplog)
    assert lines == [f"train: error: {option}: expected a folder to write into, got {a_file}, which is a file"]
    assert a_file.read_bytes() == b"not a folder"
