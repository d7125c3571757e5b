"""Whether ``K`` is a plausible pinhole matrix of an image: one check wherever a K meets an image (file
readers, the API, ``CRFDepth.forward``), with messages in the form of :mod:`crfdepth.checks`:
``<name>: expected <what>, got <what was received>`` (docs/design.md sections 1 and 8).
"""

from __future__ import annotations

import math
import warnings

import numpy as np
import torch

from crfdepth.checks import as_matrix, to_numpy
from crfdepth.errors import InputError
from crfdepth.plausibility import PlausibilityWarning

__all__ = ["INTRINSICS_TOLERANCE", "IntrinsicsWarning", "OTHER_SIZE_AGREEMENT", "OTHER_SIZE_CENTRE", "MAX_FOV_DEG", "MAX_INTRINSICS_CONDITION", "MAX_OFF_AXIS_DEG", "MAX_SKEW_RATIO",
           "MIN_FOV_DEG", "PRINCIPAL_POINT_MARGIN", "check_batch_intrinsics", "check_intrinsics"]

# Field of view of K over the image, degrees (check_intrinsics): a pinhole image cannot reach 180
# degrees, and rectified fisheye images are cut well below 170; the narrowest telephoto lenses
# on a camera sensor still see about 1 degree.
MAX_FOV_DEG = 170.0
MIN_FOV_DEG = 1.0

# Plausible pinhole K (check_intrinsics). A real K is upper triangular with K[2][2] = 1: its zeros and
# its 1 are exact, so only a computed K's rounding is allowed for (absolute, and K[1][0] relative to fy).
INTRINSICS_TOLERANCE = 1e-6
# Largest skew |K[0][1]| as a fraction of fx: real sensors have square pixel grids (s = 0, or
# below 1e-3 fx from a calibration that fits it); 0.1 fx (a 6 degree shear) is no lens's.
MAX_SKEW_RATIO = 0.1
# Largest condition number of K: about 1e3 for KITTI and 1e5 for a 100-megapixel telephoto;
# beyond 1e10 K is numerically singular (focal lengths and principal point in different units).
MAX_INTRINSICS_CONDITION = 1e10
# How far outside the image the principal point may lie, as a fraction of its width / height on
# each side: -0.5 W <= cx <= 1.5 W, -0.5 H <= cy <= 1.5 H (the image extended by half its size).
PRINCIPAL_POINT_MARGIN = 0.5
# With crop=True (the image may be a crop of the one K was calibrated for: CRFDepth.forward, training crops)
# the principal point may lie anywhere; instead every pixel must see a ray within this angle of the optical
# axis, since a pinhole image holds no ray at 90 degrees or beyond (a KITTI crop reaches at most 41 degrees).
MAX_OFF_AXIS_DEG = 85.0
# Without crop, warn (IntrinsicsWarning) when the principal point lies outside the image, or when cx / W and cy / H
# are both below 0.35 or both above 0.65 and within 1.5x of each other: the K of a smaller or larger image used on
# a resized one (a 2x upscale puts them at about 0.25). Measured cx / W, cy / H: shared KITTI frames 0.485-0.494,
# 0.461-0.488, their depth-selection crops 0.491, 0.426; NYU v2 0.509-0.510, 0.494-0.529; synthetic street and
# docs/example 0.491, 0.426.
OTHER_SIZE_CENTRE = (0.35, 0.65)
OTHER_SIZE_AGREEMENT = 1.5


class IntrinsicsWarning(PlausibilityWarning):
    """A ``K`` that passes :func:`check_intrinsics` but looks like the intrinsics of another image size."""


