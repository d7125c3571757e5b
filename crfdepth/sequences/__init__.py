"""Learning from recordings: poses, camera-view targets, free space and the photometric loss
(docs/design.md sections 12-15). :func:`make_targets` writes the camera-view targets of a KITTI raw drive or a
ROS bag (``crfdepth targets``)."""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from crfdepth.sequences.recording_targets import DriveTargets, make_targets

__all__ = ["DriveTargets", "make_targets"]


def __getattr__(name: str):
    """``DriveTargets`` and ``make_targets``, imported at first use (PEP 562): a module that needs one submodule
    (the pictures need ``targets``) does not import the recordings' readers with it."""
    if name not in __all__:
        raise AttributeError(f"module 'crfdepth.sequences' has no attribute {name!r}")
    value = getattr(importlib.import_module("crfdepth.sequences.recording_targets"), name)
    globals()[name] = value
    return value
