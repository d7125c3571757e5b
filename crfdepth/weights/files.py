"""Reading and writing weights files and checkpoints, without building a model.

Everything here works on plain data: a configuration (``CRFDepth`` keyword arguments)
and a state dict (parameter name -> tensor). Building the
:class:`~crfdepth.model.CRFDepth` is left to the caller (``CRFDepth.from_stored``), so this
module does not import :mod:`crfdepth.model` and the model can import it (docs/design.md
section 8).

- The shipped weight sets: :func:`weights_path`, :func:`pretrained_state`.
- The JSON weights file: :func:`read_weights`, :func:`write_weights`.
- Any checkpoint (the three kinds of the :mod:`crfdepth.checkpoints` docstring):
  :func:`read_checkpoint`, every floating tensor checked finite, old layouts brought up
  to date, and every stored weight (configuration value or tensor) within a sane range
  (:data:`POSITIVE_RANGE` ...): an absurd weight (confidence 1e38) is refused naming the file
  and the key, not solved into a NaN or constant depth map. Torch files (crfdepth's own model
  file, the trainer's Lightning checkpoint) are
  written and opened by :mod:`crfdepth.weights.torch_files`: read with
  ``torch.load(weights_only=True)``, a bare ``state_dict()`` refused
  (:data:`~crfdepth.weights.torch_files.BARE_STATE_DICT`): it does not say which structure
  its weights belong to.
"""

from __future__ import annotations

import json
import math
import os
from pathlib import Path
from typing import Any, Mapping

import torch

from crfdepth.config import flat_view, is_grouped
from crfdepth.errors import InputError
from crfdepth.io.files import atomic_write_bytes, check_output_file
from crfdepth.weights.torch_files import check_device, is_config, load_torch_file, unpack_torch_file

__all__ = ["DEFAULT_WEIGHTS", "LEARNED", "MAX_ABS_TENSOR", "POSITIVE_RANGE", "STD_BIAS_RANGE", "STD_EXPONENT_RANGE",
           "UNIT_RANGE", "WEIGHTS", "WEIGHTS_FORMAT", "WEIGHTS_VERSION", "check_stored", "check_weights_config",
           "json_lists", "json_state", "pretrained_state", "read_checkpoint", "read_weights", "weights_path", "write_weights"]

WEIGHTS = ("kitti", "paper", "nyu")
"""Names of the shipped weight sets (:func:`crfdepth.load_pretrained`, ``--weights``)."""
DEFAULT_WEIGHTS = "kitti"
"""The weight set used when none is named and no checkpoint is given."""
WEIGHTS_FORMAT = "crfdepth-weights"
"""Value of the ``"format"`` key of a JSON weights file."""
WEIGHTS_VERSION = 1
"""Version of the weights-file layout that this module reads and writes."""
LEARNED = ("alpha", "beta", "gamma", "delta", "sigma_d", "sigma_n", "sigma_p", "confidence", "refine_prior",
           "std_scale")
"""The learnable values in a configuration (the keys of ``CRFDepth.weights()``)."""

# Sane ranges of stored weights, far outside every value trained or set by hand (crfdepth/weights/kitti.json:
# confidence 3411, gate_softness 0.0015, the others 0.009-2.04 and std terms -1.35-1.17; CRFDepth()'s
# defaults: 0.003-100). A value outside is a damaged or mis-exported file: solved, it would end in a solver
# warning and a NaN or constant depth map. The model's own parameters (crfdepth/potentials/parameters.py)
# hold the log of each positive weight and the logit of each weight in (0, 1): the same ranges, mapped.
POSITIVE_RANGE = (1e-6, 1e6)
"""Weights > 0 (sigma_d, sigma_n, sigma_p, confidence, refine_prior, std_scale, gate_threshold,
gate_softness, irls_scale, eps): each within [1e-6, 1e6]."""
UNIT_RANGE = (1e-6, 1.0 - 1e-6)
"""Weights in (0, 1) (alpha, beta, gamma, delta): at least 1e-6 from either end."""
STD_BIAS_RANGE = (-math.log(1e6), math.log(1e6))
"""``std_terms["bias"]``, log metres (crfdepth/uncertainty/predictive.py): a std scale of 1e-6 to 1e6 m."""
STD_EXPONENT_RANGE = (-10.0, 10.0)
"""The other ``std_terms``, exponents of the predictive std's signals (fitted: 0.19-1.17); at 10 a signal
spanning two decades spans twenty of std."""
MAX_ABS_TENSOR = 1e6
"""Any other stored floating tensor (the learned head's weights): every ``|value| <= 1e6``."""
_UNIT = ("alpha", "beta", "gamma", "delta")
_POSITIVE = ("sigma_d", "sigma_n", "sigma_p", "confidence", "refine_prior", "std_scale", "gate_threshold",
             "gate_softness", "irls_scale", "eps")

