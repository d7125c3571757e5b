"""The trainer's options checked before Lightning starts (:mod:`train.__main__`): the accelerator the machine
has, the nested ``--model.crf.<group>.<field>`` flags read as YAML, and a resumed fit's model options against
its checkpoint's. Each refusal is one line naming the option (``train: error: ...``, exit status 2).
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import torch
import yaml
from jsonargparse import Namespace

from crfdepth.config import CRFConfig, plain_data
from crfdepth.errors import InputError
from train.module import build_model

__all__ = ["OptionError", "check_accelerator", "check_model_options", "merge_nested_crf", "plain", "take_nested_crf"]


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


def plain(value: Any) -> Any:
    """A parsed value as plain data (jsonargparse Namespaces as dicts, tuples as lists)."""
    if isinstance(value, Namespace):
        value = value.as_dict()
    return plain_data(value) if isinstance(value, (Mapping, list, tuple)) else value


_NESTED_CRF = "--model.crf."


def take_nested_crf(args: list[str]) -> tuple[list[str], list[tuple[list[str], str]]]:
    """``args`` without the ``--model.crf.<group>.<field> VALUE`` options, and those options as
    ``(["<group>", "<field>"], "VALUE")``. The parser would take their values as strings
    (``--model.crf.gate.enabled no`` would switch the gate on) and replace the whole group with the one
    field (``--model.crf.gate.window 7`` would drop ``gate.enabled: true`` of the config);
    :func:`merge_nested_crf` reads them as YAML and sets the one field."""
    rest, nested, i = [], [], 0
    while i < len(args):
        word = args[i]
        if isinstance(word, str) and word.startswith(_NESTED_CRF) and len(word) > len(_NESTED_CRF):
            key, sep, value = word.partition("=")
            if not sep:
                if i + 1 >= len(args):
                    raise OptionError(f"{key}: expected a value, got none")
                value, i = args[i + 1], i + 1
            nested.append((key[len(_NESTED_CRF):].split("."), value))
        else:
            rest.append(word)
        i += 1
    return rest, nested


def merge_nested_crf(crf: dict[str, Any], nested: list[tuple[list[str], str]]) -> dict[str, Any]:
    """``crf`` with each nested option of :func:`take_nested_crf` set, in order, its value read as YAML
    (``7`` an integer, ``true`` / ``no`` a boolean, ``[colour, normal]`` a list). They apply after the
    config files and ``--model.crf``."""
    crf = dict(crf or {})
    for path, text in nested:
        name = "--model.crf." + ".".join(path)
        try:
            value = yaml.safe_load(text)
        except yaml.YAMLError as exc:
            raise OptionError(f"{name}: expected a YAML value, got {text!r} ({' '.join(str(exc).split())})") from None
        where = crf
        for key in path[:-1]:
            inner = where.get(key)
            if not isinstance(inner, dict):
                if inner is not None:  # a flat option (gate: true) given a field: the group from it
                    raise OptionError(f"{name}: expected {'.'.join(path[:-1])} to be a group of fields, got "
                                      f"{inner!r} from the config; give the group as a mapping")
                inner = {}
            where[key] = inner = dict(inner)
            where = inner
        where[path[-1]] = value
    return crf


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
