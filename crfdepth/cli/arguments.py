"""The argparse types of the commands' options, options that two commands share, and what a
command reports as bad input.

:func:`int_at_least` / :func:`fraction` / :func:`positive_number` refuse a value with a
message naming what was expected; argparse prefixes it with the option.
"""

from __future__ import annotations

import argparse
import math

import numpy as np

from crfdepth.errors import InputError

__all__ = ["BAD_INPUT", "VisRange", "add_rerun_argument", "add_topic_arguments", "fraction", "int_at_least",
           "positive_number", "vis_range_type"]

# What ``crfdepth.cli.main`` reports as bad input (one line, exit status 2).
BAD_INPUT = (InputError, FileNotFoundError, PermissionError, IsADirectoryError)


def int_at_least(low: int, high: int | None = None, meaning: str | None = None):
    """An argparse ``type`` accepting integers >= ``low`` (and <= ``high`` when given); ``meaning``,
    when given, says in the message what the number is."""
    bounds = f">= {low}" if high is None else f"in [{low}, {high}]"
    note = f" ({meaning})" if meaning else ""

    def parse(text: str) -> int:
        try:
            value = int(text)
        except ValueError:
            value = low - 1
        if value < low or (high is not None and value > high):
            raise argparse.ArgumentTypeError(f"expected an integer {bounds}{note}, got {text!r}")
        return value

    return parse


def fraction(*, include_one: bool, meaning: str | None = None):
    """An argparse ``type`` accepting a number in (0, 1] (``include_one``) or in (0, 1); ``meaning``,
    when given, says in the message what the number is."""
    bounds = "(0, 1]" if include_one else "(0, 1)"
    note = f" ({meaning})" if meaning else ""

    def parse(text: str) -> float:
        try:
            value = float(text)
        except ValueError:
            value = math.nan
        if not (0.0 < value <= 1.0 if include_one else 0.0 < value < 1.0):  # also refuses nan
            raise argparse.ArgumentTypeError(f"expected a number in {bounds}{note}, got {text!r}")
        return value

    return parse


def positive_number(unit: str):
    """An argparse ``type`` accepting a finite number > 0 of ``unit`` (e.g. "metres", "seconds")."""
    def parse(text: str) -> float:
        try:
            value = float(text)
        except ValueError:
            value = float("nan")
        if not np.isfinite(value) or value <= 0:
            raise argparse.ArgumentTypeError(f"expected a finite number of {unit} > 0, got {text!r}")
        return value

    return parse


vis_range_type = positive_number("metres")  # one bound of --vis-range


class VisRange(argparse.Action):
    """``--vis-range MIN MAX`` (``nargs=2, type=vis_range_type``: each a finite number of metres > 0): stored as
    a (min, max) tuple, refused as a usage error unless MIN < MAX, so that a bad range stops the command
    before any work, not when the first picture is drawn."""

    def __call__(self, parser, namespace, values, option_string=None):
        low, high = values
        if not low < high:
            raise argparse.ArgumentError(self, f"expected MIN < MAX in metres, got {low:g} {high:g}")
        setattr(namespace, self.dest, (low, high))


def add_topic_arguments(group: argparse._ArgumentGroup, *, only_one_default: bool = False,
                        points_aliases: tuple[str, ...] = ()) -> None:
    """``--bag``, ``--image-topic``, ``--points-topic`` (+ ``points_aliases``) and ``--camera-info-topic``, the
    options of ``complete --bag`` and ``targets --bag``, on ``group``; ``only_one_default``: the command takes the
    bag's only topic of the type for a topic left out, and the help says so."""
    default = " (default: the bag's only one)" if only_one_default else ""
    group.add_argument("--bag", metavar="PATH", help="ROS 1 .bag file, ROS 2 bag folder, or its .db3 / .mcap file")
    group.add_argument("--image-topic", metavar="TOPIC", help=f"sensor_msgs/Image or CompressedImage topic{default}")
    group.add_argument("--points-topic", *points_aliases, dest="points_topic", metavar="TOPIC",
                       help=f"sensor_msgs/PointCloud2 topic{default}")
    group.add_argument("--camera-info-topic", metavar="TOPIC",
                       help="sensor_msgs/CameraInfo topic (default: camera_info beside --image-topic)")


def add_rerun_argument(parser: argparse.ArgumentParser, frames: str) -> None:
    """``--rerun [FILE.rrd]`` (:func:`crfdepth.cli.outputs.rerun_recording`); ``frames`` says what the recording
    holds per frame. ``args.recorder``, None until the command opens the recording, is what the code paths log
    their frames into."""
    parser.set_defaults(recorder=None)
    parser.add_argument("--rerun", nargs="?", const="", default=None, metavar="FILE.rrd",
                        help=f"also write a Rerun recording (needs pip install 'crfdepth[viewer]'), one time step "
                             f"per frame: {frames} (entities: crfdepth.pictures.rerun_recording). Its folder must "
                             f"exist; the file appears when the run ends, and not at all when it fails. Without "
                             f"FILE: stream to the Rerun viewer listening on its default port (9876), spawning "
                             f"one if none runs")
