"""The argparse types of the commands' options, and what a command reports as bad input.

:func:`int_at_least` / :func:`fraction` / :func:`positive_number` refuse a value with a
message naming what was expected; argparse prefixes it with the option.
"""

from __future__ import annotations

import argparse
import math

import numpy as np

from crfdepth.errors import InputError

__all__ = ["BAD_INPUT", "fraction", "int_at_least", "positive_number", "vis_range_type"]

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
