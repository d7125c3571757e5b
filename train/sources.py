"""Training sources of the data module (``extra_train``): each checked, and weighted by how many of its frames one
epoch draws (docs/design.md section 16).

Sources differ in size and in how well their targets match what the model is scored on (KITTI's
annotation, LiDAR returns held out of a scan, camera-view targets accumulated over a drive). A
source's ``weight`` scales its share of every epoch: with weight ``w`` its ``n`` frames appear
``round(w * n)`` times, as whole copies for the integer part of ``w`` and a fixed seeded choice of
frames for the rest. Each appearance is a separate item of the epoch, so the trainer's per-item draws
(flip, crop, thinning, an annotated frame's input pixels) differ between copies of a frame. A repeat
keeps the epoch a fixed list, which is what lets a stopped run resume mid-epoch (:mod:`train.sampling`).
"""

from __future__ import annotations

import math
import re
from typing import Any

import torch
from torch.utils.data import ConcatDataset, Dataset, Subset

from crfdepth.checks import check_choice
from crfdepth.data.factory import LAYOUTS
from crfdepth.errors import InputError

__all__ = ["MAX_SOURCE_WEIGHT", "check_source", "check_weight", "option_message", "weighted"]

#: A source drawn more than this many times per epoch is a typo rather than a recipe.
MAX_SOURCE_WEIGHT = 100.0


def check_weight(name: str, weight: object) -> float:
    """``weight`` as a float in (0, MAX_SOURCE_WEIGHT]; InputError naming ``name`` otherwise."""
    ok = isinstance(weight, (int, float)) and not isinstance(weight, bool) and math.isfinite(weight) \
        and 0 < weight <= MAX_SOURCE_WEIGHT
    if not ok:
        raise InputError(f"{name}: expected a number in (0, {MAX_SOURCE_WEIGHT:g}] (the source's frames drawn per "
                         f"epoch, relative to its size), got {weight!r}")
    return float(weight)


def weighted(dataset: Dataset, weight: float, seed: int = 0) -> Dataset:
    """``dataset`` repeated so that one epoch holds ``round(weight * len(dataset))`` of its frames.

    Args:
        dataset: a map-style dataset of n > 0 frames.
        weight: > 0; 1 returns ``dataset`` itself.
        seed: chooses the frames of the fractional part (a fixed choice, the same every epoch).

    Returns:
        a ``ConcatDataset`` of whole copies and a ``Subset`` (or ``dataset`` for weight 1); at least
        one frame.
    """
    if weight == 1.0:
        return dataset
    n = len(dataset)
    total = max(1, round(weight * n))
    whole, rest = divmod(total, n)
    parts: list[Dataset] = [dataset] * whole
    if rest:
        order = torch.randperm(n, generator=torch.Generator().manual_seed(seed)).tolist()
        parts.append(Subset(dataset, sorted(order[:rest])))
    return parts[0] if len(parts) == 1 else ConcatDataset(parts)


def check_source(index: int, source: Any) -> dict[str, Any]:
    """An ``extra_train`` entry, checked and normalised (``names_contain`` as a list or None, ``weight`` a float,
    1 when not given)."""
    where = f"extra_train[{index}]"
    if not isinstance(source, dict):
        raise InputError(f"{where}: expected a mapping with layout, root, options, names_contain, weight, "
                         f"got {type(source).__name__}")
    unknown = set(source) - {"layout", "root", "options", "names_contain", "weight"}
    if unknown:
        raise InputError(f"{where}: expected keys among layout, root, options, names_contain, weight, got "
                         f"{sorted(unknown)}")
    check_choice(f"{where}.layout", source.get("layout"), LAYOUTS)
    options = source.get("options")
    if options is not None and not isinstance(options, dict):
        raise InputError(f"{where}.options: expected a mapping of dataset options, got {type(options).__name__}")
    keep = source.get("names_contain")
    if isinstance(keep, str):
        keep = [keep]
    if keep is not None and (not isinstance(keep, list) or not all(isinstance(k, str) for k in keep)):
        raise InputError(f"{where}.names_contain: expected a string or a list of strings, got {keep!r}")
    weight = check_weight(f"{where}.weight", source.get("weight", 1.0))
    return {**source, "names_contain": keep, "weight": weight}


def option_message(role: str, layout: str, options: dict[str, Any], exc: TypeError) -> str:
    """One line for a dataset option the layout's dataset does not take (``exc``: Python's
    ``... got an unexpected keyword argument 'split'``), named as the user gives it."""
    where = f"{role}_options" if role in ("train", "val") else f"{role}.options"
    match = re.search(r"unexpected keyword argument '(\w+)'", str(exc))
    if match is None:
        return f"{where}: expected options of layout {layout!r}, got {sorted(options)} ({exc})"
    hint = " (a depth_completion option: with another val_layout, set val_options for it, or null)" \
        if match.group(1) == "split" else ""
    return f"{where}: expected options that layout {layout!r} takes, got {match.group(1)!r}{hint}"
