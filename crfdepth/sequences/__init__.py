"""Learning from recordings: poses, camera-view targets, free space and the photometric loss
(docs/design.md sections 12-15). :func:`make_targets` writes the camera-view targets of a KITTI raw drive or a
ROS bag (``crfdepth targets``)."""

from __future__ import annotations

from typing import TYPE_CHECKING

from crfdepth.lazy import lazy_names

if TYPE_CHECKING:
    from crfdepth.sequences.recording_targets import DriveTargets, make_targets

__all__ = ["DriveTargets", "make_targets"]


# imported at first use: a module that needs one submodule (the pictures need ``targets``) does not import the
# recordings' readers with it
__getattr__, __dir__ = lazy_names(__name__, dict.fromkeys(__all__, "crfdepth.sequences.recording_targets"))