#: What a configuration written before these options existed meant: an old checkpoint is
#: rebuilt as it was trained (docs/design.md section 3b).
_OLD_DEFAULTS = {"variable": "depth", "gate": False, "head": False, "prior": "nearest", "uncertainty": "posterior"}
_FOLDER = Path(__file__).resolve().parent  # the shipped files lie beside this module


# --------------------------------------------------------------------------- shipped weight sets


def weights_path(name: str) -> Path | None:
    """The file of the shipped weight set ``name`` (None for "paper", which has none).

    Raises:
        InputError: ``name`` is not one of :data:`WEIGHTS`.
    """
    if not isinstance(name, str) or name not in WEIGHTS:
        raise InputError(f"name: expected one of the shipped weights {', '.join(WEIGHTS)}, got {name!r}")
    return None if name == "paper" else _FOLDER / f"{name}.json"


def pretrained_state(name: str) -> tuple[dict[str, Any], dict[str, torch.Tensor]]:
    """The configuration and state dict of the shipped weight set ``name``.

    The model is ``CRFDepth(**{**config, **overrides})``, then, when ``state`` is not
    empty, ``model.load_state_dict(state)``:

    - ``"kitti"``: ``crfdepth/weights/kitti.json``, a JSON weights file. Its
      configuration holds the learned values as constructor arguments (``alpha=0.469``
      ...), so ``state`` is empty and an override of a learned value (``alpha=0.3``)
      replaces it.
    - ``"paper"``: the hand-set initial values of ``CRFDepth()``: ``({}, {})``.

    A shipped set stored as a torch file would come back as :func:`read_checkpoint` reads
    any checkpoint (old layouts upgraded, tensors checked finite).

    Args:
        name: one of :data:`WEIGHTS`.

    Returns:
        ``(config, state)``: fresh objects, the caller may change them.

    Raises:
        InputError: an unknown ``name`` (the choices are listed).
    """
    file = weights_path(name)
    if file is None:
        return {}, {}
    config, state, _ = read_checkpoint(file)
    return config, state


# --------------------------------------------------------------------------- JSON weights file


