"""The trainer's options checked before Lightning starts (:mod:`train.__main__`): the accelerator the machine
has, the CRF's configuration, and a resumed fit's model options against its checkpoint's. Each refusal is one
line naming the option (``train: error: ...``, exit status 2).

``model.crf`` is typed (:class:`crfdepth.config.CRFConfig`), so the parser itself reads it by groups:
``--model.crf.gate.window 7`` sets that one field with its type, an unknown field or a value of the wrong
type is the parser's error. The flat names of commands, config files and checkpoints written before the groups
(``--model.crf "{mode: pixel}"``) are moved into their groups before the parser sees them (:func:`grouped_args`,
:func:`grouped_crf`), and the values the groups refuse are named after parsing (:func:`check_crf`).
"""

from __future__ import annotations

import json
import os
from collections.abc import Mapping
from typing import Any

import torch
import yaml
from jsonargparse import Namespace

from crfdepth.config import FLAT, GROUPS, CRFConfig, is_group, plain_data
from crfdepth.errors import InputError
from train.module import build_model

__all__ = ["OptionError", "check_accelerator", "check_output_folders", "check_crf", "check_model_options", "grouped_args", "grouped_crf", "plain"]


class OptionError(InputError):
    """A command-line or config-file error of the parser, in one line; ``main`` exits with status 2 through
    ``SystemExit`` for it, as the parser itself does."""


_CPU_DDP = "--trainer.accelerator cpu --trainer.devices 2"


def _requested_gpus(devices: Any) -> int | None:
    """How many GPUs Lightning's ``devices`` value asks for (an index list: the highest + 1);
    None = any number ("auto", -1) or a value Lightning itself will report."""
    try:
        if isinstance(devices, str):
            text = devices.strip()
            if text in ("auto", "-1"):
                return None
            if "," in text:  # "0,1": device indices
                devices = [int(i) for i in text.split(",") if i.strip()]
            else:
                devices = int(text)
        if isinstance(devices, (list, tuple)):
            return max(int(i) for i in devices) + 1 if devices else None
        if isinstance(devices, int) and not isinstance(devices, bool):
            return None if devices == -1 else devices
    except (TypeError, ValueError):
        pass
    return None


def check_accelerator(trainer: Mapping[str, Any]) -> None:
    """Refuse a ``trainer.accelerator`` / ``trainer.devices`` this machine does not have.

    Lightning would fail later with a traceback (``MisconfigurationException``); this is one
    line that names the option and the way to run the same DDP on CPU processes.

    Raises:
        InputError: ``gpu`` / ``cuda`` without a CUDA GPU, more GPUs (or a higher GPU index)
            than there are, or ``mps`` without Apple's Metal backend.
    """
    accelerator = trainer.get("accelerator")
    if not isinstance(accelerator, str):
        return  # "auto" by default; an Accelerator object is Lightning's to check
    name = accelerator.strip().lower()
    if name in ("gpu", "cuda"):
        available = torch.cuda.device_count() if torch.cuda.is_available() else 0
        if available == 0:
            ddp = "ddp" in str(trainer.get("strategy") or "").lower()
            fix = f"{_CPU_DDP} (DDP over 2 CPU processes)" if ddp else "--trainer.accelerator cpu"
            raise InputError(f"--trainer.accelerator: expected a device this machine has, got {accelerator!r} "
                             f"on a machine without a CUDA GPU; likely fix: {fix}")
        wanted = _requested_gpus(trainer.get("devices"))
        if wanted is not None and wanted > available:
            raise InputError(
                f"--trainer.devices: expected at most {available} GPU{'s' if available != 1 else ''} "
                f"(the CUDA GPUs of this machine), got {trainer.get('devices')!r}; likely fix: "
                "--trainer.devices -1 (all of them)")
    elif name == "mps" and not torch.backends.mps.is_available():
        raise InputError(
            f"--trainer.accelerator: expected a device this machine has, got {accelerator!r} without Apple's "
            "Metal backend (torch.backends.mps.is_available() is False); likely fix: --trainer.accelerator cpu")


