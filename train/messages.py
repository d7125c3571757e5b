"""One-line messages of ``python -m train``: ``train: error: <name>: expected <what>, got <what>``.

The command line is Lightning's :class:`~lightning.pytorch.cli.LightningCLI`; its parser (jsonargparse)
reports a bad value in several indented lines after a 90-line usage, and Lightning's ``Trainer``
refuses an impossible value with a traceback. This module turns both into the one line every crfdepth
command prints (``crfdepth/checks.py``), naming the option as the user gives it (``--model.lr``,
``--trainer.max_epochs``; a key of a config file as ``model.learning_rate``):

- :func:`parser_message`: a jsonargparse error, e.g. ``Parser key "model.lr": Expected a <class
  'float'>. Got value: abc`` -> ``--model.lr: expected a number, got 'abc'``.
- :func:`check_trainer_values`: the ``trainer:`` numbers Lightning would refuse, checked before the
  ``Trainer`` is built (``--trainer.max_epochs: expected an integer >= -1 (-1: no limit) or null, got -3``).
- :func:`section_message`: a one-line :class:`~crfdepth.errors.InputError` of the model's or the data's
  constructor (``crop: expected ...``) with the section in front (``--data.crop: expected ...``).
"""

from __future__ import annotations

import difflib
import inspect
import re
from collections.abc import Iterable, Mapping
from typing import Any

from crfdepth.errors import InputError

__all__ = ["SUBCOMMANDS", "check_checkpoint_values", "check_fit_length", "check_seed", "check_trainer_values", "parser_message", "section_message", "trainer_message", "unknown_option"]

#: The subcommands of ``python -m train`` (Lightning's ``test`` and ``predict`` are not offered: the module has
#: no test or predict step; ``validate`` scores a checkpoint on any data set).
SUBCOMMANDS = ("fit", "validate")

# jsonargparse's names of types -> words
_TYPE_WORDS = {
    "int": "an integer", "float": "a number", "bool": "true or false", "str": "a string", "NoneType": "null",
    "dict": "a mapping", "list": "a list", "tuple": "a list", "Path": "a path",
}


def _split_top(text: str) -> list[str]:
    """``text`` split at the commas outside brackets and quotes."""
    parts, depth, quote, start = [], 0, None, 0
    for i, char in enumerate(text):
        if quote:
            quote = None if char == quote else quote
        elif char in "'\"":
            quote = char
        elif char in "[(":
            depth += 1
        elif char in "])":
            depth -= 1
        elif char == "," and depth == 0:
            parts.append(text[start:i].strip())
            start = i + 1
    parts.append(text[start:].strip())
    return [p for p in parts if p]


def _type_words(text: str) -> str:
    """A jsonargparse type (``<class 'float'>``, ``typing.Literal['l2', 'l1']``, ``list[int]``) in words."""
    text = text.strip()
    match = re.fullmatch(r"<class '(?:[\w.]+\.)?(\w+)'>", text)
    if match:
        return _TYPE_WORDS.get(match.group(1), match.group(1))
    match = re.fullmatch(r"(?:typing\.)?Literal\[(.*)\]", text)
    if match:
        return f"one of {match.group(1)}"
    match = re.fullmatch(r"(?:typing\.)?(?:list|List|tuple|Tuple|Sequence|collections\.abc\.Sequence)\[(.*)\]", text)
    if match:
        item = _type_words(match.group(1).split(",")[0])
        plural = {"an integer": "integers", "a number": "numbers", "a string": "strings",
                  "true or false": "booleans"}.get(item, item)
        return f"a list of {plural}"
    match = re.fullmatch(r"(?:typing\.)?(?:dict|Dict|Mapping)\[.*\]", text)
    if match:
        return "a mapping"
    return _TYPE_WORDS.get(text, text)


def _merge_choices(kinds: list[str]) -> list[str]:
    """``["one of 64, 32", "one of 'bf16'", "null"]`` -> ``["one of 64, 32, 'bf16'", "null"]``."""
    choices = [k[len("one of "):] for k in kinds if k.startswith("one of ")]
    if len(choices) < 2:
        return kinds
    others = [k for k in kinds if not k.startswith("one of ")]
    return ["one of " + ", ".join(choices), *others]