def read_weights(path: str | os.PathLike) -> dict[str, Any]:
    """Read and check a weights file; returns ``{"format", "version", "config", "about"}``.

    Raises:
        FileNotFoundError: no such file.
        InputError: naming the file and the problem: not JSON, another format or
            version, no ``config`` mapping, a learned value that is missing or not a
            finite number, or a weight outside its range (:data:`POSITIVE_RANGE`,
            :data:`UNIT_RANGE`, :data:`STD_BIAS_RANGE`, :data:`STD_EXPONENT_RANGE`).
    """
    file = Path(path)
    if not file.is_file():
        raise FileNotFoundError(f"no such weights file: {file}")
    try:
        data = json.loads(file.read_text(encoding="utf-8"))
    except (UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise InputError(f"{file}: expected a crfdepth weights file (JSON), got unreadable content ({exc})") from None
    if not isinstance(data, dict) or data.get("format") != WEIGHTS_FORMAT:
        found = data.get("format") if isinstance(data, dict) else type(data).__name__
        raise InputError(f"{file}: expected a JSON object with \"format\": \"{WEIGHTS_FORMAT}\", got format {found!r}")
    if data.get("version") != WEIGHTS_VERSION:
        raise InputError(f"{file}: expected weights-file version {WEIGHTS_VERSION}, got {data.get('version')!r}")
    config = data.get("config")
    if not isinstance(config, dict):
        raise InputError(f"{file}: expected a \"config\" object (CRFDepth arguments), got {type(config).__name__}")
    check_weights_config(file, config)
    data.setdefault("about", {})
    return data


def check_weights_config(file: Path, config: Mapping[str, Any], kind: str = "weights file", where: str = "") -> None:
    """A weights file's configuration (``where``: the path of a regime's, :mod:`crfdepth.weights.regimes`): every
    learned value a finite number within its range."""
    values = flat_view(config)  # grouped (current files) or flat (earlier ones)
    for key in LEARNED:
        value = values.get(key)
        if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
            raise InputError(f"{file}: {where}config[{key!r}]: expected a finite number, got {value!r}")
    _check_config_ranges(file, values, kind)


def write_weights(path: str | os.PathLike, config: Mapping[str, Any], about: Mapping[str, Any] | None = None,
                  state: Mapping[str, torch.Tensor] | None = None, regimes: Mapping[str, Any] | None = None) -> Path:
    """Write a weights file holding ``config`` (with the learned values) and ``about``, atomically.

    ``state``: the tensors that are not constructor arguments (the weights of the learned
    head, :mod:`crfdepth.potentials.head`), stored as nested lists under ``"state"``. ``regimes``: the
    model's regimes as :func:`crfdepth.weights.regimes.json_regimes` writes them, under ``"regimes"``.

    Raises:
        InputError: ``path`` is a folder, or ``config`` / ``about`` are not
            JSON-serialisable (nothing is written).
        FileNotFoundError: the folder of ``path`` does not exist.
    """
    file = check_output_file(path)
    payload = {"format": WEIGHTS_FORMAT, "version": WEIGHTS_VERSION, "config": dict(config),
               "about": dict(about or {})}
    if state:
        payload["state"] = json_lists(state)
    if regimes:
        payload["regimes"] = dict(regimes)
    for name in ("about", "config", "regimes"):
        try:
            json.dumps(payload.get(name))
        except (TypeError, ValueError) as exc:
            raise InputError(f"{name}: expected JSON-serialisable values ({exc})") from None
    text = json.dumps(payload, indent=2) + "\n"
    atomic_write_bytes(file, text.encode("utf-8"))
    return file


# --------------------------------------------------------------------------- any checkpoint


def read_checkpoint(path: str | os.PathLike, map_location: str | torch.device = "cpu"
                    ) -> tuple[dict[str, Any], dict[str, torch.Tensor], str]:
    """The configuration, state dict and kind of a checkpoint file of any of the three kinds.

    A JSON weights file gives its configuration and an empty state dict (the learned
    values are in the configuration). A torch file is read with ``torch.load(path,
    weights_only=True, map_location=map_location)``: a file holding anything but tensors
    and plain containers is refused without running any of its code. Its state dict is
    brought to the current layout (the old buffer ``refine_prior`` becomes the parameter
    ``log_refine_prior``) and every floating tensor in it must be finite. A bare state dict
    (``torch.save(model.state_dict(), path)``) is refused: without its configuration the
    weights would run in another structure (:data:`~crfdepth.weights.torch_files.BARE_STATE_DICT`).

    Args:
        path: the checkpoint file.
        map_location: device to load the tensors to ("cpu", "cuda", a ``torch.device``).

    Returns:
        ``(config, state, kind)``: the stored ``CRFDepth`` keyword arguments, the state
        dict (``{}`` for a weights file without a head), and the kind of file for messages
        ("weights file", "crfdepth model file", "Lightning checkpoint").

    Raises:
        FileNotFoundError: ``path`` does not exist.
        InputError: naming the file and the problem: a folder; not a checkpoint; no state
            dict in it; a bare state dict without a configuration; a Lightning checkpoint
            without ``hyper_parameters["crf"]`` or without ``model.`` keys; a tensor with NaN or
            inf (``path: <file>: parameter raw_alpha: expected finite values, got nan``); a weight out of its range, in the
            configuration (``<file>: invalid model configuration in the <kind>: config['confidence']:
            expected a number in [1e-06, 1e+06] ...``) or as a tensor (``path: <file>: parameter
            log_confidence: expected values in [-13.82, 13.82] ...``); a CUDA ``map_location``
            without CUDA.
    """
    file = Path(path)
    if not file.exists():
        raise FileNotFoundError(f"no such checkpoint file: {file}")
    if file.is_dir():
        raise InputError(f"{file}: expected a checkpoint file, got a folder")
    device = check_device(map_location)
    if _is_json(file):
        data = read_weights(file)
        state = json_state(file, data.get("state", {}), device)
        return _upgrade_config(dict(data["config"]), state), state, "weights file"
    config, state, kind = unpack_torch_file(file, load_torch_file(file, device))
    return (*check_stored(file, config, state, kind), kind)


def check_stored(file: Path, config: dict[str, Any], state: dict[str, torch.Tensor], kind: str
                 ) -> tuple[dict[str, Any], dict[str, torch.Tensor]]:
    """A torch file's configuration and state dict checked (finite tensors, every weight within its range) and
    brought up to date (old layouts, options a configuration predates)."""
    _check_finite(file, state)
    state = _upgrade(file, state)
    _check_tensor_ranges(file, state)
    _check_config_ranges(file, flat_view(config), kind)
    return _upgrade_config(config, state), state


# --------------------------------------------------------------------------- helpers


def _is_json(file: Path) -> bool:
    """Whether ``file`` starts (after white space) with ``{``: a JSON weights file."""
    with open(file, "rb") as handle:
        return handle.read(64).lstrip()[:1] == b"{"


def _check_finite(file: Path, state: Mapping[str, torch.Tensor]) -> None:
    """Every floating tensor of ``state`` is finite; the message names the file and the parameter
    as stored in the file (a NaN weight would otherwise surface deep inside a solve)."""
    for key, value in state.items():
        if not (value.is_floating_point() or value.is_complex()):
            continue
        finite = torch.isfinite(value)
        if not bool(finite.all()):
            bad = value[~finite].flatten()
            got = str(bad[0].item())
            if value.numel() > 1:
                got += f" ({bad.numel()} of {value.numel()} values not finite)"
            raise InputError(f"path: {file}: parameter {key}: expected finite values, got {got}")


def _upgrade_config(config: dict[str, Any], state: Mapping[str, torch.Tensor]) -> dict[str, Any]:
    """Options a configuration predates take their old meaning; an empty configuration (a
    Lightning checkpoint of ``CRFDepth()`` with every default) says by its state's keys whether
    it has a gate and a head."""
    if config:
        return config if is_grouped(config) else {**_OLD_DEFAULTS, **config}
    if state:
        return {"gate": "log_gate_threshold" in state, "head": any(k.startswith("head.") for k in state),
                "uncertainty": "predictive" if "std_head.weights" in state else "posterior"}
    return config


def json_lists(state: Mapping[str, torch.Tensor]) -> dict[str, list]:
    """A weights file's ``"state"``: each tensor as nested lists of float32 values (read back by :func:`json_state`)."""
    return {k: v.detach().cpu().float().tolist() for k, v in state.items()}


def json_state(file: Path, value: Any, device: torch.device) -> dict[str, torch.Tensor]:
    """The ``"state"`` of a weights file (name -> nested lists) as float32 tensors, checked finite."""
    if not is_config(value):
        raise InputError(f"{file}: expected \"state\" to map parameter names to nested lists of numbers, "
                         f"got {type(value).__name__}")
    try:
        state = {k: torch.tensor(v, dtype=torch.float32, device=device) for k, v in value.items()}
    except (TypeError, ValueError) as exc:
        raise InputError(f"{file}: \"state\": expected nested lists of numbers ({exc})") from None
    _check_finite(file, state)
    _check_tensor_ranges(file, state)
    return state


def _upgrade(file: Path, state: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
    """A state dict holding the refinement prior as the buffer ``refine_prior`` gets the parameter
    ``log_refine_prior`` the model loads (its log: learned in log space, the prior stays > 0)."""
    if "refine_prior" in state and "log_refine_prior" not in state:
        positive = state["refine_prior"] > 0
        if not bool(positive.all()):
            raise InputError(f"path: {file}: parameter refine_prior: expected values > 0, "
                             f"got {state['refine_prior'][~positive].flatten()[0].item()}")
        state = dict(state)
        state["log_refine_prior"] = state.pop("refine_prior").log()
    return state


def _is_number(value: Any) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool)


def _check_config_ranges(file: Path, values: Mapping[str, Any], kind: str) -> None:
    """The weights a configuration sets (flat names, :func:`crfdepth.config.flat_view`) within their ranges;
    values that are not numbers are left to ``CRFDepth``'s own checks."""
    checks = [(f"config[{key!r}]", value, UNIT_RANGE if key in _UNIT else POSITIVE_RANGE,
               "a weight in (0, 1)" if key in _UNIT else "a weight > 0")
              for key, value in values.items() if key in _UNIT + _POSITIVE]
    terms = values.get("std_terms")
    if isinstance(terms, Mapping):
        checks += [(f"config['std_terms'][{key!r}]", value, STD_BIAS_RANGE if key == "bias" else STD_EXPONENT_RANGE,
                    "log metres" if key == "bias" else "an exponent") for key, value in terms.items()]
    for where, value, (low, high), meaning in checks:
        # a float32 weight written back (save_weights) may sit just outside a bound: 1e-5 of it is allowed
        if _is_number(value) and not low - 1e-5 * abs(low) <= value <= high + 1e-5 * abs(high):
            raise InputError(f"{file}: invalid model configuration in the {kind}: {where}: expected a number in "
                             f"[{low:.6g}, {high:.6g}] ({meaning}), got {value!r}")


def _tensor_range(key: str, value: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, str]:
    """(low, high, meaning) of the stored tensor ``key`` (broadcast against ``value``)."""
    name = key.split("_", 1)[-1]
    if key.startswith("raw_") and name in _UNIT:
        low, high = (math.log(p / (1.0 - p)) for p in UNIT_RANGE)
        meaning = f"the logit of {name}, a weight in [{UNIT_RANGE[0]:g}, {UNIT_RANGE[1]:g}]"
    elif key.startswith("log_") and name in _POSITIVE:
        low, high = (math.log(p) for p in POSITIVE_RANGE)
        meaning = f"the log of {name}, a weight in [{POSITIVE_RANGE[0]:g}, {POSITIVE_RANGE[1]:g}]"
    elif key in _POSITIVE:
        (low, high), meaning = POSITIVE_RANGE, "a weight > 0"
    elif key == "std_head.weights" and value.numel() == 6:
        lows = [STD_BIAS_RANGE[0]] + [STD_EXPONENT_RANGE[0]] * 5
        highs = [STD_BIAS_RANGE[1]] + [STD_EXPONENT_RANGE[1]] * 5
        return (value.new_tensor(lows).view(value.shape), value.new_tensor(highs).view(value.shape),
                "the predictive std's bias (log metres) and exponents")
    else:
        (low, high), meaning = (-MAX_ABS_TENSOR, MAX_ABS_TENSOR), "a learned weight"
    return value.new_tensor(low), value.new_tensor(high), meaning


def _weight_of(key: str, free: float) -> str:
    """`` (<weight> <value>)`` of the free parameter ``key`` (``log_<weight>`` or ``raw_<weight>``), else ""."""
    name = key.split("_", 1)[-1]
    if key.startswith("log_") and name in _POSITIVE:
        return f" ({name} {math.exp(min(free, 700.0)):.4g})"
    if key.startswith("raw_") and name in _UNIT:
        return f" ({name} {1.0 / (1.0 + math.exp(-max(min(free, 700.0), -700.0))):.6g})"
    return ""


def _check_tensor_ranges(file: Path, state: Mapping[str, torch.Tensor]) -> None:
    """Every floating (finite) tensor of ``state`` within the range of its key (:func:`_tensor_range`); the
    message names the file and the parameter as the model stores it."""
    for key, value in state.items():
        if not value.is_floating_point():
            continue
        low, high, meaning = _tensor_range(key, value.double())
        slack = 1e-6 * torch.clamp(torch.maximum(low.abs(), high.abs()), min=1.0)  # a bound's float32 rounding
        outside = (value.double() < low - slack) | (value.double() > high + slack)
        if bool(outside.any()):
            bad = value[outside].flatten()
            bounds = (f"[{float(low):.4g}, {float(high):.4g}]" if low.numel() == 1 else
                      " to ".join(f"[{', '.join(f'{v:.4g}' for v in b.tolist())}]" for b in (low, high)))
            got = f"{bad[0].item():.6g}" + (f" ({bad.numel()} of {value.numel()} values outside)" if value.numel() > 1
                                           else _weight_of(key, bad[0].item()))
            raise InputError(f"path: {file}: parameter {key}: expected values in {bounds} ({meaning}), got {got}")
