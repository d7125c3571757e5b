"""``python -m train`` refuses bad input in one line, ``train: error: <name>: expected <what>, got <what>``,
with exit status 2: no traceback, no 90-line usage, and no log folder (the checks run before Lightning
makes ``lightning_logs/``). A checkpoint is read with ``torch.load(weights_only=True)`` only: a pickle
that would run code is refused without running it, and no message suggests ``weights_only=False``.

Most cases run ``train.__main__.main`` in this process (the parser's refusals leave through
``SystemExit(2)``, the others return 2); two run ``python -m train`` itself.
"""

from __future__ import annotations

import os
import pickle
import subprocess
import sys
from pathlib import Path

import pytest
import torch

from tests.train.conftest import CONFIGS, ROOT, subprocess_env

pytestmark = pytest.mark.filterwarnings("ignore::DeprecationWarning:lightning.pytorch.cli",
                                        "ignore:.*does not have many workers:UserWarning",
                                        "ignore:.*log_every_n_steps.*:UserWarning")

SMALL = ["--data.train_options", "{count: 2, height: 64, width: 192}",
         "--data.val_options", "{count: 1, seed: 1000, height: 64, width: 192}"]
BASE = ["--config", str(CONFIGS / "synthetic.yaml"), "--config", str(CONFIGS / "debug.yaml"), *SMALL]
EXPECTED = "expected a checkpoint of the trainer (a Lightning .ckpt written by python -m train)"


def refused(args: list[str], capfd, caplog) -> list[str]:
    """stderr lines of ``main(args)``, which must refuse with status 2 (returned, or through SystemExit),
    Lightning having said nothing before (its lines are log records: ``caplog``)."""
    import logging

    from train.__main__ import main

    caplog.set_level(logging.INFO)
    try:
        status = main(args)
    except SystemExit as exc:  # the parser's refusals leave as the parser does
        status = exc.code
    captured = capfd.readouterr()
    assert status == 2, captured.err[-3000:]
    lines = captured.err.splitlines()
    assert lines, "nothing on stderr"
    assert "Traceback" not in captured.err and "usage:" not in captured.err
    said = [r.getMessage() for r in caplog.records if r.name.startswith("lightning")]
    assert not said, said  # e.g. "GPU available: ...": the Trainer was built before the refusal
    return lines


@pytest.fixture
def workdir(tmp_path, monkeypatch):
    """An empty working directory (``lightning_logs/`` would appear here), ``sys.argv`` cleared."""
    monkeypatch.chdir(tmp_path)
    monkeypatch.setattr(sys, "argv", ["python -m train"])
    return tmp_path


def no_log_folder(folder: Path) -> bool:
    return not (folder / "lightning_logs").exists()


@pytest.fixture(scope="module")
def trained(tmp_path_factory) -> Path:
    """``last.ckpt`` of a two-step synthetic run (64 x 192, pixel mode)."""
    from train.__main__ import main

    logs = tmp_path_factory.mktemp("trained")
    argv, sys.argv = sys.argv, ["python -m train"]
    try:
        assert main(["fit", *BASE, "--trainer.max_epochs", "1", "--trainer.limit_val_batches", "1",
                     "--trainer.num_sanity_val_steps", "0", "--trainer.enable_progress_bar", "false",
                     "--trainer.logger.init_args.save_dir", str(logs), "--trainer.default_root_dir", str(logs)]) == 0
    finally:
        sys.argv = argv
    (last,) = logs.rglob("last.ckpt")
    return last


# ----------------------------------------------------------------------------- options


