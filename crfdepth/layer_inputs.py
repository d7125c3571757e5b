"""The checks of :func:`crfdepth.layer.crf_refine`'s inputs that are the layer's own, all run before any solve
(the shared ones are in :mod:`crfdepth.checks`); each message names the argument."""

from __future__ import annotations

import torch

from crfdepth.checks import describe
from crfdepth.errors import InputError

__all__ = ["check_anchored", "check_labels", "check_not_empty", "check_projection"]


def check_projection(projection_weight, channels: int, ref: torch.Tensor,
                      ref_features: torch.Tensor) -> torch.Tensor:
    p = projection_weight
    is_1x1 = isinstance(p, torch.Tensor) and p.dim() == 4 and tuple(p.shape[2:]) == (1, 1)
    if not isinstance(p, torch.Tensor) or not (p.dim() == 2 or is_1x1):
        raise InputError(f"projection_weight: expected an (E, C) or (E, C, 1, 1) tensor, got {describe(p)}")
    if p.shape[1] != channels:
        raise InputError(f"features: expected {p.shape[1]} channels, the C of projection_weight (E, C) = "
                         f"{tuple(p.shape[:2])}, got {channels} (features {describe(ref_features)}); give features "
                         f"with C channels or a projection_weight for {channels}")
    if p.dtype != ref.dtype or p.device != ref.device:
        raise InputError(f"projection_weight: expected dtype {ref.dtype} on {ref.device} like depth, "
                         f"got {p.dtype} on {p.device}")
    if not bool(torch.isfinite(p.detach()).all()):
        raise InputError("projection_weight: expected finite values, got NaN/inf")
    return p.reshape(p.shape[0], channels)


def check_not_empty(depth: torch.Tensor) -> None:
    """A batch of at least one frame of at least one pixel (a solve of nothing has no answer to give)."""
    if depth.numel() == 0:
        raise InputError(f"depth: expected a batch of at least 1 frame of at least 1x1 pixels, (B, 1, H, W) with "
                         f"B, H, W >= 1, got shape {tuple(depth.shape)}")


def check_anchored(eps: torch.Tensor, scale: torch.Tensor, confidence: torch.Tensor, sparse, lam) -> None:
    """``prior_weight`` large enough to keep ``A`` numerically positive definite in every frame.

    In a frame with no pixel of confidence > 0 and no LiDAR pixel, ``A = eps I + L(w)`` with
    edge weights up to ``edge_scale``: its smallest eigenvalue is ``eps``, and below the
    machine epsilon of the depth's dtype times ``edge_scale`` it is lost in rounding (the solve
    breaks down into NaN/inf, or stops at a meaningless x). Frames with some data are anchored
    by it and need no floor (docs/design.md section 3).
    """
    floor = torch.finfo(confidence.dtype).eps * float(scale.detach())
    if float(eps.detach()) >= floor:
        return
    anchored = (confidence.detach().flatten(1) > 0).any(dim=1)
    if sparse is not None and float(lam.detach()) > 0:
        anchored |= (sparse.detach().flatten(1) > 0).any(dim=1)
    if bool(anchored.all()):
        return
    frames = torch.nonzero(~anchored).flatten().tolist()
    raise InputError(f"prior_weight: expected at least {floor:.3g} (edge_scale {float(scale.detach()):g} x the "
                     f"machine epsilon of {str(confidence.dtype).replace('torch.', '')}) for frame(s) {frames[:10]} "
                     f"(batch index), which have no pixel with confidence > 0 and no LiDAR pixel: there "
                     f"prior_weight alone anchors the depth and a smaller one makes the system numerically "
                     f"singular; got {float(eps.detach()):g}")


def check_labels(labels, depth: torch.Tensor) -> torch.Tensor:
    b, _, h, w = depth.shape
    if not isinstance(labels, torch.Tensor) or tuple(labels.shape) != (b, h, w) \
            or labels.dtype not in (torch.int64, torch.int32):
        got = describe(labels) + (f" {labels.dtype}" if isinstance(labels, torch.Tensor) else "")
        raise InputError(f"labels: expected a ({b}, {h}, {w}) int64 tensor of segment indices, got {got}")
    if labels.device != depth.device:
        raise InputError(f"labels: expected device {depth.device} like depth, got {labels.device}")
    if labels.numel() and int(labels.min()) < 0:
        raise InputError(f"labels: expected segment indices >= 0, got minimum {int(labels.min())}")
    return labels.long()
