"""Every ``python -m train`` command of README.md (and of docs/*.md) runs as written, for one optimiser step.

The commands are read from the documents' fenced ``bash`` blocks (a line continued with ``\\`` is one
command), so a command added or changed there is run here. Each runs in a working directory laid out like
the repository root (``configs/`` in it, ``../shared/data/kitti`` beside it), so that the configs'
relative paths hold, with:

- the documents' placeholder data root ``/data/kitti`` replaced by the shared sample frames. Their
  depth-completion frames are the val_selection frames (drive 0001 frame 5, cameras 02 and 03), which the
  data module rightly refuses to train and validate on at once; there camera 02 is the training frame and
  camera 03 the validation frame;
- a placeholder checkpoint (``path/to/best.ckpt``) replaced by the best checkpoint of the document's fit
  with the same configs;
- what the command's block does first: ``crfdepth targets --drive ...`` run as written; the loop over ROS
  bags replaced by two synthetic drives written where ``crfdepth targets --bag`` writes them (``seq/``), one
  of them named as the command holds out;
- options appended that make the run one step: one training batch, one validation batch, no sanity check,
  no loader workers, a 176 x 608 training crop;
- the DDP command on a machine without a CUDA GPU: its one-line refusal checked, then run with the fix it
  names (DDP over two CPU processes).

Each run exits 0 without a traceback and without Lightning's ``weights_only`` default line; a fit leaves
its checkpoint after exactly one optimiser step, validated (``epoch000-rmse...ckpt``); ``validate`` prints
the metrics. The runs are slow (Lightning in subprocesses, full-size validation frames; the sequence
recipe's targets take about 90 s) and part of CI.
"""

from __future__ import annotations

import json
import re
import shlex
import shutil
import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path

import pytest
import torch
import yaml

from tests.train.conftest import ROOT, subprocess_env

DOCUMENTS = [ROOT / "README.md", *sorted((ROOT / "docs").rglob("*.md"))]
PLACEHOLDER_DATA = "/data/kitti"
ONE_STEP = ["--trainer.max_epochs", "1", "--trainer.limit_train_batches", "1", "--trainer.limit_val_batches", "1",
            "--trainer.num_sanity_val_steps", "0", "--trainer.enable_progress_bar", "false",
            "--data.num_workers", "0", "--data.crop", "[176, 608]"]
ONE_BATCH = ["--trainer.limit_val_batches", "1", "--trainer.enable_progress_bar", "false", "--data.num_workers", "0"]
SUBCOMMANDS = ("fit", "validate", "test", "predict")


@dataclass(frozen=True)
class Command:
    """A ``python -m train`` command of a document, with the commands of its block before it."""

    document: str
    words: tuple[str, ...]
    before: tuple[tuple[str, ...], ...]

    @property
    def subcommand(self) -> str:
        return self.words[3]

    @property
    def configs(self) -> list[str]:
        return [self.words[i + 1] for i, w in enumerate(self.words[:-1]) if w in ("--config", "-c")]

    @property
    def id(self) -> str:
        return f"{self.document}:{self.subcommand}:{'+'.join(Path(c).stem for c in self.configs)}"

    def option(self, name: str) -> str | None:
        for i, word in enumerate(self.words):
            if word == name and i + 1 < len(self.words):
                return self.words[i + 1]
            if word.startswith(name + "="):
                return word.split("=", 1)[1]
        return None

    def needs_kitti(self) -> bool:
        """The shared KITTI frames: the placeholder data root, or a path to them in the block or the configs'
        values."""
        words = [w for command in (self.words, *self.before) if command is self.words or command[:3] != (
            "python", "-m", "train") for w in command]
        values = [json.dumps(yaml.safe_load((ROOT / c).read_text())) for c in self.configs]
        return any(PLACEHOLDER_DATA in w or "shared/data/kitti" in w for w in [*words, *values])


def _block_commands(block: str) -> list[tuple[str, ...]]:
    commands = []
    for line in block.replace("\\\n", " ").splitlines():
        words = tuple(shlex.split(line, comments=True))
        if words:
            commands.append(words)
    return commands