@pytest.mark.parametrize("args, first_line", [
    (["--model.crf.gate.windw", "3"],
     "--model.crf.gate.windw: expected an option of python -m train fit (--help lists them), got an unknown one "
     "(did you mean --model.crf.gate.window?)"),
    (["--model.crf", "{gate: {windw: 3}}"],
     "model.crf.gate.windw: expected an option of python -m train fit (--help lists them), got an unknown one "
     "(did you mean model.crf.gate.window?)"),
    (["--model.crf", "{mde: pixel}"],
     "model.crf.mde: expected an option of python -m train fit (--help lists them), got an unknown one "
     "(did you mean model.crf.structure.mode?)"),
    (["--model.crf.structure.mode", "pxl"], "--model.crf.structure.mode: expected one of 'superpixel', 'pixel', got 'pxl'"),
    (["--model.crf.gate.window", "abc"], "--model.crf.gate.window: expected an integer, got 'abc'"),
    (["--model.crf.gate.window", "4"], "--model.crf.gate.window: expected an odd int >= 3 (pixels), got 4"),
    (["--model.crf.potentials.on", "[normal]"],
     "--model.crf.potentials.on: expected a subset of ('colour', 'normal', 'distance') containing 'colour', "
     "got ('normal',)"),
    (["--model.crf", "{gate: true, aggregate: median}"],  # flat names, checked as their groups
     "--model.crf.structure.aggregate: the occlusion gate weights a mean, expected 'mean' with gate=True, "
     "got 'median'"),
    (["--model.crf.solver.rtol", "-1"], "--model.crf.solver.rtol: expected a number in (0, 1), got -1.0"),
    (["--model.lr", "abc"], "--model.lr: expected a number, got 'abc'"),
    (["--model.loss", "l3"], "--model.loss: expected one of 'l2', 'l1', 'huber', got 'l3'"),
    (["--data.batch_size", "two"], "--data.batch_size: expected an integer, got 'two'"),
    (["--trainer.max_epochs", "abc"], "--trainer.max_epochs: expected an integer or null, got 'abc'"),
    (["--trainer.max_epochs", "-3"], "--trainer.max_epochs: expected an integer >= -1 (-1: no limit) or null, got -3"),
    (["--trainer.limit_val_batches", "1.5"],
     "--trainer.limit_val_batches: expected an integer >= 0 (batches) or a number in [0, 1] (share of the batches), "
     "got 1.5"),
    (["--trainer.accumulate_grad_batches", "0"], "--trainer.accumulate_grad_batches: expected an integer >= 1, got 0"),
    (["--trainer.devices", "[a]"],
     "--trainer.devices: expected an integer >= 1, -1 (all), a list of device indices or 'auto', got '[a]'"),
    (["--checkpoint.mode", "maxx"], "--checkpoint.mode: expected 'min' or 'max', got 'maxx'"),
    (["--data.btach_size", "2"],
     "--data.btach_size: expected an option of python -m train fit (--help lists them), got an unknown one "
     "(did you mean --data.batch_size?)"),
    (["--data.crop", "[1, 2, 3]"], "--data.crop: expected [height, width], two integers > 0, got [1, 2, 3]"),
    (["--data.val_fraction", "2"], "--data.val_fraction: expected a value in (0, 1), got 2.0"),
    (["--data.val_options", "{count: 1, sed: 3}"],
     "--data.val_options: expected options that layout 'synthetic' takes, got 'sed'"),
    (["--weights_only", "false"],
     "--weights_only: expected true (checkpoints are read with torch.load(weights_only=True) only, so that "
     "reading one never runs code), got false"),
    (["--config", "no/such.yaml"], "--config: expected an existing file, got '{workdir}/no/such.yaml', which does not exist"),
])
def test_a_bad_option_is_one_line_before_any_log_folder(workdir, capfd, caplog, args, first_line):
    lines = refused(["fit", *BASE, *args], capfd, caplog)
    assert lines == [f"train: error: {first_line.format(workdir=workdir)}"]
    assert no_log_folder(workdir)


def test_an_unknown_key_in_a_config_file_is_named(workdir, capfd, caplog):
    bad = workdir / "bad.yaml"
    bad.write_text("model:\n  learning_rate: 0.1\n")
    lines = refused(["fit", *BASE, "--config", str(bad)], capfd, caplog)
    assert len(lines) == 1
    assert lines[0].startswith("train: error: model.learning_rate: expected an option of python -m train fit")
    assert no_log_folder(workdir)


def test_a_missing_subcommand_is_one_line(workdir, capfd, caplog):
    assert refused([], capfd, caplog) == ["train: error: subcommand: expected one of fit, validate, got none"]
    assert refused(["fitt"], capfd, caplog) == ["train: error: subcommand: expected one of 'fit', 'validate', got 'fitt'"]


# ----------------------------------------------------------------------------- checkpoints


class _RunsCode:
    """Unpickling this runs ``touch <marker>``: what a malicious checkpoint does."""

    def __init__(self, marker: Path) -> None:
        self.marker = marker

    def __reduce__(self):
        return os.system, (f"touch {self.marker}",)