def _got(value: str, text_type: bool) -> str:
    value = value.strip()
    return repr(value) if text_type else value


def _option(key: str, from_file: bool = False) -> str:
    """The user's name of a parser key: ``--model.lr`` on the command line, ``model.lr`` in a config file."""
    return key if from_file else f"--{key}"


def _close_sibling(key: str, options: list[str]) -> list[str]:
    """The option under the same parent as ``key`` whose last name is closest to ``key``'s (``model.crf.mde`` ->
    ``model.crf.structure.mode``, ``model.crf.gate.windw`` -> ``model.crf.gate.window``); [] when none is close."""
    parent, _, leaf = key.rpartition(".")
    if not parent:
        return []
    under = [o for o in options if o.startswith(parent + ".")]
    close = difflib.get_close_matches(leaf, [o.rpartition(".")[2] for o in under], n=1, cutoff=0.6)
    return [next(o for o in under if o.rpartition(".")[2] == close[0])] if close else []


def unknown_option(name: str, known: Iterable[str], subcommand: str | None = None) -> str:
    """``name: expected an option of python -m train <subcommand>, got an unknown one (did you mean ...?)``."""
    flag = name.startswith("--")
    key, options = name.lstrip("-"), [k.lstrip("-") for k in known]
    close = _close_sibling(key, options) or difflib.get_close_matches(key, options, n=1, cutoff=0.6)
    hint = f" (did you mean {'--' if flag else ''}{close[0]}?)" if close else ""
    where = f"python -m train {subcommand}" if subcommand else "python -m train"
    return f"{name}: expected an option of {where} (--help lists them), got an unknown one{hint}"


def parser_message(text: str, known: Iterable[str] = (), subcommand: str | None = None) -> str:
    """One line for a jsonargparse error message ``text`` (``known``: the parser's option names, for
    "did you mean"). Messages it does not recognise are kept, on one line."""
    text = text.strip()
    match = re.match(r'Parser key "([^"]+)":\s*(.*)', text, flags=re.S)
    if match:
        key, detail = match.group(1), match.group(2)
        name = _option(key)
        missing = re.match(r"File does not exist: '?(.*?)'?$", detail.strip())
        if missing:
            return f"{name}: expected an existing file, got {missing.group(1)!r}, which does not exist"
        union = re.search(r"Subtypes: \[(.*)\]\s*\n\s*Errors:", detail, flags=re.S)
        given = re.search(r"Given value type: <class '(\w+)'>\s*\n\s*Given value: (.*)$", detail, flags=re.S)
        if union and given:
            kinds = _merge_choices(list(dict.fromkeys(_type_words(t) for t in _split_top(union.group(1)))))
            expected = ", ".join(kinds[:-1]) + f" or {kinds[-1]}" if len(kinds) > 1 else kinds[0]
            return f"{name}: expected {expected}, got {_got(given.group(2), given.group(1) == 'str')}"
        simple = re.search(r"Expected a (.+)\. Got value: (.*)$", detail, flags=re.S)
        if simple:
            return f"{name}: expected {_type_words(simple.group(1))}, got {_got(simple.group(2), True)}"
        return f"{name}: {' '.join(detail.split())}"
    match = re.match(r"unrecognized arguments: (.*)", text, flags=re.S)
    if match:
        flags = [a for a in match.group(1).split() if a.startswith("-")]
        first = flags[0].split("=")[0] if flags else match.group(1).split()[0]
        return unknown_option(first, known, subcommand)
    match = re.match(r"Subcommand '(\w+)' does not accept option '([^']+)'", text)
    if match:
        return unknown_option(match.group(2), known, match.group(1))
    match = re.match(r'expected "subcommand" to be one of \{(.*)\}', text)
    if match:
        return f"subcommand: expected one of {', '.join(match.group(1).split(','))}, got none"
    match = re.match(r"argument subcommand: invalid choice: '(.*)' \(choose from (.*)\)", text)
    if match:
        hint = (" (python -m train has no test or predict: validate scores a checkpoint on a data set, "
                "--data.val_layout / --data.val_root name it)" if match.group(1) in ("test", "predict") else "")
        return f"subcommand: expected one of {match.group(2)}, got {match.group(1)!r}{hint}"
    match = re.match(r"argument ([\w./-]+): expected one argument", text)
    if match:
        name = match.group(1).split('/')[-1]
        return (f"{name}: expected a value, got none (a value that starts with '-' reads as an option: give it as "
                f"{name}=VALUE)")
    match = re.match(r"Problems parsing config\s*:?\s*(.*)", text, flags=re.S)
    if match:
        return f"--config: expected a YAML file or YAML text, got one that does not parse ({' '.join(match.group(1).split())})"
    return " ".join(text.split())