def training_commands() -> list[Command]:
    """The ``python -m train <subcommand>`` commands of the documents' bash blocks, in order."""
    found = []
    for document in DOCUMENTS:
        text = document.read_text(encoding="utf-8")
        for block in re.findall(r"^```(?:bash|sh|shell|console)\n(.*?)^```", text, flags=re.S | re.M):
            commands = _block_commands(block)
            for i, words in enumerate(commands):
                if words[:3] == ("python", "-m", "train") and len(words) > 3 and words[3] in SUBCOMMANDS:
                    found.append(Command(document.name, words, tuple(commands[:i])))
    return found


COMMANDS = training_commands()


def test_the_documents_hold_the_training_commands():
    """The reading above finds the training page's recipes (a block that is not ```bash would be missed)."""
    ids = [c.id for c in COMMANDS]
    for expected in ("training.md:fit:synthetic+debug", "training.md:fit:synthetic", "training.md:fit:kitti_raw",
                     "training.md:fit:kitti_dc", "training.md:fit:kitti_raw+ddp", "training.md:validate:kitti_raw",
                     "training.md:fit:kitti_weights", "training.md:fit:kitti_annotated", "training.md:fit:bag_sequence", "training.md:fit:kitti_sequence"):
        assert expected in ids, ids
    for command in COMMANDS:
        for config in command.configs:
            assert (ROOT / config).is_file(), f"{command.id}: no {config}"


# ----------------------------------------------------------------------------- the data


@pytest.fixture(scope="module")
def kitti_view(kitti_root, tmp_path_factory) -> Path:
    """The shared frames, with depth completion's camera 02 only and val_selection's camera 03 only."""
    view = tmp_path_factory.mktemp("kitti")
    for entry in kitti_root.iterdir():
        if entry.name not in ("depth_completion", "depth_selection"):
            (view / entry.name).symlink_to(entry)
    for folder, camera in (("depth_completion", "/image_02/"), ("depth_selection", "image_03")):
        for file in (kitti_root / folder).rglob("*"):
            if file.is_file() and camera in file.as_posix():
                link = view / file.relative_to(kitti_root)
                link.parent.mkdir(parents=True, exist_ok=True)
                link.symlink_to(file)
    return view


def _bag_drives(seq: Path, held_out: list[str]) -> None:
    """``seq/`` as ``crfdepth targets --bag`` leaves it for bags ``my_bag_1`` and the held-out names: each a
    synthetic drive ``seq/<date>/<name>_sync`` with its targets in ``seq/<name>_sync``."""
    from crfdepth.data.synthetic import make_sequence
    from tests.sequence_drive import DAY, DRIVE, make_targets, write_drive

    scratch = seq.parent / "scratch"
    drive = write_drive(scratch / "raw", make_sequence(5, 1, height=352, width=1216, movers=1))
    targets = make_targets(drive, scratch / "targets", k=2)
    (seq / DAY).mkdir(parents=True)
    for calibration in (scratch / "raw" / DAY).glob("calib_*.txt"):
        shutil.copy(calibration, seq / DAY)
    for name in ["my_bag_1", *held_out]:
        shutil.copytree(drive, seq / DAY / f"{name}_sync")
        shutil.copytree(targets / DRIVE, seq / f"{name}_sync")


def _run(words: list[str], cwd: Path, timeout: float = 900) -> subprocess.CompletedProcess:
    env = {**subprocess_env(), "PYTHONPATH": str(ROOT)}
    return subprocess.run(words, cwd=cwd, env=env, capture_output=True, text=True, timeout=timeout)


