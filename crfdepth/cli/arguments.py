"""The argparse types of the commands' options, options that two commands share, and what a
command reports as bad input.

:func:`int_at_least` / :func:`fraction` / :func:`positive_number` refuse a value with a
message naming what was expected; argparse prefixes it with the option.
"""

from __future__ import annotations

import argparse
import math

import numpy as np

from crfdepth.errors import BAD_INPUT  # what crfdepth.cli.main reports as bad input (one line, exit status 2)

__all__ = ["BAD_INPUT", "MAX_COUNT", "OneLineParser", "MAX_DEVICES", "MAX_RINGS", "MAX_SEED", "MAX_WORKERS", "STRATEGIES", "VisRange",
           "add_batch_arguments", "add_rerun_argument", "add_topic_arguments", "fraction", "int_at_least",
           "positive_number", "seed_type", "vis_range_type"]

class OneLineParser(argparse.ArgumentParser):
    """An ArgumentParser whose usage errors are one line naming the option, exit status 2:
    ``<prog>: error: --strategy: expected one of 'auto', 'spawn', 'ddp', got 'fsdp'``, like the messages of
    :class:`~crfdepth.errors.InputError`. A value outside an option's choices is told in these words, not
    argparse's (whose format changes between Python releases); argparse's ``argument`` prefix is dropped.
    Sub-parsers made from one are of its class too. The ``crfdepth`` commands and the benchmark scripts use it.
    """

    def error(self, message: str):
        self.exit(2, f"{self.prog}: error: {message.removeprefix('argument ')}\n")

    def _check_value(self, action: argparse.Action, value: object) -> None:
        if action.choices is not None and value not in action.choices:
            raise argparse.ArgumentError(action, f"expected one of {', '.join(map(repr, action.choices))}, "
                                                 f"got {value!r}")


MAX_COUNT = 2**31 - 1
"""Largest value of an integer option without a bound of its own (a count of frames, a window): the largest C
``int``, so that no option reaches a library as a number it cannot hold (a 20-digit ``--keep-every-ring`` was an
``OverflowError`` traceback)."""
MAX_SEED = 2**32 - 1
"""Largest ``--seed``: what every seeding API the commands reach takes (``numpy.random.seed`` stops at
2**32 - 1; ``numpy.random.default_rng`` and ``torch.Generator.manual_seed`` take more)."""
MAX_RINGS = 128
"""Largest ``--keep-every-ring``: the most laser rings a LiDAR has (128-beam sensors; KITTI's HDL-64E has 64)."""


def int_at_least(low: int, high: int | None = None, meaning: str | None = None):
    """An argparse ``type`` accepting integers in [``low``, ``high``] (``high`` None: :data:`MAX_COUNT`);
    ``meaning``, when given, says in the message what the number is. Refused: ``--name: expected an integer in
    [lo, hi] (meaning), got 'value'``."""
    high = MAX_COUNT if high is None else high
    note = f" ({meaning})" if meaning else ""

    def parse(text: str) -> int:
        try:
            value = int(text)
        except ValueError:
            value = low - 1
        if not low <= value <= high:
            raise argparse.ArgumentTypeError(f"expected an integer in [{low}, {high}]{note}, got {text!r}")
        return value

    return parse


def seed_type(meaning: str | None = None):
    """An argparse ``type`` for a ``--seed``: an integer in [0, :data:`MAX_SEED`]."""
    return int_at_least(0, MAX_SEED, meaning)


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


# More reading processes than this cannot keep up better with a solve that takes seconds per
# frame; the cap turns a typo (--workers 400) into a usage error instead of 400 processes.
MAX_WORKERS = 64
# --devices: processes on one machine (GPUs, or CPU processes sharing the cores); the same cap, for the same reason.
MAX_DEVICES = 64
# --batch-size: frames per model call; more than this holds no machine's memory at KITTI's frame size.
MAX_BATCH = 1024
# How --devices processes are started (crfdepth.runs.ranks.joined_group), named after Lightning's strategies.
STRATEGIES = ("auto", "spawn", "ddp")


def add_batch_arguments(group: argparse._ActionsContainer) -> None:
    """``--batch-size B`` and ``--workers N`` (read by :func:`crfdepth.runs.batches.frame_batches`), and ``--devices N``, ``--num-nodes
    M`` and ``--strategy`` (:mod:`crfdepth.runs.processes`, :mod:`crfdepth.runs.ranks`, :mod:`crfdepth.runs.launch`),
    shared by ``complete --input-dir`` / ``--input-list`` and ``evaluate``."""
    group.add_argument("--batch-size", type=int_at_least(1, MAX_BATCH), default=1, metavar="B",
                       help=f"frames per model call, 1 to {MAX_BATCH} (default 1, the fastest on CPU as measured; "
                            "batches are meant for --device cuda); consecutive frames of the same size go together, a size "
                            "change starts a new batch. Each frame's solve stops when it has converged, so "
                            "depths differ from batch 1 by the solver tolerance only (measured: at most 1/256 m, "
                            "one unit of a depth PNG)")
    group.add_argument("--workers", type=int_at_least(0, MAX_WORKERS), default=0, metavar="N",
                       help=f"processes that read and check frames ahead of the model (DataLoader "
                            f"num_workers, 0 to {MAX_WORKERS}; default 0: this process, enough for local KITTI "
                            f"frames, which read in about 20 ms; more help when reading is slow, e.g. from "
                            f"network storage)")
    group.add_argument("--devices", type=int_at_least(1, MAX_DEVICES), default=1, metavar="N",
                       help=f"N processes, one per device, 1 to {MAX_DEVICES} (--device cuda: GPUs 0..N-1; cpu: N "
                            "processes sharing the cores), the batches dealt to them in turn: the outputs are one process's (depth within "
                            "one PNG code: the threads' summation order)")
    group.add_argument("--num-nodes", type=int_at_least(1), default=1, metavar="M",
                       help="M machines of N --devices each: start the same command on every node with torchrun "
                            "--nnodes M --nproc-per-node N (or srun under torchrun); rank 0 checks, plans and "
                            "reports, every rank does its dealt batches (the output folder shared)")
    group.add_argument("--strategy", choices=STRATEGIES, default="auto",
                       help="how the --devices processes are started, named after Lightning's strategies: auto "
                            "(default) = a rank of the launcher's group when started by torchrun or srun, else "
                            "spawn for --devices N > 1; spawn = N local processes started by torch.multiprocessing "
                            "(one machine, no launcher); ddp = one rank per device in a torch.distributed group "
                            "(gloo): under torchrun it joins the launcher's group, and without one it starts the N "
                            "ranks on this machine itself with torch's elastic launcher (the same command in each; "
                            "--devices 1: one process)")
