"""The README's DDP command on a machine without the GPUs it asks for: one line, no traceback.

``configs/ddp.yaml`` asks for every CUDA GPU; without one Lightning would fail inside the
Trainer with a ``MisconfigurationException`` traceback. ``train.options.check_accelerator``
refuses it first (status 2, ``train: error: ...``) and names the CPU fallback. CUDA is
patched away (or down to one GPU) so the tests behave the same on a GPU machine; nothing is
trained: a run that passes the check is stopped before Lightning builds the model.
"""

from __future__ import annotations

import re
import shlex
import sys
from pathlib import Path

import pytest
import torch

import train.__main__ as train_main

ROOT = Path(__file__).resolve().parents[2]


def _readme_ddp_command() -> list[str]:
    """The arguments of the ``python -m train fit ... configs/ddp.yaml`` line of docs/training.md."""
    lines = [line for line in (ROOT / "docs" / "training.md").read_text().splitlines()
             if line.startswith("python -m train fit") and "configs/ddp.yaml" in line]
    assert len(lines) == 1, lines
    return shlex.split(lines[0])[3:]  # after "python -m train"


@pytest.fixture
def gpus(monkeypatch):
    """Set how many CUDA GPUs torch reports (0 = none)."""
    monkeypatch.setattr(sys, "argv", ["python -m train"])
    monkeypatch.chdir(ROOT)  # the README's config paths are relative to the repository root

    def set_count(count: int) -> None:
        monkeypatch.setattr(torch.cuda, "is_available", lambda: count > 0)
        monkeypatch.setattr(torch.cuda, "device_count", lambda: count)
    return set_count


@pytest.fixture
def stop_after_checks(monkeypatch):
    """Stop a run that passed the checks before Lightning instantiates anything."""
    class Checked(Exception):
        pass

    def stop(self):
        raise Checked(self.config[self.config["subcommand"]]["trainer"])
    monkeypatch.setattr(train_main.CRFDepthCLI, "before_instantiate_classes", stop)
    return Checked


def test_readme_ddp_command_without_a_gpu_is_one_line(gpus, capsys):
    gpus(0)
    args = _readme_ddp_command()
    assert args == ["fit", "--config", "configs/kitti_raw.yaml", "--config", "configs/ddp.yaml"]
    assert train_main.main(args) == 2
    captured = capsys.readouterr()
    assert captured.err.splitlines() == [
        "train: error: --trainer.accelerator: expected a device this machine has, got 'gpu' on a machine "
        "without a CUDA GPU; likely fix: --trainer.accelerator cpu --trainer.devices 2 (DDP over 2 CPU processes)"]
    assert captured.out == ""


def test_the_suggested_fix_passes_the_check(gpus, stop_after_checks, capsys):
    gpus(0)
    assert train_main.main(_readme_ddp_command()) == 2
    fix = re.search(r"likely fix: (.*?) \(", capsys.readouterr().err).group(1)  # the options the message names
    with pytest.raises(stop_after_checks) as checked:
        train_main.main([*_readme_ddp_command(), *fix.split()])
    trainer = checked.value.args[0]
    assert (trainer["accelerator"], trainer["strategy"], int(trainer["devices"])) == ("cpu", "ddp", 2)


def test_a_single_gpu_config_without_a_gpu_gets_the_plain_cpu_fix(gpus, capsys):
    gpus(0)
    status = train_main.main(["fit", "--config", "configs/synthetic.yaml", "--trainer.accelerator", "gpu"])
    assert status == 2
    assert capsys.readouterr().err.splitlines()[0].endswith("likely fix: --trainer.accelerator cpu")


@pytest.mark.parametrize("devices, ok", [("1", True), ("2", False), ("[0]", True), ("[1]", False),
                                         ("0,1", False), ("-1", True), ("auto", True)])
def test_more_gpus_than_the_machine_has(gpus, capsys, stop_after_checks, devices, ok):
    gpus(1)
    args = [*_readme_ddp_command(), "--trainer.devices", devices]
    if ok:
        with pytest.raises(stop_after_checks):
            train_main.main(args)
    else:
        assert train_main.main(args) == 2
        assert capsys.readouterr().err.splitlines()[0].startswith(
            "train: error: --trainer.devices: expected at most 1 GPU (the CUDA GPUs of this machine), got ")


def test_check_accelerator_accepts_cpu_and_auto():
    for trainer in ({"accelerator": "cpu", "devices": 2}, {"accelerator": "auto", "devices": "auto"}, {}):
        assert train_main.check_accelerator(trainer) is None  # no error