def _bad_checkpoints(folder: Path, trained: Path) -> dict[str, tuple[Path, str]]:
    """name -> (file, what the message says it got)."""
    data = trained.read_bytes()
    (folder / "truncated.ckpt").write_bytes(data[: len(data) // 2])
    (folder / "text.ckpt").write_text("not a checkpoint\n")
    with open(folder / "unsafe.ckpt", "wb") as handle:
        pickle.dump({"state_dict": _RunsCode(folder / "ran")}, handle, protocol=2)
    ckpt = torch.load(trained, weights_only=True)
    torch.save(ckpt["state_dict"], folder / "bare.ckpt")
    torch.save({**ckpt, "hyper_parameters": {"hidden": 3}}, folder / "other_module.ckpt")
    from crfdepth.checkpoints import load_model, save_model
    save_model(load_model(trained), folder / "model.pt")
    weights_only = {k: v for k, v in ckpt.items() if k not in ("optimizer_states", "lr_schedulers", "loops")}
    torch.save(weights_only, folder / "weights_only.ckpt")
    (folder / "a_folder.ckpt").mkdir()
    return {
        "missing": (folder / "missing.ckpt", f"{folder / 'missing.ckpt'}, which does not exist"),
        "folder": (folder / "a_folder.ckpt", f"the folder {folder / 'a_folder.ckpt'}"),
        "truncated": (folder / "truncated.ckpt",
                      f"{folder / 'truncated.ckpt'}, a damaged or truncated torch.save archive (its zip directory "
                      "is missing)"),
        "text": (folder / "text.ckpt", f"{folder / 'text.ckpt'}, which torch.load(weights_only=True) does not read: "
                                       "neither a torch.save archive nor a pickle; it starts with b'not a ch'"),
        "unsafe": (folder / "unsafe.ckpt", f"{folder / 'unsafe.ckpt'}, which torch.load(weights_only=True) refuses"),
        "bare state dict": (folder / "bare.ckpt", f"{folder / 'bare.ckpt'}, a bare state dict"),
        "another module's": (folder / "other_module.ckpt",
                             f"{folder / 'other_module.ckpt'}, a Lightning checkpoint of another model: no "
                             "hyper_parameters['crf'] (the CRF's configuration)"),
        "model file": (folder / "model.pt", f"{folder / 'model.pt'}, a crfdepth model file (crfdepth.save_model)"),
        "weights only": (folder / "weights_only.ckpt", None),
    }


@pytest.mark.parametrize("case", ["missing", "folder", "truncated", "text", "unsafe", "bare state dict",
                                  "another module's", "model file", "weights only"])
def test_a_bad_ckpt_path_is_one_line_and_never_run(workdir, capfd, caplog, trained, case):
    path, got = _bad_checkpoints(workdir, trained)[case]
    lines = refused(["fit", *BASE, "--ckpt_path", str(path)], capfd, caplog)
    assert len(lines) == 1, lines
    if got is None:  # a checkpoint without the training state cannot resume a fit
        assert lines[0] == (f"train: error: --ckpt_path: {EXPECTED} with the training state to resume from, got "
                            f"{path}, which holds the model's weights only (no optimizer_states, loops: saved with "
                            "checkpoint.save_weights_only)")
    else:
        assert lines[0].startswith(f"train: error: --ckpt_path: {EXPECTED}, got {got}")
    assert "weights_only=False" not in lines[0] and "weights_only` set to `False" not in lines[0]
    assert not (workdir / "ran").exists()  # the unsafe pickle's code never ran
    assert no_log_folder(workdir)


def test_validate_refuses_a_bad_checkpoint_alike(workdir, capfd, caplog, trained):
    path, got = _bad_checkpoints(workdir, trained)["unsafe"]
    lines = refused(["validate", *BASE, "--ckpt_path", str(path)], capfd, caplog)
    assert len(lines) == 1 and lines[0].startswith(f"train: error: --ckpt_path: {EXPECTED}, got {got}")
    assert not (workdir / "ran").exists() and no_log_folder(workdir)


def test_export_refuses_a_bad_checkpoint_in_one_line(workdir, capsys, trained):
    from train.export import main

    for case in ("unsafe", "truncated", "missing"):
        folder = workdir / case
        folder.mkdir()
        path, got = _bad_checkpoints(folder, trained)[case]
        assert main([str(path), "--out", str(workdir / "w.json")]) == 2
        err = capsys.readouterr().err.splitlines()
        assert len(err) == 1 and err[0].startswith(f"train.export: error: checkpoint: {EXPECTED}, got {got}")
    assert not (workdir / "unsafe" / "ran").exists() and not (workdir / "w.json").exists()


# ----------------------------------------------------------------------------- python -m train itself


@pytest.mark.parametrize("args, first_line", [
    (["--model.crf.gate.windw", "3"], "train: error: --model.crf.gate.windw: expected an option of python -m train "
                                      "fit (--help lists them), got an unknown one (did you mean --model.crf.gate.window?)"),
    (["--model.crf.gate.window", "4"], "train: error: --model.crf.gate.window: expected an odd int >= 3 (pixels), got 4"),
    (["--ckpt_path", "unsafe.ckpt"], f"train: error: --ckpt_path: {EXPECTED}, got unsafe.ckpt, which "
                                     "torch.load(weights_only=True) refuses"),
])
def test_python_m_train_prints_one_line_and_exits_2(tmp_path, args, first_line):
    with open(tmp_path / "unsafe.ckpt", "wb") as handle:
        pickle.dump({"state_dict": _RunsCode(tmp_path / "ran")}, handle, protocol=2)
    env = {**subprocess_env(), "PYTHONPATH": str(ROOT)}
    proc = subprocess.run([sys.executable, "-m", "train", "fit", *BASE, *args], cwd=tmp_path, env=env,
                          capture_output=True, text=True, timeout=300)
    assert proc.returncode == 2, proc.stderr[-3000:]
    lines = proc.stderr.splitlines()
    assert len(lines) == 1 and lines[0].startswith(first_line), proc.stderr[-3000:]
    assert proc.stdout == "" and not (tmp_path / "ran").exists() and no_log_folder(tmp_path)


def test_a_run_logs_no_weights_only_default(workdir, caplog, trained):
    """Every checkpoint is saved and read with weights_only said: Lightning's "`weights_only` was not set,
    defaulting to `False`" line (once per epoch and per resume before) is gone."""
    import logging

    from train.__main__ import main

    caplog.set_level(logging.INFO)
    logs = workdir / "logs"
    status = main(["fit", *BASE, "--trainer.max_epochs", "2", "--trainer.limit_val_batches", "1",
                   "--trainer.num_sanity_val_steps", "0", "--trainer.enable_progress_bar", "false",
                   "--trainer.logger.init_args.save_dir", str(logs), "--trainer.default_root_dir", str(logs),
                   "--ckpt_path", str(trained)])
    assert status == 0
    assert "Restored all states from the checkpoint" in caplog.text
    assert "weights_only" not in caplog.text


def _printed_crf(main, args: list[str], capsys) -> dict:
    """``model.crf`` of ``--print_config``."""
    import yaml

    with pytest.raises(SystemExit) as exit_info:
        main([*args, "--print_config"])
    assert exit_info.value.code in (0, None)
    return yaml.safe_load(capsys.readouterr().out)["model"]["crf"]


def test_a_nested_model_key_sets_one_field_with_its_type(capsys, monkeypatch):
    """``model.crf`` is typed (``CRFConfig``): ``--model.crf.<group>.<field> VALUE`` sets that field alone, with its
    type (``no`` a boolean, ``[colour, normal]`` a list), the config's other fields kept; ``--print_config`` shows
    all five groups, every field with its value."""
    from crfdepth.config import GROUPS, CRFConfig
    from train.__main__ import main

    monkeypatch.setattr(sys, "argv", ["python -m train"])
    crf = _printed_crf(main, ["fit", "--config", str(CONFIGS / "kitti_weights.yaml"), "--model.crf.gate.window", "7",
                              "--model.crf.structure.rounds=2", "--model.crf.potentials.on", "[colour, normal]"], capsys)
    assert list(crf) == list(GROUPS)
    expected = CRFConfig.build({"structure": {"mode": "pixel", "variable": "log", "rounds": 2},
                                "gate": {"enabled": True, "window": 7}, "potentials": {"on": ["colour", "normal"]}})
    assert CRFConfig.build(crf) == expected
    assert crf["gate"] == expected.groups()["gate"]  # every field, with its value
    off = _printed_crf(main, ["fit", "--config", str(CONFIGS / "kitti_weights.yaml"), "--model.crf.gate.enabled", "no"],
                       capsys)
    assert off["gate"]["enabled"] is False and off["structure"]["variable"] == "log"


def test_flat_crf_names_still_work(workdir, capsys, monkeypatch):
    """The flat names of commands and config files written before the groups (``{mode: pixel, gate: true}``) are
    moved into their groups before the parser reads them: the same configuration as the groups give."""
    from crfdepth.config import CRFConfig
    from train.__main__ import main

    wanted = CRFConfig.build(mode="pixel", gate=True, gate_window=7)
    flat = workdir / "flat.yaml"
    flat.write_text("model:\n  crf: {mode: pixel, gate: true, gate_window: 7}\n")
    for args in (["--model.crf", "{mode: pixel, gate: true, gate_window: 7}"],
                 ["--model.crf={mode: pixel, gate: true, gate_window: 7}"],
                 ["--model", "{crf: {mode: pixel, gate: true, gate_window: 7}}"],
                 ["--config", str(flat)],
                 ["--model.crf", "{structure: {mode: pixel}, gate: true}", "--model.crf.gate.window", "7"]):
        assert CRFConfig.build(_printed_crf(main, ["fit", *BASE, *args], capsys)) == wanted, args


def test_flat_names_move_into_their_groups_as_given():
    """Flat names go into their groups over the group's fields; no default filled in, an unknown key left for
    the parser to name; a configuration by groups is returned as it is."""
    from train.options import grouped_crf

    flat = {"mode": "pixel", "gate": True, "potentials": ["colour"], "structure": {"rounds": 2, "mode": "superpixel"},
            "mde": 1}
    assert grouped_crf(flat) == {"structure": {"rounds": 2, "mode": "pixel"}, "gate": {"enabled": True},
                                 "potentials": {"on": ["colour"]}, "mde": 1}
    grouped = {"gate": {"enabled": True}, "structure": {"mode": "pixel"}}
    assert grouped_crf(grouped) is grouped


def test_a_checkpoint_with_flat_crf_names_is_read(workdir, monkeypatch, trained):
    """A checkpoint written before the groups (``hyper_parameters["crf"]`` by flat names) validates, its
    configuration read as the groups it means."""
    from crfdepth.config import CRFConfig
    from train.__main__ import CRFDepthCLI, main

    checkpoint = torch.load(trained, weights_only=True)
    stored = CRFConfig.build(checkpoint["hyper_parameters"]["crf"], superpixels=1234, rtol=1e-4)
    checkpoint["hyper_parameters"]["crf"] = {k: list(v) if isinstance(v, tuple) else v for k, v in stored.flat().items()}
    torch.save(checkpoint, workdir / "flat.ckpt")
    seen = {}
    monkeypatch.setattr(CRFDepthCLI, "before_validate", lambda cli: seen.update(settings=cli.model.model.settings))
    assert main(["validate", *BASE, "--ckpt_path", str(workdir / "flat.ckpt"), "--trainer.limit_val_batches", "1",
                 "--trainer.enable_progress_bar", "false"]) == 0
    assert seen["settings"] == stored


@pytest.mark.kitti
def test_a_dataset_option_of_another_layout_is_named(workdir, capfd, caplog, kitti_root):
    """What made the README's val_selection command fail: configs/kitti_dc.yaml gave ``val_options: {split:
    val}``, an option of depth_completion, which ``--data.val_layout val_selection`` then received. The
    config no longer sets it; given explicitly, it is named in one line."""
    lines = refused(["fit", "--config", str(CONFIGS / "kitti_dc.yaml"), "--data.root",
                     str(kitti_root / "depth_completion"), "--data.val_layout", "val_selection", "--data.val_root",
                     str(kitti_root / "depth_selection" / "val_selection_cropped"), "--data.val_options", "{split: val}"],
                    capfd, caplog)
    assert lines == ["train: error: --data.val_options: expected options that layout 'val_selection' takes, got "
                     "'split' (a depth_completion option: with another val_layout, set val_options for it, or null)"]
    assert no_log_folder(workdir)


@pytest.mark.parametrize("value", [4, 4.0, 0.5, 0])
def test_batch_limits_given_as_whole_floats_are_counts(value):
    """A union ``int | float`` parsed 4 as 4.0 on Python 3.12 (an H200 machine): Lightning counts that as 4
    batches, so the check accepts it; 1.5 stays refused (above)."""
    from train.messages import check_trainer_values

    check_trainer_values({"limit_train_batches": value, "val_check_interval": value if value >= 1 else 0.5})
