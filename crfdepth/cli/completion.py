"""A frame or a batch through :mod:`crfdepth.api` for a command: errors retold in the user's flags.

- :func:`frame_errors` / :func:`flag_names`: one frame through
  :func:`crfdepth.api.complete_depth`, errors under the user's flags (``complete``'s
  one-frame, point-cloud and bag modes);
- :func:`check_sample` / :func:`complete_batch_with_cli_advice`: a batch of checked frames
  through :func:`crfdepth.api.complete_checked` (``complete --input-dir`` and ``evaluate``);
  a frame too large for the memory is refused with the CLI's options as the fix.
"""

from __future__ import annotations

import argparse
import contextlib
import sys
from collections.abc import Iterator

import torch

from crfdepth import api
from crfdepth.cli.progress import FrameProgress
from crfdepth.data.sample import Batch, Sample
from crfdepth.errors import InputError
from crfdepth.memory import MemoryRefusal, cli_advice
from crfdepth.model import CRFDepth
from crfdepth.plausibility import ImplausibleDepth

__all__ = ["check_sample", "complete_batch_with_cli_advice", "flag_names", "frame_errors"]


def flag_names(exc: InputError, flags: dict[str, str]) -> InputError:
    """The API's message with its argument name (``K``, ``sparse`` ...) replaced by the user's flag."""
    text = str(exc)
    head, sep, rest = text.partition(":")
    if sep and head.strip() in flags:
        return InputError(f"{flags[head.strip()]}:{rest}")
    if "*" in flags:  # a message about the inputs together (e.g. no point lands in the image)
        return InputError(f"{flags['*']}: {text}")
    return exc


@contextlib.contextmanager
def frame_errors(args: argparse.Namespace, model, size: tuple[int, int], where: dict[str, str],
                 sparse_units: str | None = None) -> Iterator[None]:
    """Around one frame's :func:`crfdepth.api.complete_depth` (one-frame, point-cloud and bag modes; folder mode
    calls :func:`complete_batch_with_cli_advice`): its errors name ``where``'s flags, and a sparse map refused as
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
        raise flag_names(exc, where) from None
    finally:
        if isinstance(model, CRFDepth):
            model.progress = hook


def check_sample(sample: Sample) -> None:
    """Refuse a frame that :func:`crfdepth.api.complete_depth` would refuse, with its checks and
    messages (:func:`crfdepth.api.check_frame`; names ``image``, ``sparse``, ``K``)."""
    api.check_frame(sample.image, sample.sparse, sample.K)


def complete_batch_with_cli_advice(model: CRFDepth, batch: Batch, return_std: bool
                                   ) -> tuple[torch.Tensor, torch.Tensor | None]:
    """:func:`crfdepth.api.complete_checked` of a batch of frames checked by :func:`check_sample` (so not
    checked again), on the model's device: (B, H, W) float32 depth and std (None without ``return_std``),
    metres. A memory refusal advises the CLI's options."""
    device = next(model.parameters()).device
    try:
        return api.complete_checked(model, batch.image, batch.sparse, batch.K, return_std=return_std)
    except MemoryRefusal as exc:
        raise exc.retold("image", cli_advice(device.type, len(batch))) from None
