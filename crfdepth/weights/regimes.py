"""The regimes of a model: the shipped ones, and how crfdepth's files hold them (docs/design.md sections 8, 17).

The default model sends frames with few returns to other models, its regimes (:mod:`crfdepth.inference.regime`).
A file of the model holds them too: a model reloaded without them would complete those frames with its own weights,
and nothing would say so. Both of crfdepth's files keep them under ``"regimes"``, a mapping of the regime's attribute
(``"sparse_regime"``, ``"line_regime"``, ``"indoor_regime"``) to what the file holds for a model:
``{"config", "state_dict"}`` in a model file (:func:`crfdepth.save_model`), ``{"config"}`` with the learned values
written in, and ``"state"`` where it has a learned head, in a weights file (:func:`crfdepth.save_weights`). Each is
checked as the file's own model is. A file without the key (a Lightning checkpoint, a file written before) has none.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any, Mapping, Sequence

import torch

from crfdepth.errors import InputError
from crfdepth.weights.files import check_stored, check_weights_config, json_lists, json_state
from crfdepth.weights.torch_files import is_config, load_torch_file

__all__ = ["REGIMES_KEY", "SPARSE_REGIMES", "json_regimes", "read_regimes"]

SPARSE_REGIMES: dict[str, dict[str, dict[str, Any]]] = {"kitti": {
    "scattered": {"structure": {"mode": "pixel", "coarse": 6, "near_inverse": 10.0, "coarse_shifts": 2}},
    "lines": {"structure": {"mode": "pixel", "coarse": 6, "variable": "log", "coarse_shifts": 2}},
    "indoor": "nyu",
}}
"""Shipped set -> the configurations (hand-set weights) of the models that complete its frames with few returns
(:meth:`CRFDepth.from_pretrained <crfdepth.model.CRFDepth.from_pretrained>`, docs/design.md section 17):
``"scattered"`` (500 samples; near blocks from the inverse-depth unknown, chosen by cross-validation) and
``"lines"`` (returns on scan lines: 16 beams; the log unknown, chosen by cross-validation), each a configuration of
hand-set weights; ``"indoor"`` (scattered returns within a room's depths) a shipped set's name."""
REGIMES_KEY = "regimes"
"""The key of a file's regimes."""


def json_regimes(records: Mapping[str, tuple[Mapping[str, Any], Mapping[str, torch.Tensor]]]) -> dict[str, Any]:
    """A weights file's ``"regimes"`` from name -> ``(config with the learned values, head state)``."""
    out = {}
    for name, (config, state) in records.items():
        out[name] = {"config": dict(config)}
        if state:
            out[name]["state"] = json_lists(state)
    return out


def read_regimes(file: Path, kind: str, device: torch.device, names: Sequence[str]
                 ) -> dict[str, tuple[dict[str, Any], dict]]:
    """name -> ``(config, state)`` of each regime a checkpoint ``file`` of ``kind`` (as
    :func:`crfdepth.weights.files.read_checkpoint` names it) holds, checked; ``{}`` where it holds none. ``names``:
    the regimes a model has (:data:`crfdepth.inference.regime.REGIMES`, a layer above this one).

    Raises:
        InputError: naming the file and the regime: ``"regimes"`` not a mapping of ``names``, a record without its
            configuration or state, or a weight that the file's own model would be refused for.
    """
    if kind == "weights file":
        raw, state_key = json.loads(file.read_text(encoding="utf-8")).get(REGIMES_KEY), "state"
    elif kind == "crfdepth model file":
        raw, state_key = load_torch_file(file, device).get(REGIMES_KEY), "state_dict"
    else:
        return {}
    if raw is None:
        return {}
    if not is_config(raw) or not set(raw) <= set(names):
        got = sorted(map(str, raw)) if isinstance(raw, Mapping) else type(raw).__name__
        raise InputError(f"{file}: \"{REGIMES_KEY}\": expected a mapping of names among {', '.join(names)}, "
                         f"got {got}")
    out = {}
    for name, record in raw.items():
        where = f"{REGIMES_KEY}[{name!r}]"
        config = record.get("config") if isinstance(record, Mapping) else None
        if not is_config(config):
            got = f"keys {sorted(map(str, record))}" if isinstance(record, Mapping) else type(record).__name__
            raise InputError(f"{file}: {where}: expected a mapping with a \"config\" (CRFDepth arguments), got "
                             f"{got if config is None else 'a config of ' + type(config).__name__}")
        state = record.get(state_key, {} if state_key == "state" else None)
        try:
            if state_key == "state":
                check_weights_config(file, config, f"weights file's {where}", where=where + ".")
                out[name] = dict(config), json_state(file, state, device)
            elif not isinstance(state, dict) or not all(isinstance(v, torch.Tensor) for v in state.values()):
                raise InputError(f"{file}: {where}: expected a \"state_dict\" of tensors, got {type(state).__name__}")
            else:
                out[name] = check_stored(file, dict(config), state, f"{kind}'s {where}")
        except InputError as exc:  # a tensor's message names the parameter, not whose it is
            raise InputError(str(exc) if where in str(exc) else f"{exc} (in {where})") from None
    return out
