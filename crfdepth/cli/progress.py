"""A status line on stderr for a long single frame: the model's stages as they start.

``crfdepth complete`` completes one large frame in tens of seconds (a 6000x4000 frame: 46 s
on 2 CPU cores). :class:`FrameProgress` is hooked into the model
(:attr:`crfdepth.model.CRFDepth.progress`, called at each stage's start) and writes
``complete: 6000x4000 frame: superpixels (SLIC), 3.2 s`` on stderr once the frame is expected
to take, or has taken, more than :data:`SHOW_AFTER_S` seconds. On a terminal the line is
rewritten in place and ended when the frame is done; with ``--verbose`` and no terminal
(a log file) each stage is a line of its own. Nothing is written with ``--quiet``, in the
bag mode (which has its own per-frame progress bar), or when stderr is neither a terminal
nor asked for with ``--verbose``. A frame below the threshold pays one ``if`` per stage.

:class:`FrameBars` is the progress bar of a run over many frames (:mod:`crfdepth.runs.progress`).
"""

from __future__ import annotations

import sys
import time
from typing import TextIO

from tqdm import tqdm

__all__ = ["FrameBars", "FrameProgress", "REPEAT_AFTER_S", "SECONDS_PER_PIXEL", "SHOW_AFTER_S", "STAGE_NAMES"]

SHOW_AFTER_S = 2.0
"""Seconds (expected or elapsed) from which a frame's stages are shown."""
REPEAT_AFTER_S = 1.0
"""A stage already shown (the model runs some once per frame or per round) is shown again only this many
seconds after the last line."""
SECONDS_PER_PIXEL = {"cpu": 1.0e-6}
"""Rough forward time per pixel by device type, for the expectation (2 CPU threads: 0.6-1.9 us per pixel at
4000x3000-6000x4000, docs/design.md section 10); other devices start showing from the elapsed time only."""
STAGE_NAMES = {"fill": "nearest fill", "slic": "superpixels (SLIC)", "graph": "superpixel graph",
               "normals": "LiDAR normals", "potentials": "potentials", "solve": "solve", "painting": "painting",
               "refine": "pixel refinement", "uncertainty": "standard deviation"}
"""What the line calls the model's stages (the keys of ``CRFOutput.timings``)."""


class FrameProgress:
    """The status line of one frame of ``height`` x ``width`` pixels on ``device_type``.

    Use as a context manager around the model call, with :meth:`stage` as the model's
    ``progress`` hook; ``enabled`` False writes nothing.
    """

    def __init__(self, height: int, width: int, device_type: str, *, enabled: bool, label: str = "complete",
                 stream: TextIO | None = None) -> None:
        self.stream = stream if stream is not None else sys.stderr
        self.enabled = enabled
        self.terminal = bool(getattr(self.stream, "isatty", lambda: False)())
        self.prefix = f"{label}: {width}x{height} frame"
        self.expected = height * width * SECONDS_PER_PIXEL.get(device_type, 0.0)
        self.start = time.perf_counter()
        self.shown = False
        self.seen: set[str] = set()
        self.last = 0.0  # elapsed seconds at the last line
        self.width = 0  # characters of the line on a terminal

    def stage(self, name: str) -> None:
        """The model's hook: a stage named ``name`` starts."""
        if not self.enabled:
            return
        elapsed = time.perf_counter() - self.start
        if not self.shown and max(self.expected, elapsed) < SHOW_AFTER_S:
            return
        if name in self.seen and elapsed - self.last < REPEAT_AFTER_S:
            return  # a stage met again (per frame, per round) within the second: no new line
        self.seen.add(name)
        self.last = elapsed
        self._write(f"{self.prefix}: {STAGE_NAMES.get(name, name)}, {elapsed:.1f} s")

    def _write(self, line: str) -> None:
        if self.terminal:
            padding = " " * max(self.width - len(line), 0)
            self.stream.write(f"\r{line}{padding}")
            self.width = len(line)
        else:
            self.stream.write(line + "\n")
        self.stream.flush()
        self.shown = True

    def __enter__(self) -> "FrameProgress":
        self.start = time.perf_counter()
        return self

    def __exit__(self, kind, value, traceback) -> None:
        if self.shown:
            elapsed = time.perf_counter() - self.start
            self._write(f"{self.prefix}: {'done' if kind is None else 'stopped'}, {elapsed:.1f} s")
            if self.terminal:
                self.stream.write("\n")
                self.stream.flush()


class FrameBars:
    """The progress of a run over many frames (``check``, ``complete``, ``evaluate``): a tqdm bar of frames on
    stderr when it is a terminal (the run asks none with ``--quiet``); picklable, as ``--devices`` processes
    receive it with the run."""

    def __call__(self, desc: str, total: int) -> tqdm:
        return tqdm(total=total, unit="frame", desc=desc, disable=not sys.stderr.isatty())