def check_intrinsics(K: object, what: str = "K", image_size: tuple[int, int] | None = None,
                     crop: bool = False) -> np.ndarray:
    """(3, 3) float64 copy of ``K`` after checking it is a plausible pinhole matrix of the image.

    Accepts a 3x3 nested list, array or tensor, or 9 numbers (row-major). Requires, in this order:

    - finite numbers;
    - focal lengths ``fx = K[0,0] > 0`` and ``fy = K[1,1] > 0``;
    - last row 0 0 1 and ``K[1,0] = 0`` (upper triangular; within ``INTRINSICS_TOLERANCE`` = 1e-6,
      ``K[1,0]`` relative to fy): a transposed K or a projection matrix's other rows fail here;
    - a skew ``|K[0,1]| <= MAX_SKEW_RATIO * fx`` (0.1 fx);
    - non-singular: condition number at most ``MAX_INTRINSICS_CONDITION`` (1e10);

    and, when ``image_size`` = (height, width) in pixels is given:

    - the principal point within half an image of the image (``PRINCIPAL_POINT_MARGIN``:
      ``-W/2 <= cx <= 1.5 W``, same for cy): further out almost always means K belongs to
      another resolution or has cx and cy swapped (docs/design.md section 1);
    - (without ``crop``) a principal point inside the image and, when it is off-centre, not off-centre by the
      same factor in both axes: else an :class:`IntrinsicsWarning` (not an error: a crop can do it) saying which
      image size K looks made for (the K of a 1242x375 image used on its 2x upscale);
    - a field of view (the angle between the rays through the image's opposite edges,
      horizontal or vertical, whichever is wider) in (``MIN_FOV_DEG``, ``MAX_FOV_DEG``) =
      (1, 170) degrees. A pinhole image approaches 180 degrees only as its edges go to
      infinity; fisheye cameras rectified to a pinhole image are cut to about 90-150 degrees
      (the stretched borders are useless), so 170 admits every real wide-angle or rectified
      fisheye camera while refusing fx = 4 px on a KITTI frame (179 degrees); 1 degree admits
      long telephoto lenses (a 1000 mm lens on a 36 mm sensor: 2 degrees) while refusing K of
      a full image applied to a few-pixel crop.

    With ``crop=True`` the image may be a crop of the one K was calibrated for (``CRFDepth.forward``, where
    training crops arrive): the principal point may then lie anywhere, and instead every pixel must lie
    within ``MAX_OFF_AXIS_DEG`` (85) degrees of the optical axis.

    Apply it wherever a K meets an image. ``what`` is the user's name of K (``K``,
    ``--intrinsics``, ``K (rig.yaml)``). Messages quote at most a short prefix of a value
    that is not a matrix of numbers, never its whole repr.
    """
    if isinstance(K, torch.Tensor):
        K = to_numpy(K)  # float16 / bfloat16 as float32
    try:
        K = np.array(K, dtype=np.float64)
    except (TypeError, ValueError, OverflowError):
        import reprlib

        short = reprlib.Repr()
        short.maxlevel, short.maxlist, short.maxtuple, short.maxdict = 2, 4, 4, 4
        short.maxstring = short.maxother = short.maxlong = 40
        try:
            got = short.repr(K)
        except Exception:  # a repr that fails (an int of 100,000 digits): the type alone
            got = type(K).__name__
        raise InputError(f"{what}: expected a 3x3 matrix of numbers, got {got}") from None
    K = as_matrix(K, (3, 3), what, allow_flat=True)
    fx, fy, cx, cy, skew = K[0, 0], K[1, 1], K[0, 2], K[1, 2], K[0, 1]
    if fx <= 0 or fy <= 0:
        raise InputError(f"{what}: expected focal lengths fx = K[0][0] > 0 and fy = K[1][1] > 0 (pixels), got "
                         f"fx={fx:g}, fy={fy:g}")
    tol = INTRINSICS_TOLERANCE
    if abs(K[2, 0]) > tol or abs(K[2, 1]) > tol or abs(K[2, 2] - 1.0) > tol:
        hint = (": K looks transposed (cx and cy belong in the last column)"
                if cx == 0 and cy == 0 and K[2, 2] == 1 else "")
        raise InputError(f"{what}: expected the last row of K to be 0 0 1, got "
                         f"{' '.join(f'{v:g}' for v in K[2])} (tolerance {tol:g}){hint}")
    if abs(K[1, 0]) > tol * fy:
        raise InputError(f"{what}: expected an upper-triangular K, K[1][0] = 0 (within {tol:g} fy), got "
                         f"K[1][0]={K[1, 0]:g}: K is mistyped, or a rotation is mixed into it")
    if abs(skew) > MAX_SKEW_RATIO * fx:
        raise InputError(f"{what}: expected a skew |K[0][1]| <= {MAX_SKEW_RATIO:g} fx = {MAX_SKEW_RATIO * fx:g} px "
                         f"(pixel grids are rectangular: 0 or nearly), got K[0][1]={skew:g} ({skew / fx:.3g} fx): "
                         f"K is mistyped, or a rotation is mixed into it")
    condition = float(np.linalg.cond(K))
    if not condition <= MAX_INTRINSICS_CONDITION:
        raise InputError(f"{what}: expected a non-singular K (condition number <= {MAX_INTRINSICS_CONDITION:g}), got "
                         f"condition number {condition:.3g} (fx={fx:g}, fy={fy:g}, cx={cx:g}, cy={cy:g}): focal "
                         f"lengths and principal point in different units?")
    if image_size is not None:
        height, width = image_size
        low, high = -PRINCIPAL_POINT_MARGIN, 1.0 + PRINCIPAL_POINT_MARGIN
        if not crop and not (low * width <= cx <= high * width and low * height <= cy <= high * height):
            raise InputError(f"{what}: expected the principal point of the {width}x{height} (WxH) image within "
                             f"half an image of it (cx in [{low * width:g}, {high * width:g}], cy in "
                             f"[{low * height:g}, {high * height:g}] px), got (cx, cy) = ({cx:g}, {cy:g}), far "
                             f"outside: K probably belongs to another image size (scale K with the image after a "
                             f"resize or crop) or cx and cy are swapped")
        # Field of view: the angle between the rays of the image's two edges, cx and cy anywhere.
        fov_x = math.degrees(math.atan((width - cx) / fx) + math.atan(cx / fx))
        fov_y = math.degrees(math.atan((height - cy) / fy) + math.atan(cy / fy))
        if not crop:
            _warn_other_size(what, cx, cy, width, height, fov_x, fov_y)
        if max(fov_x, fov_y) >= MAX_FOV_DEG:
            raise InputError(f"{what}: expected a field of view below {MAX_FOV_DEG:g} degrees over the {width}x{height} "
                             f"(WxH) image, got {fov_x:.1f} x {fov_y:.1f} degrees (fx={fx:g}, fy={fy:g} "
                             f"px): the focal lengths are too short for this image; K is probably for a "
                             f"smaller image, in other units (mm instead of pixels) or the focal length is mistyped")
        if max(fov_x, fov_y) <= MIN_FOV_DEG:
            raise InputError(f"{what}: expected a field of view above {MIN_FOV_DEG:g} degree over the {width}x{height} "
                             f"(WxH) image, got {fov_x:.3g} x {fov_y:.3g} degrees (fx={fx:g}, fy={fy:g} "
                             f"px): the focal lengths are too long for this image; K is probably for a larger "
                             f"image (scale K with the image after a resize)")
        if crop:  # after the field of view, whose message names a unit error better
            corners = [math.hypot((u - cx) / fx, (v - cy) / fy) for u in (0, width) for v in (0, height)]
            off_axis = math.degrees(math.atan(max(corners)))
            if off_axis >= MAX_OFF_AXIS_DEG:
                raise InputError(f"{what}: expected every pixel of the {width}x{height} (WxH) image within "
                                 f"{MAX_OFF_AXIS_DEG:g} degrees of the optical axis (a pinhole image), got a corner "
                                 f"{off_axis:.1f} degrees off it (fx={fx:g}, fy={fy:g}, cx={cx:g}, cy={cy:g}): K "
                                 f"probably belongs to another image size or is in other units")
    return K


