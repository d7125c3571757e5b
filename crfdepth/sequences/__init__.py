"""Learning from recordings: poses, camera-view targets, free space and the photometric loss
(docs/design.md sections 12-15). :func:`make_targets` writes the camera-view targets of a KITTI raw drive or a
ROS bag (``crfdepth targets``)."""

from crfdepth.sequences.recording_targets import DriveTargets, make_targets

__all__ = ["DriveTargets", "make_targets"]