# --------------------------------------------------------------------------- trainer values


def _integer(value: Any) -> bool:
    return isinstance(value, int) and not isinstance(value, bool)


def _number(value: Any) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool)


def _whole(value: Any) -> bool:
    """An integer, or a float with no fraction: a union type of ``int | float`` may parse 4 as 4.0 (seen with
    jsonargparse on Python 3.12), which Lightning counts as 4 batches."""
    return _integer(value) or (isinstance(value, float) and value.is_integer())


# option -> (accepted?, what is expected); None is Lightning's default for most of them and always passes
_TRAINER_VALUES = {
    "max_epochs": (lambda v: _integer(v) and v >= -1, "an integer >= -1 (-1: no limit) or null"),
    "min_epochs": (lambda v: _integer(v) and v >= 0, "an integer >= 0 or null"),
    "max_steps": (lambda v: _integer(v) and v >= -1, "an integer >= -1 (-1: no limit)"),
    "min_steps": (lambda v: _integer(v) and v >= 0, "an integer >= 0 or null"),
    "num_sanity_val_steps": (lambda v: _integer(v) and v >= -1, "an integer >= -1 (-1: the whole validation set)"),
    "log_every_n_steps": (lambda v: _integer(v) and v >= 0, "an integer >= 0"),
    "check_val_every_n_epoch": (lambda v: _integer(v) and v >= 1, "an integer >= 1 or null"),
    "accumulate_grad_batches": (lambda v: _integer(v) and v >= 1, "an integer >= 1"),
    "num_nodes": (lambda v: _integer(v) and v >= 1, "an integer >= 1"),
    "gradient_clip_val": (lambda v: _number(v) and v >= 0, "a number >= 0 or null"),
    "val_check_interval": (lambda v: _whole(v) and v >= 1 or (_number(v) and 0.0 < v <= 1.0),
                           "an integer >= 1 (batches) or a number in (0, 1] (share of an epoch)"),
    **{f"limit_{stage}_batches": (lambda v: (_whole(v) and v >= 0) or (_number(v) and 0.0 <= v <= 1.0),
                                  "an integer >= 0 (batches) or a number in [0, 1] (share of the batches)")
       for stage in ("train", "val", "test", "predict")},
}


def check_trainer_values(trainer: Mapping[str, Any]) -> None:
    """Refuse the ``trainer:`` values that Lightning's ``Trainer`` would refuse with a traceback
    (``max_epochs: -3``, ``limit_val_batches: 1.5`` ...), before anything is built.

    Raises:
        InputError: ``--trainer.<option>: expected <what>, got <value>``.
    """
    for name, (accepted, expected) in _TRAINER_VALUES.items():
        value = trainer.get(name)
        if value is not None and not accepted(value):
            raise InputError(f"--trainer.{name}: expected {expected}, got {value!r}")
    devices = trainer.get("devices")
    ok = devices is None or (_integer(devices) and (devices >= 1 or devices == -1)) or (
        isinstance(devices, (list, tuple)) and devices and all(_integer(d) and d >= 0 for d in devices)) or (
        isinstance(devices, str) and re.fullmatch(r"\s*(auto|-1|\d+|\d+(\s*,\s*\d*)+)\s*", devices) is not None
        and devices.strip() != "0")
    if not ok:
        raise InputError(f"--trainer.devices: expected an integer >= 1, -1 (all), a list of device indices or "
                         f"'auto', got {devices!r}")


