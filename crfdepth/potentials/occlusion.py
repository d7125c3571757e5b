"""See-through LiDAR points: a hard mask and a soft, learnable gate (docs/design.md section 3b).

The KITTI Velodyne sits about 0.27 m behind and 0.08 m above the colour camera, so it sees
background the camera does not: just inside a foreground object's silhouette, a raw scan
projected into the image holds background returns ("see-through" points) among the
foreground ones. KITTI's annotated ground truth has them removed; ``velodyne_raw`` keeps
them, and a CRF that trusts them pulls the foreground towards the background.

**Rule.** For a LiDAR pixel k with depth ``z_k`` let ``m_k`` be the smallest depth in the
``window x window`` square around it (empty pixels ignored; k itself included, so
``m_k <= z_k``), and

    r_k = 1/m_k - 1/z_k   >= 0   (1/m).

k is see-through when ``r_k`` exceeds a threshold. Inverse depth, not metres, because
(i) the parallax that makes see-through points is ``f * b * (1/z_near - 1/z_far)`` pixels
for a LiDAR-camera offset ``b``, so ``f * b * r_k`` is the width in pixels of the band
through which background can leak (``f * b`` ~ 720 px * 0.3 m ~ 216 px m: r = 0.015 is a
3-pixel band, one to two azimuth steps of the scanner); (ii) on any plane ``1/z`` is affine
in pixel coordinates, so a slanted surface changes r only by its inverse-depth gradient
times the window radius: ``1/(f h)`` = 8.4e-4 1/m per row for the road (``h`` = 1.65 m
camera height, at every distance, where z changes 0.76 m per row at 30 m), about
``1/(f d)`` per column for a wall at lateral distance ``d`` (1.4e-3 at 1 m). A metric
threshold cannot be both: "more than 1.5 m deeper" in 5x5 flags road returns behind road
returns on the real scans (1.1% of its flags), 1.0 m in 9x9 removed 21% of the points of
the official frames.

**Defaults**, measured on 40 synthetic street scenes
(:func:`crfdepth.data.synthetic.make_scene`, seeds 0-39, KITTI's mount and a 64-beam
scanner; a return is *hidden* when the camera's ray to it meets a surface more than
0.1 m + 2% in front of it) and on the real raw scans of drive 0060 and the object
frames; never on drive 0001 frame 5, the official validation frame. "Through the CRF"
is crfdepth with the shipped learned weights on the scene's dense depth, the hard mask
applied to its input, RMSE / MAE in mm per image:

- ``window = 5``: the window must reach from a see-through return to a foreground one,
  which in a 64-beam scan lies in the same ring about 2 px away (azimuth step ~0.17
  degrees), or one ring (4-6 px) below at top edges; but every pixel of radius also
  removes legitimate background returns just *outside* each silhouette (with sparse
  samples, inside and just outside look alike). Through the CRF, seeds 20-39 (no mask
  1140 / 199; removing exactly the hidden returns 917 / 164): 3x3 1043 / 183, 5x5
  1008 / 175, 7x7 1026 / 181; 9x9 was 16 mm worse than 5x5 on seeds 0-19 and 11x11
  47 mm. A taller window (9 rows x 5 columns) reaches the ring below: 992 / 179, better
  RMSE but worse MAE for 40% more returns removed on the real scans; not worth a second
  window parameter.
- ``threshold = 0.015`` 1/m: in 5x5 the CRF results for 0.01, 0.015 and 0.02 lie within
  5 mm (1011, 1008, 1013); 0.015 is the smallest value at which no flagged road return
  has a road return as its nearer neighbour on the real scans (0.4% of the flags at
  0.01). It removes 3.1% of the real scans' returns (0.8-6.1% per frame), against 2.5%
  in a virtual camera placed at the LiDAR (no parallax: every flag there is a
  legitimate return next to an edge); on the synthetic scenes it flags 74% of the
  hidden returns (68% of their squared error) and 0.34% of the visible ones.
- No metric or relative component: through the CRF (seeds 0-39) the inverse rule alone
  gives 1007 / 176, "or more than 10% (20%) deeper than the nearest" 1019 / 180
  (1011 / 179), the metric rule "more than 1.5 m deeper" in 5x5 1043 / 185; a metric
  floor ("and more than 0.5 m deeper") changed no result by more than 1 mm (seeds 0-19).
- ``softness = 0.003`` 1/m (threshold / 5): g > 0.9 for r < 0.0086 (planes, range
  noise), g < 0.1 for r > 0.0216; the model learns both through their logarithms.

The window is set for a 64-beam scan at KITTI's resolution (1216x352, f ~ 720 px); for a
sparser scanner or a larger image, scale it with the spacing of the returns.
"""

