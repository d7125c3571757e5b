"""crfdepth: dense, calibrated depth from a camera image and sparse LiDAR with a learnable CRF.

Start with :meth:`crfdepth.CRFDepth.from_pretrained` (the model with the weights learned on
KITTI), :func:`crfdepth.complete_depth` (arrays in, arrays out, any rig) or the ``crfdepth``
command. The library does not need Lightning; the
trainer lives in the separate ``train`` package.
"""

from __future__ import annotations

import importlib
import importlib.util
from typing import TYPE_CHECKING

from crfdepth._version import __version__  # pyproject.toml's version, via the package metadata
from crfdepth.errors import ConvergenceError, ConvergenceWarning, InputError

if TYPE_CHECKING:
    from crfdepth.api import complete_batch, complete_depth
    from crfdepth.checkpoints import load_model, load_pretrained, save_model, save_weights
    from crfdepth.layer import CRFRefine, crf_refine
    from crfdepth.linalg import SolveInfo, solve_grid_laplacian, solve_laplacian
    from crfdepth.model import CRFDepth, CRFOutput

# Where each public name lives, imported at its first use (PEP 562): ``import crfdepth`` (and so ``crfdepth
# --version``, ``--help``) does not import torch, kornia, scipy or OpenCV until a name that needs them is used.
_LAZY = {
    "complete_batch": "crfdepth.api",
    "complete_depth": "crfdepth.api",
    "load_model": "crfdepth.checkpoints",
    "load_pretrained": "crfdepth.checkpoints",
    "save_model": "crfdepth.checkpoints",
    "save_weights": "crfdepth.checkpoints",
    "CRFRefine": "crfdepth.layer",
    "crf_refine": "crfdepth.layer",
    "SolveInfo": "crfdepth.linalg",
    "solve_grid_laplacian": "crfdepth.linalg",
    "solve_laplacian": "crfdepth.linalg",
    "CRFDepth": "crfdepth.model",
    "CRFOutput": "crfdepth.model",
}


def __getattr__(name: str):
    """The public name ``name`` of :data:`_LAZY`, imported from its module at first use and kept here; or the
    submodule ``crfdepth.<name>`` (``crfdepth.api`` after ``import crfdepth``, as when this file imported it)."""
    if name in _LAZY:
        value = getattr(importlib.import_module(_LAZY[name]), name)
    elif not name.startswith("_") and importlib.util.find_spec(f"crfdepth.{name}") is not None:
        value = importlib.import_module(f"crfdepth.{name}")
    else:
        raise AttributeError(f"module 'crfdepth' has no attribute {name!r}")
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(_LAZY))


__all__ = [
    "CRFDepth",
    "CRFOutput",
    "CRFRefine",
    "ConvergenceError",
    "ConvergenceWarning",
    "InputError",
    "SolveInfo",
    "complete_batch",
    "complete_depth",
    "crf_refine",
    "load_model",
    "load_pretrained",
    "save_model",
    "save_weights",
    "solve_grid_laplacian",
    "solve_laplacian",
    "__version__",
]
