"""A frame through :mod:`crfdepth.api` for a command: errors retold in the user's flags.

- :func:`frame_errors` / :func:`flag_names`: one frame through
  :func:`crfdepth.api.complete_depth`, errors under the user's flags (``complete``'s
  one-frame, point-cloud and bag modes);
- :func:`cli_error`: an error of the library in the command line's words;
- :func:`cli_advice`: the fix a memory refusal advises on the command line, for one frame or (given to
  :mod:`crfdepth.runs` as ``memory_advice``) a batch of the folder modes and ``evaluate``.
"""

from __future__ import annotations

import argparse
import contextlib
import sys
from collections.abc import Iterator

import torch

from crfdepth.cli.progress import FrameProgress
from crfdepth.errors import InputError
from crfdepth.inputs import InvertedTransform
from crfdepth.memory import MemoryRefusal
from crfdepth.model import CRFDepth
from crfdepth.plausibility import ImplausibleDepth
from crfdepth.runs.batches import flag_names

__all__ = ["cli_advice", "cli_error", "flag_names", "frame_errors"]

# The fix of a T_cam_lidar that looks inverted, in the command line's words (crfdepth.inputs.InvertedTransform).
_TRANSFORM_FIX = "invert it in the calibration file, or give --trust-transform to use it as given"


def cli_error(exc: InputError, flags: dict[str, str]) -> InputError:
    """``exc`` in the command line's words: named by the user's ``flags`` (:func:`flag_names`), and a transform that
    looks inverted with ``--trust-transform`` as its fix."""
    if isinstance(exc, InvertedTransform):
        exc = exc.retold(_TRANSFORM_FIX)
    return flag_names(exc, flags)


def cli_advice(device: str, batch: int | None = None) -> str:
    """The likely fix of a memory refusal in the CLI, whose ``--device`` is ``device``: of one frame, or
    (``batch`` given) of a batch of the folder modes."""
    other = "--device cuda" if device == "cpu" else "--device cpu"
    if batch is None:
        return f"use a smaller image or {other}"
    return f"use smaller images{', --batch-size 1' if batch > 1 else ''} or {other}"


@contextlib.contextmanager
def frame_errors(args: argparse.Namespace, model, size: tuple[int, int], where: dict[str, str],
                 sparse_units: str | None = None) -> Iterator[None]:
    """Around one frame's :func:`crfdepth.api.complete_depth` (one-frame, point-cloud and bag modes; folder mode
    calls :func:`crfdepth.api.complete_checked`): its errors name ``where``'s flags, and a sparse map refused as
    not metres gets the hints of the ``--sparse-units`` it was read in.

    A frame too large for the memory (refused up front, or an allocator failure in the forward) is an
    InputError naming the image's flag with the CLI's fix. Outside the bag mode and without ``--quiet``, a
    frame of ``size`` (height, width) expected to take or taking more than a few seconds gets a status line of
    the model's stages on stderr when it is a terminal or with ``--verbose`` (:mod:`crfdepth.cli.progress`).
    """
    bag = getattr(args, "bag", None) is not None
    show = not getattr(args, "quiet", False) and not bag and (sys.stderr.isatty() or getattr(args, "verbose", False))
    progress = FrameProgress(*size, torch.device(args.device).type, enabled=show)
    hook = model.progress if isinstance(model, CRFDepth) else None
    if isinstance(model, CRFDepth) and show:
        model.progress = progress.stage
    try:
        with progress:
            yield
    except MemoryRefusal as exc:
        raise exc.retold(where.get("image", "image"), cli_advice(args.device)) from None
    except ImplausibleDepth as exc:
        if sparse_units is None:
            raise flag_names(exc, where) from None
        raise exc.retold(where["sparse"], sparse_units) from None
    except InputError as exc:
        raise cli_error(exc, where) from None
    finally:
        if isinstance(model, CRFDepth):
            model.progress = hook
