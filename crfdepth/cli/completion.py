"""A frame or a batch through :mod:`crfdepth.api` for a command: errors retold in the user's flags.

- :func:`complete_frame` / :func:`flag_names`: one frame through
  :func:`crfdepth.api.complete_depth`, errors under the user's flags (``complete``'s
  one-frame, point-cloud and bag modes);
- :func:`check_sample` / :func:`complete_batch_with_cli_advice`: a batch of checked frames
  through :func:`crfdepth.api.complete_batch` (``complete --input-dir`` and ``evaluate``);
  a frame too large for the memory is refused with the CLI's options as the fix.
"""

from __future__ import annotations

import argparse
import sys

import numpy as np
import torch

from crfdepth import api
from crfdepth.cli.progress import FrameProgress
from crfdepth.data.sample import Batch, Sample
from crfdepth.errors import InputError
from crfdepth.memory import MemoryRefusal, cli_advice
from crfdepth.model import CRFDepth

__all__ = ["check_sample", "complete_batch_with_cli_advice", "complete_frame", "flag_names"]


def flag_names(exc: InputError, flags: dict[str, str]) -> InputError:
    """The API's message with its argument name (``K``, ``sparse`` ...) replaced by the user's flag."""
    text = str(exc)
    head, sep, rest = text.partition(":")
    if sep and head.strip() in flags:
        return InputError(f"{flags[head.strip()]}:{rest}")
    if "*" in flags:  # a message about the inputs together (e.g. no point lands in the image)
        return InputError(f"{flags['*']}: {text}")
    return exc


def complete_frame(args: argparse.Namespace, model, image, where: dict[str, str], with_std: bool, **inputs):
    """One frame through :func:`crfdepth.api.complete_depth` (one-frame, point-cloud and bag modes; folder mode
    calls its batched form, :func:`complete_batch_with_cli_advice`); errors name ``where``'s flags. Returns
    float64 numpy (H, W) depth and std (None without ``with_std``), metres.

    A frame too large for the memory (refused up front, or an allocator failure in the forward) is an
    InputError naming the image's flag with the CLI's fix. Outside the bag mode and without ``--quiet``, a
    frame expected to take or taking more than a few seconds gets a status line of the model's stages on
    stderr when it is a terminal or with ``--verbose`` (:mod:`crfdepth.cli.progress`).
    """
    bag = getattr(args, "bag", None) is not None
    show = not getattr(args, "quiet", False) and not bag and (sys.stderr.isatty() or getattr(args, "verbose", False))
    height, width = np.shape(image)[:2]
    progress = FrameProgress(height, width, torch.device(args.device).type, enabled=show)
    hook = model.progress if isinstance(model, CRFDepth) else None
    if isinstance(model, CRFDepth) and show:
        model.progress = progress.stage
    try:
        with progress:
            depth, std = api.complete_depth(image, model=model, device=args.device, return_std=with_std,
                                            trust_transform=args.trust_transform, **inputs)
    except MemoryRefusal as exc:
        raise exc.retold(where.get("image", "image"), cli_advice(args.device)) from None
    except InputError as exc:
        raise flag_names(exc, where) from None
    finally:
        if isinstance(model, CRFDepth):
            model.progress = hook
    as_numpy = (lambda a: a.double().cpu().numpy()) if isinstance(depth, torch.Tensor) else \
        (lambda a: a.astype(np.float64))
    return as_numpy(depth), (None if std is None else as_numpy(std))


def check_sample(sample: Sample) -> None:
    """Refuse a frame that :func:`crfdepth.api.complete_depth` would refuse, with its checks and
    messages (:func:`crfdepth.api.check_frame`; names ``image``, ``sparse``, ``K``)."""
    api.check_frame(sample.image, sample.sparse, sample.K)


def complete_batch_with_cli_advice(model: CRFDepth, batch: Batch, return_std: bool
                                   ) -> tuple[torch.Tensor, torch.Tensor | None]:
    """:func:`crfdepth.api.complete_batch` of a batch of frames checked by :func:`check_sample`, on the
    model's device: (B, H, W) float32 depth and std (None without ``return_std``), metres. A memory refusal
    advises the CLI's options."""
    device = next(model.parameters()).device
    try:
        return api.complete_batch(batch.image, batch.sparse, batch.K, model=model, device=device,
                                  return_std=return_std)
    except MemoryRefusal as exc:
        raise exc.retold("image", cli_advice(device.type, len(batch))) from None
