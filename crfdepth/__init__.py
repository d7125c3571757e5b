"""crfdepth: dense, calibrated depth from a camera image and sparse LiDAR with a learnable CRF.

Start with :meth:`crfdepth.CRFDepth.from_pretrained` (the model with the weights learned on
KITTI), :func:`crfdepth.complete_depth` (arrays in, arrays out, any rig) or the ``crfdepth``
command. The library does not need Lightning; the
trainer lives in the separate ``train`` package.
"""

from crfdepth._version import __version__  # pyproject.toml's version, via the package metadata
from crfdepth.api import complete_batch, complete_depth
from crfdepth.checkpoints import load_model, load_pretrained, save_model, save_weights
from crfdepth.errors import ConvergenceError, ConvergenceWarning, InputError
from crfdepth.layer import CRFRefine, crf_refine
from crfdepth.linalg import SolveInfo, solve_grid_laplacian, solve_laplacian
from crfdepth.model import CRFDepth, CRFOutput

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
