"""Every command of the documents' shell blocks is checked by a test.

``crfdepth ...`` lines (also under torchrun's ``-m crfdepth``) are parsed by the command's own
parser here, so a renamed option or choice fails; the others are run by the test named for their
kind below. A command of a kind nobody checks fails, so a new block needs its test.
"""

from __future__ import annotations

import shlex

import pytest
import yaml

from crfdepth.cli import build_parser
from crfdepth.io.calibration import load_any_calibration
from tests.documents import code_blocks

# Commands run elsewhere: (the words they start with) -> the test that runs them.
RUN_ELSEWHERE = {
    ("python", "-m", "train"): "tests/train/test_readme_training.py",
    ("python", "-m", "crfdepth.data.example_bag"): "tests/data/test_example_bag.py",
    ("python", "-m", "train.export"): "tests/train/test_export.py",
    ("python3", "-m", "venv"): ".ci/run (the README's two commands)",
    ("python", "-m", "pytest"): ".ci/run (the README's two commands)",
    ("pip", "install"): ".ci/run (the README's two commands)",
    (".", ".venv/bin/activate"): ".ci/run (the README's two commands)",
}


def _commands() -> list[tuple[str, list[str]]]:
    """(document, words) of every command of every bash block; loops and ``&&`` chains split."""
    found = []
    for document, _, block in code_blocks("bash"):
        for line in block.replace("\\\n", " ").splitlines():
            lexer = shlex.shlex(line, posix=True, punctuation_chars=";&")
            lexer.whitespace_split, lexer.commenters = True, "#"
            tokens = list(lexer)
            for words in _split(tokens):
                if words[:1] in (["do"], ["done"]):
                    words = words[1:]
                if words and words[0] != "for":
                    found.append((document, words))
    return found


def _split(tokens: list[str]) -> list[list[str]]:
    """Shell tokens cut at ``;`` and ``&&``."""
    parts = [[]]
    for token in tokens:
        if token in (";", "&&"):
            parts.append([])
        else:
            parts[-1].append(token)
    return parts


COMMANDS = _commands()


def _crfdepth_arguments(words: list[str]) -> list[str] | None:
    """The arguments of the ``crfdepth`` command in ``words`` (direct or ``torchrun ... -m crfdepth``)."""
    if words[0] == "crfdepth":
        return words[1:]
    if "-m" in words and words[words.index("-m") + 1:][:1] == ["crfdepth"]:
        return words[words.index("-m") + 2:]
    return None


def test_the_documents_hold_commands_of_every_kind():
    documents = {document for document, _ in COMMANDS}
    assert {"README.md", "docs/getting-started.md", "docs/own-sensors.md", "docs/ros.md", "docs/training.md",
            "docs/at-scale.md"} <= documents
    assert sum(_crfdepth_arguments(words) is not None for _, words in COMMANDS) >= 8


@pytest.mark.parametrize("document, words", COMMANDS, ids=[f"{d}:{' '.join(w[:3])}" for d, w in COMMANDS])
def test_every_command_is_checked(document, words):
    arguments = _crfdepth_arguments(words)
    if arguments is None:
        owner = [test for prefix, test in RUN_ELSEWHERE.items() if tuple(words[:len(prefix)]) == prefix]
        assert owner, f"{document}: no test checks `{' '.join(words)}`: add its kind to RUN_ELSEWHERE with the test"
        return
    try:
        build_parser().parse_args(arguments)
    except SystemExit as refused:
        pytest.fail(f"{document}: `crfdepth {' '.join(arguments)}` is refused by the parser (exit {refused.code})")


def test_a_renamed_option_would_be_caught():
    with pytest.raises(SystemExit):
        build_parser().parse_args(["complete", "--image", "a.png", "--no-such-option"])


@pytest.mark.parametrize("document, index, text", code_blocks("yaml"), ids=lambda v: str(v)[:30])
def test_every_yaml_block_is_a_calibration_that_loads(document, index, text, tmp_path):
    """The documents' YAML blocks are rig calibration files (docs/own-sensors.md): each loads."""
    assert isinstance(yaml.safe_load(text), dict), f"{document} yaml block {index}"
    path = tmp_path / "rig.yaml"
    path.write_text(text)
    calibration = load_any_calibration(path)
    assert calibration.K.shape == (3, 3) and calibration.T_cam_lidar.shape == (4, 4)