def check_output_folders(config: Mapping[str, Any]) -> None:
    """Refuse an output folder of the run that is an existing file (``--trainer.default_root_dir``,
    ``--checkpoint.dirpath``, the logger's ``save_dir``): Lightning would fail on its first write, after
    training, with a traceback; or replace a file the user gave as input.

    Raises:
        InputError: ``--checkpoint.dirpath: expected a folder to write into, got x.ckpt, which is a file``.
    """
    def get(section: Any, key: str) -> Any:  # a parsed section is a jsonargparse Namespace or a dict
        return section.get(key) if section is not None and hasattr(section, "get") else None

    trainer, checkpoint = get(config, "trainer"), get(config, "checkpoint")
    candidates = [("--trainer.default_root_dir", get(trainer, "default_root_dir")),
                  ("--checkpoint.dirpath", get(checkpoint, "dirpath")),
                  ("--trainer.logger.init_args.save_dir", get(get(get(trainer, "logger"), "init_args"), "save_dir"))]
    for name, value in candidates:
        if isinstance(value, (str, os.PathLike)) and str(value) and os.path.exists(value) and not os.path.isdir(value):
            raise InputError(f"{name}: expected a folder to write into, got {os.fspath(value)}, which is a file")


def plain(value: Any) -> Any:
    """A parsed value as plain data (jsonargparse Namespaces as dicts, tuples as lists)."""
    if isinstance(value, Namespace):
        value = value.as_dict()
    return plain_data(value) if isinstance(value, (Mapping, list, tuple)) else value


_SUBCOMMANDS = ("fit", "validate", "test", "predict")


def grouped_crf(crf: Any) -> Any:
    """``crf`` with its flat names (``{mode: pixel, gate: true}``; :data:`crfdepth.config.FLAT`, the keys of files
    and checkpoints written before the groups) moved into their groups (``{structure: {mode: pixel}, gate:
    {enabled: true}}``), applied over the groups as :meth:`crfdepth.config.CRFConfig.build` applies them. No
    default is filled in, no value checked: the parser does that. Anything else (not a mapping, a key that is
    neither a group nor a flat name) is left as it is, for the parser to name."""
    if not isinstance(crf, Mapping) or not any(key in FLAT and not (key in GROUPS and is_group(value))
                                               for key, value in crf.items()):
        return crf
    result: dict[str, Any] = {}
    flat: dict[str, Any] = {}
    for key, value in crf.items():
        if key in FLAT and not (key in GROUPS and is_group(value)):
            flat[key] = value
        else:
            result[key] = dict(value) if key in GROUPS and isinstance(value, Mapping) else value
    for key, value in flat.items():
        group, name = FLAT[key]
        inner = result.setdefault(group, {})
        if isinstance(inner, dict):
            inner[name] = value
        else:  # a group given as something else ("structure: pixel"): the parser names it
            result[key] = value
    return result


def _grouped_config(config: Any) -> Any:
    """A configuration (a ``--config`` file's, ``--model``'s) with ``model.crf`` (``<subcommand>.model.crf``
    in a file given before the subcommand) by groups (:func:`grouped_crf`); the same object when it has none
    by flat names."""
    if not isinstance(config, Mapping):
        return config
    if "model" in config and isinstance(config["model"], Mapping) and "crf" in config["model"]:
        crf = grouped_crf(config["model"]["crf"])
        if crf is not config["model"]["crf"]:
            return {**config, "model": {**config["model"], "crf": crf}}
    for sub in _SUBCOMMANDS:
        if sub in config:
            inner = _grouped_config(config[sub])
            if inner is not config[sub]:
                return {**config, sub: inner}
    return config


def _read(text: str, path: bool) -> Any:
    """The YAML of ``text`` (of the file it names, with ``path`` and such a file); None when it is not YAML."""
    try:
        if path and os.path.isfile(text):
            with open(text, encoding="utf-8") as handle:
                text = handle.read()
        return yaml.safe_load(text)
    except (OSError, UnicodeDecodeError, yaml.YAMLError):
        return None  # the parser reports it


