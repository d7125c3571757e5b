"""Weights on disk: the shipped sets, the file formats and the checked loading step.

Nothing here builds a model, so :mod:`crfdepth.model` can use it
(``CRFDepth.from_pretrained``); :mod:`crfdepth.checkpoints` holds the functions that do
(``load_model``, ``save_model``, ``save_weights``). The shipped sets are ``"kitti"`` (learned
on real KITTI frames; ``crfdepth/weights/README.md`` says how) and ``"paper"`` (the hand-set
values of ``CRFDepth()``, no file).
"""

from crfdepth.weights.files import (
    DEFAULT_WEIGHTS,
    LEARNED,
    WEIGHTS,
    WEIGHTS_FORMAT,
    WEIGHTS_VERSION,
    pretrained_state,
    read_checkpoint,
    read_weights,
    weights_path,
    write_weights,
)
from crfdepth.weights.regimes import SPARSE_REGIMES
from crfdepth.weights.state import load_state
from crfdepth.weights.torch_files import BARE_STATE_DICT, MODEL_FORMAT, MODEL_VERSION, write_model_file

__all__ = ["BARE_STATE_DICT", "DEFAULT_WEIGHTS", "LEARNED", "MODEL_FORMAT", "MODEL_VERSION", "SPARSE_REGIMES", "WEIGHTS",
           "WEIGHTS_FORMAT", "WEIGHTS_VERSION", "load_state", "pretrained_state", "read_checkpoint", "read_weights",
           "weights_path", "write_model_file", "write_weights"]