from __future__ import annotations

import warnings
from typing import NamedTuple

import torch
import torch.nn.functional as F

from crfdepth.checks import check_map, check_number, check_scalar_tensor
from crfdepth.config import DEFAULT_SOFTNESS, DEFAULT_THRESHOLD, DEFAULT_WINDOW
from crfdepth.errors import InputError
from crfdepth.geometry.windows import window_max

__all__ = [
    "DEFAULT_SOFTNESS",
    "DEFAULT_THRESHOLD",
    "DEFAULT_WINDOW",
    "MIN_KEPT_SHARE",
    "GateResult",
    "OcclusionFallbackWarning",
    "gate_or_fallback",
    "occlusion_gate",
    "see_through_mask",
    "see_through_residual",
]

MIN_KEPT_SHARE = 0.1
""":func:`gate_or_fallback` falls back when a frame keeps less than this share of its data
weight. Real scans lose 0.6-6.1% of their returns per frame to the default mask; a frame
keeping under 10% is not an occlusion pattern but a gate gone wrong (e.g. a learned
threshold collapsed)."""


class OcclusionFallbackWarning(UserWarning):
    """A frame's occlusion gate would have removed (nearly) all of its LiDAR evidence."""


class GateResult(NamedTuple):
    """What :func:`gate_or_fallback` returns.

    Attributes:
        gate: (B, 1, H, W) gate values in (0, 1]; all ones in the frames that fell back.
        fell_back: (B,) bool, True where a frame's gate was replaced by ones.
    """

    gate: torch.Tensor
    fell_back: torch.Tensor


def _check_window(window: object) -> int:
    is_int = isinstance(window, int) and not isinstance(window, bool)
    if not is_int or window < 3 or window % 2 == 0:
        got = repr(window) if is_int else f"{type(window).__name__} {window!r}"
        raise InputError(f"window: expected an odd integer >= 3 (pixels), got {got}")
    return window


def _check_sparse(sparse: object) -> torch.Tensor:
    return check_map("sparse", sparse, channels=1, nonneg=True)


def _residual(sparse: torch.Tensor, window: int) -> torch.Tensor:
    """r = 1/m - 1/z at LiDAR pixels, 0 elsewhere; detached; inputs already checked."""
    s = sparse.detach()
    valid = s > 0
    inv = s.reciprocal().nan_to_num_(posinf=0.0)  # 1/z, 0 at empty pixels (1/0 = inf)
    # Largest inverse depth (nearest return) in the window (equal to max_pool2d, O(log window)).
    # Empty pixels hold 0, below any return; the border is ignored; the pixel itself takes
    # part, so r >= 0.
    near = window_max(inv, window)
    return torch.where(valid, near - inv, 0.0)


def see_through_residual(sparse: torch.Tensor, *, window: int = DEFAULT_WINDOW) -> torch.Tensor:
    """Inverse-depth lead ``r = 1/m - 1/z`` of the nearest return around each LiDAR pixel.

    Args:
        sparse: (B, 1, H, W) LiDAR z-depth in metres, 0 = no return. Not modified.
        window: side of the square neighbourhood in pixels, odd, >= 3.

    Returns:
        (B, 1, H, W) ``r >= 0`` in 1/m at LiDAR pixels (``m`` the smallest depth in the
        window, ``z`` the pixel's own), 0 at empty pixels; detached, dtype of ``sparse``.

    Raises:
        InputError: ``sparse`` not a finite, non-negative (B, 1, H, W) floating tensor;
            ``window`` not an odd integer >= 3.
    """
    sparse = _check_sparse(sparse)
    return _residual(sparse, _check_window(window))