def _workspace(tmp_path: Path, command: Command, request) -> tuple[Path, dict[str, str]]:
    """The working directory of ``command`` (module docstring) and the placeholder replacements."""
    work = tmp_path / "work"
    work.mkdir()
    (work / "configs").symlink_to(ROOT / "configs")
    replace: dict[str, str] = {}
    if command.needs_kitti():
        view = request.getfixturevalue("kitti_view")
        (tmp_path / "shared" / "data").mkdir(parents=True)
        (tmp_path / "shared" / "data" / "kitti").symlink_to(view)
        replace[PLACEHOLDER_DATA] = str(view)
    for words in command.before:
        if words[:2] == ("crfdepth", "targets") and "--drive" in words:
            done = _run([sys.executable, "-m", "crfdepth", *words[1:]], work)
            assert done.returncode == 0, done.stdout[-2000:] + done.stderr[-3000:]
        elif words[:1] == ("for",) and "--bag" in words:
            held_out = yaml.safe_load(command.option("--data.val_names_contain") or "[]")
            _bag_drives(work / "seq", [held_out] if isinstance(held_out, str) else list(held_out))
    return work, replace


def _argv(command: Command, replace: dict[str, str]) -> list[str]:
    words = list(command.words)
    for i, word in enumerate(words):
        for placeholder, real in replace.items():
            words[i] = words[i].replace(placeholder, real)
    return [sys.executable, *words[1:]]


def _checked(proc: subprocess.CompletedProcess, what: str) -> str:
    output = proc.stdout + proc.stderr
    assert proc.returncode == 0, f"{what} failed:\n{output[-6000:]}"
    assert "Traceback" not in output, output[-6000:]
    assert "`weights_only` was not set" not in output
    return output


_FITS: dict[tuple[str, ...], Path] = {}  # the fits run so far: words -> checkpoints folder


def _fit(command: Command, work: Path, replace: dict[str, str], extra: list[str] = ()) -> Path:
    """Run the fit ``command`` for one step in ``work``; its checkpoints folder."""
    proc = _run([*_argv(command, replace), *ONE_STEP, *extra], work)
    _checked(proc, command.id)
    (last,) = work.rglob("last.ckpt")
    checkpoint = torch.load(last, weights_only=True, map_location="cpu")
    assert checkpoint["global_step"] == 1, checkpoint["global_step"]
    assert [p.name for p in last.parent.glob("epoch000-rmse*.ckpt")], "no validated checkpoint"
    _FITS[command.words] = last.parent
    return last.parent


def _checkpoint_for(command: Command, tmp_path: Path, request) -> Path:
    """The best checkpoint of the document's fit with ``command``'s configs (run now if not yet)."""
    fits = [c for c in COMMANDS if c.subcommand == "fit" and c.configs == command.configs]
    assert fits, f"{command.id}: no fit with configs {command.configs} to take a checkpoint from"
    fit = fits[0]
    folder = _FITS.get(fit.words)
    if folder is None:
        work, replace = _workspace(tmp_path / "fit", fit, request)
        folder = _fit(fit, work, replace)
    (best,) = folder.glob("epoch000-rmse*.ckpt")
    return best


def _marks(command: Command) -> list:
    return [pytest.mark.slow, *([pytest.mark.kitti] if command.needs_kitti() else [])]


@pytest.mark.parametrize("command", [pytest.param(c, id=c.id, marks=_marks(c)) for c in COMMANDS])
def test_the_command_runs(command, tmp_path, request):
    work, replace = _workspace(tmp_path, command, request)
    if command.subcommand == "fit":
        if "configs/ddp.yaml" in command.configs and not torch.cuda.is_available():
            refused = _run(_argv(command, replace), work)
            lines = refused.stderr.splitlines()
            assert refused.returncode == 2 and len(lines) == 1, refused.stderr[-3000:]
            assert lines[0].startswith("train: error: --trainer.accelerator: expected a device this machine has")
            fix = re.search(r"likely fix: (.*?) \(", lines[0]).group(1).split()
            _fit(command, work, replace, fix)
        else:
            _fit(command, work, replace)
        return
    for i, word in enumerate(command.words):  # a placeholder checkpoint: the document's fit's
        if word.endswith(".ckpt") and not (work / word).exists():
            replace[word] = str(_checkpoint_for(command, tmp_path, request))
    output = _checked(_run([*_argv(command, replace), *ONE_BATCH], work), command.id)
    assert "val/rmse" in output
