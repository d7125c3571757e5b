"""Pictures for people: a depth or std map with a colour bar in metres under it (docs/design.md sections 1 and 5).

- :func:`depth_picture`: TURBO on inverse depth (near = warm), see :func:`crfdepth.pictures.colour.colorize_depth`;
- :func:`std_picture`: VIRIDIS on a log scale by default (:func:`crfdepth.pictures.colour.colorize_std`);
- :func:`targets_picture`: camera-view targets on their image, dropped returns by reason (section 14).

``vis_range=(min_m, max_m)`` gives the same colours for the same metres in every frame of a
sequence; without it the range is the map's 2nd to 98th percentile, and an end of the bar that the
map's values pass is labelled open (``<=2 m``, ``>=67 m``). The bar is drawn with OpenCV (no
matplotlib at run time).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np

from crfdepth.errors import InputError
from crfdepth.pictures.colour import (
    BLACK,
    WHITE,
    Scale,
    as_map,
    check_color,
    check_scale,
    check_vis_range,
    colorize_depth,
    colorize_std,
    depth_range,
    std_range,
)
from crfdepth.sequences.targets import REASON_COLOURS, Targets

__all__ = ["captioned", "depth_picture", "std_picture", "targets_picture"]


def depth_picture(depth, vis_range: tuple[float, float] | None = None, *,
                  invalid_color=BLACK) -> np.ndarray:
    """A depth map a reader can read: :func:`colorize_depth` with a colour bar in metres below.

    Near = warm (TURBO on inverse depth, see :func:`colorize_depth`). The bar under the
    map runs from ``min_m`` (left, dark red) to ``max_m`` (right, dark blue) on the same
    inverse-depth scale, with tick labels in metres ("5 m", "10 m", ...); depths outside
    the range get the colour of the nearer end.

    Args:
        depth: (H, W) depth in metres (also (1, H, W) or (1, 1, H, W); numpy or torch);
            0, negative or non-finite = no depth (``invalid_color``).
        vis_range: ``(min_m, max_m)``, 0 < min_m < max_m: a fixed range, the same
            colours for the same metres in every frame of a sequence. Default
            :func:`depth_range` of this map (2nd to 98th percentile of its valid depths),
            so colours are comparable within a frame only.
        invalid_color: (R, G, B) of pixels without depth; default black.

    Returns:
        (H + 44, max(W, 320), 3) uint8 RGB: the map at the top left (pixel for pixel
        :func:`colorize_depth` with the same range), the colour bar on white below it.

    Raises:
        InputError: not a 2-D real map, a bad ``vis_range``, or no valid depth when
            ``vis_range`` is None.
    """
    d = as_map("depth", depth)
    lo, hi = depth_range(d) if vis_range is None else check_vis_range(vis_range, positive=True)
    rgb = colorize_depth(d, lo, hi, invalid_color=invalid_color)
    valid = d[np.isfinite(d) & (d > 0)] if vis_range is None else None
    return _with_colour_bar(rgb, _Scale("inverse", lo, hi), "depth",
                            lambda m: colorize_depth(m, lo, hi, invalid_color=invalid_color), valid)


def std_picture(std, vis_range: tuple[float, float] | None = None, lidar=None, *, scale: Scale = "log",
                lidar_color=WHITE, invalid_color=BLACK) -> np.ndarray:
    """An uncertainty map a reader can read: :func:`colorize_std` with a colour bar in metres below.

    Certain = dark (VIRIDIS). On the default log scale the bar's ticks are log-spaced
    (1, 2, 5 per decade, "0.5 m", "1 m", "2 m", ...) and equal steps of colour are equal
    *ratios* of std, so both the small std near the LiDAR and the large std far from it
    are told apart (docs/design.md section 5).

    Args:
        std: (H, W) standard deviation in metres (also (1, H, W) or
            (1, 1, H, W); numpy or torch); negative or non-finite = no value
            (``invalid_color``); 0 = the bottom colour.
        vis_range: ``(min_m, max_m)``, min_m < max_m (> 0 for log): a fixed range for a
            sequence. Default :func:`std_range` (2nd to 98th percentile of the stds > 0).
        lidar: optional (H, W) sparse depth in metres (0 = no point); when given, its
            points are drawn as single pixels of ``lidar_color`` over the map, to show
            where the measurements are.
        scale: "log" (default) or "linear".
        lidar_color: (R, G, B) of the LiDAR pixels; default white (not in VIRIDIS).
        invalid_color: (R, G, B) of pixels without a value; default black.

    Returns:
        (H + 44, max(W, 320), 3) uint8 RGB: the map at the top left (pixel for pixel
        :func:`colorize_std` with the same range and scale, but for the LiDAR pixels), the
        colour bar on white below it.

    Raises:
        InputError: not a 2-D real map, a bad ``vis_range`` or ``scale``, ``lidar`` not
            of the map's shape, or no std > 0 when ``vis_range`` is None on the log scale.
    """
    s = as_map("std", std)
    scale = check_scale(scale)
    if vis_range is not None:
        lo, hi = check_vis_range(vis_range, positive=scale == "log")
    elif scale == "log":
        lo, hi = std_range(s)
    else:  # linear: from 0 to the 98th percentile
        lo, hi = 0.0, std_range(s)[1]
    rgb = colorize_std(s, lo, hi, scale=scale, invalid_color=invalid_color)
    if lidar is not None:
        points = as_map("lidar", lidar)
        if points.shape != s.shape:
            raise InputError(f"lidar: expected an (H, W) sparse depth map of shape {s.shape} like std, "
                             f"got shape {points.shape}")
        rgb[np.isfinite(points) & (points > 0)] = check_color(lidar_color, "lidar_color")
    valid = s[np.isfinite(s) & (s >= 0)] if vis_range is None else None
    return _with_colour_bar(rgb, _Scale(scale, lo, hi), "std" if scale == "linear" else "std, log",
                            lambda m: colorize_std(m, lo, hi, scale=scale, invalid_color=invalid_color), valid)


# --------------------------------------------------------------------------- colour bar

_BAR_PANEL_HEIGHT = 44
_BAR_MIN_WIDTH = 320
_BAR_TOP, _BAR_BOTTOM = 6, 20  # rows of the colour strip in the panel
_TICK_LENGTH = 4
_LABEL_BASELINE = 38
_FONT, _FONT_SCALE = cv2.FONT_HERSHEY_SIMPLEX, 0.45
_INK, _PAPER, _FRAME = (0, 0, 0), (255, 255, 255), (128, 128, 128)


@dataclass(frozen=True)
class _Scale:
    """Where metres sit on a bar: position 0 = ``lo`` (left), 1 = ``hi`` (right)."""

    kind: str  # "inverse" (depth), "log" or "linear" (std)
    lo: float
    hi: float

    def position(self, metres: np.ndarray) -> np.ndarray:
        m = np.asarray(metres, dtype=np.float64)
        if self.kind == "inverse":
            return (1.0 / self.lo - 1.0 / m) / (1.0 / self.lo - 1.0 / self.hi)
        if self.kind == "log":
            return np.log(m / self.lo) / math.log(self.hi / self.lo)
        return (m - self.lo) / (self.hi - self.lo)

    def metres(self, position: np.ndarray) -> np.ndarray:
        t = np.asarray(position, dtype=np.float64)
        if self.kind == "inverse":
            return 1.0 / (1.0 / self.lo - t * (1.0 / self.lo - 1.0 / self.hi))
        if self.kind == "log":
            return self.lo * (self.hi / self.lo) ** t
        return self.lo + t * (self.hi - self.lo)

    def candidate_ticks(self) -> list[float]:
        """Round values inside the range, most important first (1, 5, 2, then 3 per decade)."""
        if self.kind == "linear":
            raw = (self.hi - self.lo) / 5.0
            step = min((m * 10.0 ** math.floor(math.log10(raw)) for m in (1, 2, 5, 10)),
                       key=lambda s: abs(s - raw))
            first = math.ceil(self.lo / step)
            return [k * step for k in range(first, int(math.floor(self.hi / step)) + 1)]
        decades = range(math.floor(math.log10(self.lo)), math.ceil(math.log10(self.hi)) + 1)
        values = [m * 10.0 ** e for m in (1, 5, 2, 3) for e in decades]
        return [v for v in values if self.lo <= v <= self.hi]


def _format_metres(value: float) -> str:
    if value == 0:
        return "0 m"
    text = f"{value:.0f}" if abs(value) >= 100 else f"{value:.2g}"
    return f"{text} m"


def _bar_labels(scale: _Scale, values: np.ndarray | None) -> list[tuple[float, str]]:
    """The bar's tick values and labels, most important first: both ends (open, ``<=`` / ``>=``, where the map's
    ``values`` pass them; None: a fixed range, the same bar in every frame), then round values."""
    below = values is not None and values.size > 0 and float(values.min()) < scale.lo
    above = values is not None and values.size > 0 and float(values.max()) > scale.hi
    return [(scale.lo, ("<=" if below else "") + _format_metres(scale.lo)),
            (scale.hi, (">=" if above else "") + _format_metres(scale.hi)),
            *((v, _format_metres(v)) for v in scale.candidate_ticks() if v not in (scale.lo, scale.hi))]


def _with_colour_bar(rgb: np.ndarray, scale: _Scale, title: str, paint, values: np.ndarray | None) -> np.ndarray:
    """``rgb`` on top of a white panel holding ``title`` and the colour bar of ``scale``.

    ``paint(metres)`` colours a (1, n) row of metres exactly as the map was coloured, so
    the bar shows the map's own colours. ``values``: the map's valid values when the range is
    the default one (its 2nd to 98th percentile); an end of the bar that they pass is labelled
    open, ``<=5 m`` or ``>=67 m``, since every value beyond it has that end's colour. None (a
    fixed ``vis_range``): the bar is the same in every frame.
    """
    h, w = rgb.shape[:2]
    width = max(w, _BAR_MIN_WIDTH)
    out = np.full((h + _BAR_PANEL_HEIGHT, width, 3), _PAPER, np.uint8)
    out[:h, :w] = rgb
    panel = out[h:]
    (title_w, title_h), _ = cv2.getTextSize(title, _FONT, _FONT_SCALE, 1)
    middle = (_BAR_TOP + _BAR_BOTTOM) // 2
    cv2.putText(panel, title, (8, middle + title_h // 2), _FONT, _FONT_SCALE, _INK, 1, cv2.LINE_AA)
    x0, x1 = 8 + title_w + 28, width - 24  # bar columns [x0, x1); room for half a label each side
    n = x1 - x0
    positions = np.arange(n) / (n - 1)
    panel[_BAR_TOP:_BAR_BOTTOM, x0:x1] = paint(scale.metres(positions)[None])[0]
    cv2.rectangle(panel, (x0 - 1, _BAR_TOP - 1), (x1, _BAR_BOTTOM), _FRAME, 1)
    # Ticks: both ends first, then round values while their labels do not overlap.
    taken: list[tuple[int, int]] = []
    for value, label in _bar_labels(scale, values):
        x = x0 + int(round(float(scale.position(value)) * (n - 1)))
        (label_w, _), _ = cv2.getTextSize(label, _FONT, _FONT_SCALE, 1)
        left = min(max(x - label_w // 2, 0), width - label_w)
        span = (left - 4, left + label_w + 4)
        if any(span[0] < b and a < span[1] for a, b in taken):
            continue
        taken.append(span)
        cv2.line(panel, (x, _BAR_BOTTOM), (x, _BAR_BOTTOM + _TICK_LENGTH - 1), _INK, 1)
        cv2.putText(panel, label, (left, _LABEL_BASELINE), _FONT, _FONT_SCALE, _INK, 1, cv2.LINE_AA)
    return out


def captioned(rgb: np.ndarray, caption: str) -> np.ndarray:
    """``rgb`` over a white panel as tall as a colour bar's, holding ``caption`` (one line, its font shrunk to fit the
    width): a picture without a scale laid out like those with one.

    Returns:
        (H + 44, W, 3) uint8 RGB.
    """
    h, w = rgb.shape[:2]
    out = np.full((h + _BAR_PANEL_HEIGHT, w, 3), _PAPER, np.uint8)
    out[:h] = rgb
    (text_w, text_h), _ = cv2.getTextSize(caption, _FONT, _FONT_SCALE, 1)
    font_scale = _FONT_SCALE * min(1.0, (w - 16) / max(text_w, 1))
    text_h = cv2.getTextSize(caption, _FONT, font_scale, 1)[0][1]
    cv2.putText(out[h:], caption, (8, (_BAR_PANEL_HEIGHT + text_h) // 2), _FONT, font_scale, _INK, 1, cv2.LINE_AA)
    return out


def targets_picture(image, targets: Targets, vis_range: tuple[float, float] | None = None) -> np.ndarray:
    """The image with the targets coloured by depth and the dropped returns by reason.

    Targets are painted like :func:`crfdepth.pictures.colour.colorize_depth` (near = warm) on the
    image darkened to half; pixels without a target where a dropped return lands are
    painted with :data:`REASON_COLOURS` (occluded: magenta, moved: white). A legend strip
    under the picture names the colours and the density.

    Args:
        image: (H, W, 3) RGB image of the frame, uint8 or floats in [0, 1].
        targets: its :class:`Targets`.
        vis_range: ``(min_m, max_m)`` of the depth colours (default: the targets' range).

    Returns:
        (H + 24, W, 3) uint8 RGB.

    Raises:
        InputError: ``image`` is not an (H, W, 3) image of the targets' size, or a bad
            ``vis_range``.
    """
    rgb = np.asarray(image)
    shape = targets.depth.shape
    if rgb.shape != (*shape, 3) or not (rgb.dtype == np.uint8 or np.issubdtype(rgb.dtype, np.floating)):
        raise InputError(f"image: expected a {shape[0]}x{shape[1]} (HxW) RGB image (uint8, or floats in [0, 1]) like "
                         f"the targets, got shape {rgb.shape} {rgb.dtype}")
    if rgb.dtype != np.uint8:
        rgb = np.round(np.clip(np.nan_to_num(rgb), 0.0, 1.0) * 255.0).astype(np.uint8)
    out = (rgb // 2).copy()
    has = targets.depth > 0
    if has.any():
        colours = colorize_depth(targets.depth, vis_range=vis_range)
        out[has] = colours[has]
    for code, colour in REASON_COLOURS.items():
        out[targets.reason == code] = colour
    strip = np.full((24, shape[1], 3), 255, dtype=np.uint8)
    counts = targets.counts()
    text = (f"targets {100 * targets.density:.1f}% (scans {targets.window[0]}-{targets.window[-1]})  "
            f"occluded {counts['occluded']} (magenta)  moved {counts['moved']} (white)")
    cv2.putText(strip, text, (4, 17), cv2.FONT_HERSHEY_SIMPLEX, 0.4, (0, 0, 0), 1, cv2.LINE_AA)
    return np.concatenate([out, strip], axis=0)