def see_through_mask(sparse: torch.Tensor, *, window: int = DEFAULT_WINDOW,
                     threshold: float = DEFAULT_THRESHOLD) -> torch.Tensor:
    """LiDAR pixels judged see-through: ``r > threshold`` (hard rule, not differentiable).

    Args:
        sparse: (B, 1, H, W) LiDAR z-depth in metres, 0 = no return. Not modified.
        window: side of the square neighbourhood in pixels, odd, >= 3 (default 5).
        threshold: inverse-depth lead in 1/m, > 0, a number or a one-element tensor
            (default 0.015): a return is flagged when some return in its window is nearer
            by more than this in ``1/z``.

    Returns:
        (B, 1, H, W) bool, True at flagged LiDAR pixels, False elsewhere (always False at
        empty pixels and at the nearest return of each window).

    Raises:
        InputError: bad ``sparse`` or ``window`` (:func:`see_through_residual`), or a
            ``threshold`` that is not one finite value > 0.
    """
    sparse = _check_sparse(sparse)
    window = _check_window(window)
    t = check_scalar_tensor("threshold", threshold, sparse, positive=True, ref_name="sparse")
    return _residual(sparse, window) > t.detach()


def occlusion_gate(sparse: torch.Tensor, threshold, softness, *,
                   window: int = DEFAULT_WINDOW) -> torch.Tensor:
    """Soft see-through gate ``g in (0, 1]``, differentiable in ``threshold`` and ``softness``.

    ``g = sigmoid((threshold - r) / softness) / sigmoid(threshold / softness)`` with ``r``
    of :func:`see_through_residual`: exactly 1 where ``r = 0`` (nothing nearer in the
    window), decreasing in ``r``, 1/2 near ``r = threshold`` (for ``threshold >>
    softness``) and tending to 0 above it; computed through ``logsigmoid`` so that it
    neither underflows to NaN nor loses gradient for ``threshold / softness`` up to
    hundreds. It is meant to multiply a return's data weight (docs/design.md section 3b).

    Args:
        sparse: (B, 1, H, W) LiDAR z-depth in metres, 0 = no return. Detached: no
            gradient flows to it. Not modified.
        threshold: inverse-depth lead in 1/m, > 0: a number or a one-element tensor
            (e.g. ``log_threshold.exp()``), on the device of ``sparse``; default value
            :data:`DEFAULT_THRESHOLD`.
        softness: transition width in 1/m, > 0, number or one-element tensor; default
            value :data:`DEFAULT_SOFTNESS`.
        window: side of the square neighbourhood in pixels, odd, >= 3.

    Returns:
        (B, 1, H, W) gate in the dtype of ``sparse``: values in (0, 1] at LiDAR pixels
        (a value below the dtype's smallest number, ``(r - threshold) / softness`` beyond
        about 100 in float32, rounds to 0), exactly 1 at empty pixels (so the gate can
        multiply a dense weight map). Carries the autograd graph of ``threshold`` and
        ``softness``.

    Raises:
        InputError: bad ``sparse`` or ``window``; ``threshold`` or ``softness`` not a
            finite value > 0, not one element, or on another device.
    """
    sparse = _check_sparse(sparse)
    window = _check_window(window)
    t = check_scalar_tensor("threshold", threshold, sparse, positive=True, ref_name="sparse")
    s = check_scalar_tensor("softness", softness, sparse, positive=True, ref_name="sparse")
    return _soft_gate(sparse, t, s, window)