_CHECKPOINT_VALUES = {
    "mode": (lambda v: v in ("min", "max"), "'min' or 'max'"),
    "save_top_k": (lambda v: _integer(v) and v >= -1, "an integer >= -1 (-1: every checkpoint)"),
    "every_n_train_steps": (lambda v: _integer(v) and v >= 0, "an integer >= 0 (0: off) or null"),
    "every_n_epochs": (lambda v: _integer(v) and v >= 0, "an integer >= 0 (0: off) or null"),
}


#: ``--seed_everything``'s range: Lightning's ``seed_everything`` (numpy's seeds) takes [0, 2**32 - 1].
MAX_SEED = 2**32 - 1


def check_seed(seed: Any) -> None:
    """Refuse a ``--seed_everything`` Lightning's ``seed_everything`` would refuse with a traceback (-1, a
    20-digit number).

    Raises:
        InputError: ``--seed_everything: expected true, false or an integer in [0, 4294967295], got -1``.
    """
    if seed is None or isinstance(seed, bool) or (_integer(seed) and 0 <= seed <= MAX_SEED):
        return
    raise InputError(f"--seed_everything: expected true (a random seed), false (none) or an integer in "
                     f"[0, {MAX_SEED}], got {seed!r}")


def check_fit_length(trainer: Mapping[str, Any]) -> None:
    """Refuse a ``fit`` that would train nothing: ``--trainer.max_epochs 0`` or ``--trainer.max_steps 0`` (Lightning
    stops before the first step without a word, and the run's checkpoint is the untrained model)."""
    for name, meaning in (("max_epochs", "epochs"), ("max_steps", "optimiser steps")):
        if trainer.get(name) == 0 and not isinstance(trainer.get(name), bool):
            raise InputError(f"--trainer.{name}: expected an integer >= 1 (or -1: no limit) for fit, got 0 (a fit of "
                             f"0 {meaning} trains nothing)")


def check_checkpoint_values(checkpoint: Mapping[str, Any]) -> None:
    """Refuse the ``checkpoint:`` values Lightning's ``ModelCheckpoint`` would refuse with a traceback.

    Raises:
        InputError: ``--checkpoint.<option>: expected <what>, got <value>``.
    """
    for name, (accepted, expected) in _CHECKPOINT_VALUES.items():
        value = checkpoint.get(name)
        if value is not None and not accepted(value):
            raise InputError(f"--checkpoint.{name}: expected {expected}, got {value!r}")


def trainer_message(exc: Exception, section: str = "trainer", cls: type | None = None) -> str:
    """One line for an exception of a Lightning constructor (``cls``, default the ``Trainer``): its message
    with the option it names (the first ```name``` that is an argument of ``cls``) in front as
    ``--<section>.<name>``."""
    if cls is None:
        from lightning.pytorch import Trainer as cls

    text = " ".join(str(exc).split())
    params = set(inspect.signature(cls.__init__).parameters)
    named = [n for n in re.findall(r"`(\w+)`", text) if n in params]
    return f"--{section}.{named[0]}: {text}" if named else f"--{section}: {text}"


def section_message(section: str, exc: InputError, parameters: Iterable[str]) -> str:
    """``exc`` (``name: ...`` from the constructor of the ``section``'s class) with the section in front of
    each name that is one of the class's ``parameters`` (``crop: ...`` -> ``--data.crop: ...``;
    ``val_names_contain, val_fraction: ...``; ``extra_train[1].layout: ...``); other messages unchanged."""
    text = str(exc)
    head, sep, rest = text.partition(": ")
    if not sep:
        return text
    names = [n.strip() for n in head.split(",")]
    known = set(parameters)
    if not all(re.match(r"[A-Za-z_]\w*", n) and re.match(r"[A-Za-z_]\w*", n).group(0) in known for n in names):
        return text
    return ", ".join(f"--{section}.{n}" for n in names) + sep + rest