def _warn_other_size(what: str, cx: float, cy: float, width: int, height: int, fov_x: float, fov_y: float) -> None:
    """Warn (:class:`IntrinsicsWarning`) when the principal point says that K belongs to another image size:
    outside the image, or off-centre by the same factor in both axes (``OTHER_SIZE_CENTRE`` and
    ``OTHER_SIZE_AGREEMENT``), as the K of a smaller (or larger) image used on a resized one. A crop moves
    the principal point along one axis, or both by different factors, and is not warned about."""
    rx, ry = cx / width, cy / height
    outside = not (0 <= cx <= width and 0 <= cy <= height)
    low, high = OTHER_SIZE_CENTRE
    scaled = (rx > 0 and ry > 0 and max(rx, ry) / min(rx, ry) <= OTHER_SIZE_AGREEMENT
              and ((rx < low and ry < low) or (rx > high and ry > high)))
    if not (outside or scaled):
        return
    scale = 0.5 / math.sqrt(rx * ry) if rx > 0 and ry > 0 else None
    where = "outside the image" if outside else f"at ({rx:.2f}, {ry:.2f}) of its width and height"
    likely = (f"; K looks like the intrinsics of a {2 * cx:.0f}x{2 * cy:.0f} image (the image is {scale:.2g}x that "
              f"size): scale fx, fy, cx and cy by {scale:.3g} after resizing the image" if scaled and scale else
              "; K probably belongs to another image size (scale K with the image after a resize, shift cx, cy "
              "after a crop) or cx and cy are swapped")
    warnings.warn(f"{what}: expected the principal point near the centre of the {width}x{height} (WxH) image, got "
                  f"(cx, cy) = ({cx:g}, {cy:g}), {where} (field of view {fov_x:.0f} x {fov_y:.0f} degrees){likely}",
                  IntrinsicsWarning, stacklevel=4)


def check_batch_intrinsics(K: torch.Tensor, image_size: tuple[int, int], batched: bool) -> None:
    """Check each frame's intrinsics of a (B, 3, 3) ``K`` (as :func:`crfdepth.checks.check_frames`
    returns it) against the (height, width) of the image with :func:`check_intrinsics` (``crop=True``: the frame
    may be a crop, as training crops are):
    named ``K[b]`` when ``batched`` (K was given per frame), else ``K`` and checked once. One copy of
    the B x 9 numbers to the host."""
    values = K.detach().to("cpu", torch.float64).numpy()
    for b in range(values.shape[0] if batched else min(1, values.shape[0])):
        check_intrinsics(values[b], f"K[{b}]" if batched else "K", image_size, crop=True)