def _soft_gate(sparse: torch.Tensor, t: torch.Tensor, s: torch.Tensor, window: int) -> torch.Tensor:
    """:func:`occlusion_gate` of checked arguments."""
    r = _residual(sparse, window).flatten()
    at = torch.nonzero(sparse.detach().flatten() > 0).flatten()  # the returns; 1 elsewhere
    g = torch.exp(F.logsigmoid((t - r[at]) / s) - F.logsigmoid(t / s))
    return torch.ones_like(r).index_put((at,), g).view_as(sparse)


def gate_or_fallback(sparse: torch.Tensor, threshold, softness, *, window: int = DEFAULT_WINDOW,
                     weight: torch.Tensor | None = None,
                     min_kept_share: float = MIN_KEPT_SHARE) -> GateResult:
    """:func:`occlusion_gate`, replaced by ones (with a warning) in frames it would empty.

    Per frame, ``kept = sum(weight * gate)`` and ``full = sum(weight)`` over its LiDAR
    pixels; where ``kept < min_kept_share * full`` the frame's gate becomes all ones and an
    :class:`OcclusionFallbackWarning` names the frame's batch index and both sums. The
    default gate cannot empty a frame (the nearest return of every window keeps g = 1),
    but a learned threshold or a pathological scan can leave all but a handful of
    returns; then the raw data are a better bet than a solve resting on a few points.
    Frames without any return keep their gate (all ones) without a warning.

    Args:
        sparse, threshold, softness, window: as for :func:`occlusion_gate`.
        weight: optional (B, 1, H, W) non-negative data weights of the returns (e.g. the
            model's confidence map), same shape, dtype and device as ``sparse``; None =
            1 per return (the sums count returns).
        min_kept_share: the share in (0, 1) below which a frame falls back
            (default :data:`MIN_KEPT_SHARE`).

    Returns:
        :class:`GateResult` ``(gate, fell_back)``.

    Raises:
        InputError: as :func:`occlusion_gate`; a bad ``weight`` or ``min_kept_share``.
    """
    gate = occlusion_gate(sparse, threshold, softness, window=window)
    min_kept_share = float(check_number("min_kept_share", min_kept_share, low=0.0, high=1.0))
    if weight is not None:
        weight = check_map("weight", weight, ref=sparse, channels=1, ref_name="sparse", nonneg=True)
    return _with_fallback(sparse, gate, weight, min_kept_share)


def trusted_gate(sparse: torch.Tensor, threshold, softness, window: int) -> GateResult:
    """:func:`gate_or_fallback` of arguments the caller has checked (the model's: its checked input and its
    own positive parameters), without checking them again (two passes over the map less per frame)."""
    t, s = (torch.as_tensor(v, dtype=sparse.dtype, device=sparse.device) for v in (threshold, softness))
    return _with_fallback(sparse, _soft_gate(sparse, t, s, window), None, MIN_KEPT_SHARE)


def _with_fallback(sparse: torch.Tensor, gate: torch.Tensor, weight: torch.Tensor | None,
                   min_kept_share: float) -> GateResult:
    valid = (sparse.detach() > 0).to(gate.dtype)
    w = valid if weight is None else weight.detach() * valid
    full = w.sum(dim=(1, 2, 3))
    kept = (w * gate.detach()).sum(dim=(1, 2, 3))
    fell = (full > 0) & (kept < min_kept_share * full)
    if bool(fell.any()):
        for b in torch.nonzero(fell).flatten().tolist():
            warnings.warn(
                f"occlusion gate: frame {b} would keep {float(kept[b]):.4g} of {float(full[b]):.4g} data weight "
                f"({float(kept[b] / full[b]):.1%} < min_kept_share {min_kept_share:g}, "
                f"{int(valid[b].sum())} returns); using gate 1 for this frame",
                OcclusionFallbackWarning, stacklevel=3)
        gate = torch.where(fell.view(-1, 1, 1, 1), torch.ones_like(gate), gate)
    return GateResult(gate, fell)
