"""The weights shipped with crfdepth, and the small JSON file format that holds them.

Two named weight sets:

- ``"kitti"`` (the default of :func:`complete_depth <crfdepth.api.complete_depth>`, the
  ``crfdepth`` commands and :meth:`CRFDepth.from_pretrained
  <crfdepth.model.CRFDepth.from_pretrained>`): learned on real KITTI frames by the
  Lightning trainer in ``train/``; the file is ``crfdepth/weights/kitti.json`` and
  ``crfdepth/weights/README.md`` beside it says which frames, config and command made it,
  and what it measured.
- ``"paper"``: the hand-set initial values of ``CRFDepth()`` (no file).

A weights file is JSON, not a pickle: the CRF has ten learnable numbers, so the file is
its complete ``CRFDepth`` configuration (``model.config`` with the learned values of
``alpha .. std_scale`` written in) plus a free-form ``"about"`` record::

    {"format": "crfdepth-weights", "version": 1,
     "config": {"mode": "superpixel", ..., "alpha": 0.41, ...},
     "about": {"data": ..., "command": ..., "validation": ...}}

``CRFDepth(**config)`` rebuilds the model (the learned values are stored as float32 values
written out in full, so the rebuilt parameters equal the trained ones to float32
rounding of the logit/log, about 1e-7 relative). :func:`save_weights` writes one from any
model; ``python -m train.export`` turns a trainer checkpoint into one;
:func:`crfdepth.checkpoint.load_model` reads one like any checkpoint.
"""

from __future__ import annotations

import json
import math
import os
from pathlib import Path
from typing import Any, Mapping

from crfdepth.errors import InputError
from crfdepth.io.files import atomic_write_bytes, check_output_file

__all__ = ["FORMAT", "VERSION", "WEIGHTS", "DEFAULT_WEIGHTS", "weights_path", "load_pretrained",
           "read_weights", "save_weights"]

FORMAT = "crfdepth-weights"
"""Value of the ``"format"`` key of a weights file."""
VERSION = 1
"""Version of the weights-file layout that this module reads and writes."""
WEIGHTS = ("kitti", "paper")
"""Names accepted by :func:`load_pretrained` (and ``--weights`` of the CLI)."""
DEFAULT_WEIGHTS = "kitti"
"""The weight set used when none is named and no checkpoint is given."""

_FOLDER = Path(__file__).resolve().parent / "weights"
#: The learnable values in a configuration (the keys of ``CRFDepth.weights()``).
LEARNED = ("alpha", "beta", "gamma", "delta", "sigma_d", "sigma_n", "sigma_p", "confidence", "refine_prior",
           "std_scale")


def weights_path(name: str) -> Path | None:
    """The file of the shipped weight set ``name`` (None for "paper", which has none)."""
    if name not in WEIGHTS:
        raise InputError(f"weights: expected one of {', '.join(WEIGHTS)}, got {name!r}")
    return None if name == "paper" else _FOLDER / f"{name}.json"


def load_pretrained(name: str = DEFAULT_WEIGHTS, **overrides: Any):
    """A :class:`~crfdepth.model.CRFDepth` with a shipped weight set, in eval mode.

    Args:
        name: "kitti" (learned on KITTI; see ``crfdepth/weights/README.md``) or "paper"
            (the hand-set initial values of ``CRFDepth()``).
        **overrides: ``CRFDepth`` keyword arguments that replace the stored ones, e.g.
            ``mode="pixel"`` (the learned weights on the pixel graph) or
            ``potentials=("colour",)``. Overriding a learned value (``alpha=...``) is
            allowed and replaces it.

    Returns:
        The model on the CPU, float32, in eval mode.

    Raises:
        InputError: an unknown ``name``, or overrides that ``CRFDepth`` rejects.
    """
    from crfdepth.model import CRFDepth

    file = weights_path(name)
    config = {} if file is None else read_weights(file)["config"]
    try:
        return CRFDepth(**{**config, **overrides}).eval()
    except TypeError as exc:  # an unknown keyword argument
        raise InputError(f"overrides: not CRFDepth arguments ({exc})") from None


def read_weights(path: str | os.PathLike) -> dict[str, Any]:
    """Read and check a weights file; returns ``{"format", "version", "config", "about"}``.

    Raises:
        FileNotFoundError: no such file.
        InputError: naming the file and the problem: not JSON, another format or
            version, no ``config`` mapping, or a learned value that is missing or not a
            finite number.
    """
    file = Path(path)
    if not file.is_file():
        raise FileNotFoundError(f"no such weights file: {file}")
    try:
        data = json.loads(file.read_text(encoding="utf-8"))
    except (UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise InputError(f"{file}: expected a crfdepth weights file (JSON), got unreadable content ({exc})") from None
    if not isinstance(data, dict) or data.get("format") != FORMAT:
        found = data.get("format") if isinstance(data, dict) else type(data).__name__
        raise InputError(f"{file}: expected a JSON object with \"format\": \"{FORMAT}\", got format {found!r}")
    if data.get("version") != VERSION:
        raise InputError(f"{file}: expected weights-file version {VERSION}, got {data.get('version')!r}")
    config = data.get("config")
    if not isinstance(config, dict):
        raise InputError(f"{file}: expected a \"config\" object (CRFDepth arguments), got {type(config).__name__}")
    for key in LEARNED:
        value = config.get(key)
        if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
            raise InputError(f"{file}: config[{key!r}]: expected a finite number, got {value!r}")
    data.setdefault("about", {})
    return data


def save_weights(model, path: str | os.PathLike, about: Mapping[str, Any] | None = None) -> Path:
    """Write ``model`` as a weights file (its configuration with the learned values), atomically.

    Args:
        model: a :class:`~crfdepth.model.CRFDepth`.
        path: the output ``.json`` file; its folder must exist. An existing file is replaced.
        about: JSON-serialisable record of how the weights were made (data, command,
            validation metrics ...).

    Returns:
        ``path`` as a :class:`~pathlib.Path`.

    Raises:
        InputError: ``model`` is not a CRFDepth, ``path`` is a folder, or ``about`` is not
            JSON-serialisable.
        FileNotFoundError: the folder of ``path`` does not exist.
    """
    from crfdepth.model import CRFDepth

    if not isinstance(model, CRFDepth):
        raise InputError(f"model: expected a CRFDepth, got {type(model).__name__}")
    file = check_output_file(path)
    config = dict(model.config)
    config.update(model.weights())  # the current (learned) values replace the initial ones
    payload = {"format": FORMAT, "version": VERSION, "config": config, "about": dict(about or {})}
    try:
        text = json.dumps(payload, indent=2) + "\n"
    except (TypeError, ValueError) as exc:
        raise InputError(f"about: expected JSON-serialisable values ({exc})") from None
    atomic_write_bytes(file, text.encode("utf-8"))
    return file
