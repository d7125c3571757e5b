"""The NYU Depth v2 colour camera (Kinect v1) and its intrinsics at the sizes the datasets ship (docs/design.md section 17).

NYU v2's images are undistorted and the depth registered to them; at 640 x 480 the colour camera has
``fx = 518.86``, ``fy = 519.47``, ``cx = 325.58``, ``cy = 253.74`` pixels (zero skew).
:func:`nyu_intrinsics` gives ``K`` for a frame of another size: a scale of 640 x 480 (the 160 x 120
frames of loader tests, the 320 x 240 of the protocol) or a crop of it (the 560 x 425 crop of the
labeled set that many papers use, top-left corner (40, 44)).
"""

from __future__ import annotations

import torch

from crfdepth.data.sampling import resized_intrinsics
from crfdepth.errors import InputError

__all__ = ["LABELED_CROP", "NYU_HEIGHT", "NYU_K", "NYU_WIDTH", "nyu_intrinsics"]

NYU_WIDTH, NYU_HEIGHT = 640, 480
#: (3, 3) float32 ``K`` of the NYU v2 colour camera at 640 x 480, pixels (pixel ``(u, v)`` centred at ``(u, v)``).
NYU_K = torch.tensor([[518.86, 0.0, 325.58], [0.0, 519.47, 253.74], [0.0, 0.0, 1.0]], dtype=torch.float32)
#: ``{(width, height): (left, top)}`` of the known crops of the 640 x 480 frame: the labeled set's 560 x 425.
LABELED_CROP = {(560, 425): (40, 44)}


def nyu_intrinsics(width: int, height: int, crop: tuple[int, int] | None = None, *,
                   argument: str = "width, height") -> torch.Tensor:
    """``K`` of a NYU v2 frame of ``width x height`` pixels.

    Args:
        width: the frame's width, pixels.
        height: the frame's height, pixels.
        crop: ``(left, top)`` of the frame in the 640 x 480 image when it is a crop of it; None: the
            frame is the 640 x 480 image, a scale of it, or a known crop (560 x 425: ``(40, 44)``).
        argument: the user's name of the size in messages (a dataset names the image file).

    Returns:
        (3, 3) float32 ``K``, pixels: :data:`NYU_K` itself at 640 x 480; scaled by ``s = width / 640``
        (``fx s``, ``fy s``; ``c' = (c + 0.5) s - 0.5``, the pixel-centre convention of
        :class:`~crfdepth.data.sampling.Resize`, so that ``nyu_intrinsics(320, 240)`` is the ``K`` the
        protocol's resize gives); shifted by a crop (``cx - left``, ``cy - top``: 560 x 425 gives
        ``cx = 285.58``, ``cy = 209.74``).

    Raises:
        InputError: a size that is neither 640 x 480 scaled by one factor on both axes nor a known crop;
            a ``crop`` that does not fit inside 640 x 480.
    """
    w, h = int(width), int(height)
    if crop is None and (w, h) in LABELED_CROP:
        crop = LABELED_CROP[(w, h)]
    K = NYU_K.clone()
    if crop is not None:
        left, top = (int(v) for v in crop)
        if left < 0 or top < 0 or left + w > NYU_WIDTH or top + h > NYU_HEIGHT:
            raise InputError(f"crop: expected (left, top) of a {w}x{h} window inside the {NYU_WIDTH}x{NYU_HEIGHT} "
                             f"NYU v2 frame, got {tuple(crop)}")
        K[0, 2] -= left
        K[1, 2] -= top
        return K
    if w <= 0 or h <= 0 or w * NYU_HEIGHT != h * NYU_WIDTH:
        known = ", ".join(f"{cw}x{ch}" for cw, ch in LABELED_CROP)
        raise InputError(f"{argument}: expected a NYU v2 frame of {NYU_WIDTH}x{NYU_HEIGHT} (WxH), a scale of it "
                         f"(e.g. 320x240, 160x120) or a known crop ({known}), got {w}x{h}")
    if w == NYU_WIDTH:
        return K
    return resized_intrinsics(K, w / NYU_WIDTH, h / NYU_HEIGHT)