def _grouped_value(flag: str, text: Any) -> Any:
    """The value of ``flag`` (YAML text or a file's path) with the CRF's flat names by groups: JSON for
    ``--model.crf`` and ``--model``, YAML text for ``--config`` (a file with flat names is given as its converted
    text); ``text`` itself when there is nothing to convert."""
    if not isinstance(text, str):
        return text
    value = _read(text, path=True)  # each takes a file's path too
    if flag == "--model.crf":
        grouped = grouped_crf(value)
    elif flag == "--model":
        grouped = _grouped_config({"model": value})["model"] if isinstance(value, Mapping) else value
    else:
        grouped = _grouped_config(value)
    if grouped is value:
        return text
    return yaml.safe_dump(grouped, sort_keys=False) if flag == "--config" else json.dumps(grouped)


_CONVERTED = ("--config", "--model", "--model.crf")


def grouped_args(args: list[str]) -> list[str]:
    """``args`` with the CRF's configuration by groups wherever it is given by flat names
    (``--model.crf "{mode: pixel}"`` -> ``--model.crf '{"structure": {"mode": "pixel"}}'``, a ``--config`` file's
    ``model.crf``, ``--model "{crf: ...}"``): the parser checks the groups (``crf: CRFConfig``), and the commands
    and config files written before them keep working."""
    result, i = [], 0
    while i < len(args):
        word = args[i]
        name, sep, value = word.partition("=") if isinstance(word, str) else (word, "", "")
        if name in _CONVERTED and sep:
            result.append(f"{name}={_grouped_value(name, value)}")
        elif name in _CONVERTED and i + 1 < len(args):
            result += [word, _grouped_value(name, args[i + 1])]
            i += 1
        else:
            result.append(word)
        i += 1
    return result


def check_crf(crf: Any) -> None:
    """Refuse a parsed ``model.crf`` (its five groups) whose values the model refuses: the parser checks each
    field's type and choices, the groups and ``CRFDepth`` check ranges and rules across fields (an odd gate
    window, the gate with the mean aggregate) as they are built. Checked here, before Lightning starts.

    Raises:
        InputError: ``--model.crf.<group>.<field>: expected ..., got ...`` (``--model.crf.gate.window:
            expected an odd int >= 3 (pixels), got 4``).
    """
    try:
        build_model(plain(crf))
    except InputError as exc:  # "crf.gate.window: ..."
        raise InputError(f"--model.{exc}") from None


def _flat_items(value: Any, prefix: str) -> dict[str, Any]:
    if isinstance(value, Mapping):
        return {k: v for key, item in value.items() for k, v in _flat_items(item, f"{prefix}.{key}").items()}
    return {prefix: value}


def check_model_options(model: Mapping[str, Any] | None, stored: Mapping[str, Any]) -> None:
    """Refuse to resume a fit with other model options than the checkpoint's (``stored``: its
    ``hyper_parameters``). Lightning's CLI would replace the given options with the stored ones without a
    word; the resumed run is the run it resumes. The CRF's configuration is compared complete (defaults
    filled in, groups or flat names alike).

    Raises:
        InputError: ``--model.<key>: expected the checkpoint's <value> ..., got <value>`` for the first
            option that differs (``--model.crf.structure.mode`` inside the CRF's configuration).
    """
    given = plain(model) or {}
    for key, then in stored.items():
        if key.startswith("_") or key not in given:
            continue
        now = given[key]
        if key == "crf":
            try:
                build_model(now)  # a fault of the given configuration is named as such first
            except InputError as exc:  # "crf.gate: ..."
                raise InputError(f"--model.{exc}") from None
            then_flat = _flat_items(CRFConfig.build(then).groups(), "crf")
            now_flat = _flat_items(CRFConfig.build(now).groups(), "crf")
            differ = [(k, then_flat.get(k), now_flat.get(k)) for k in now_flat if then_flat.get(k) != now_flat.get(k)]
        else:
            differ = [(key, then, now)] if plain(then) != now else []
        if differ:
            name, then_value, now_value = differ[0]
            raise InputError(f"--model.{name}: expected the checkpoint's {then_value!r} when resuming its run with "
                             f"--ckpt_path (a resumed run is the run it resumes), got {now_value!r}; give the options "
                             "it was trained with, or train afresh without --ckpt_path")
