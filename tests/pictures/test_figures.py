"""crfdepth.pictures.figures: sizes, colours at known metres and bad input of the pictures with a colour bar,
and the targets picture (tests/pictures/test_colour.py checks the bars' ticks and ranges)."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
import torch

from crfdepth.errors import InputError
from crfdepth.pictures import figures
from crfdepth.pictures.colour import colorize_depth, colorize_std, depth_range, std_range
from crfdepth.pictures.figures import depth_picture, std_picture, targets_picture
from crfdepth.sequences.targets import KEPT, MOVED, OCCLUDED, REASON_COLOURS, Targets

PANEL, MIN_WIDTH = 44, 320  # the colour bar's rows under the map, and its smallest width


def _lut(colormap: int) -> np.ndarray:
    """(256, 3) RGB colours of an OpenCV colour map, index = code."""
    return cv2.cvtColor(cv2.applyColorMap(np.arange(256, dtype=np.uint8)[None], colormap), cv2.COLOR_BGR2RGB)[0]


TURBO, VIRIDIS = _lut(cv2.COLORMAP_TURBO), _lut(cv2.COLORMAP_VIRIDIS)


@pytest.mark.parametrize(("h", "w"), [(3, 4), (10, 500)])
def test_pictures_are_the_map_over_a_white_panel_at_least_320_wide(h, w):
    depth = np.linspace(5.0, 50.0, h * w).reshape(h, w)
    lo, hi = depth_range(depth)  # the default range of both pictures (linear std: from 0)
    for picture, colours in ((depth_picture(depth), colorize_depth(depth, lo, hi)),
                             (std_picture(depth, scale="linear"), colorize_std(depth, 0.0, hi, scale="linear"))):
        assert picture.shape == (h + PANEL, max(w, MIN_WIDTH), 3) and picture.dtype == np.uint8
        np.testing.assert_array_equal(picture[:h, :w], colours)
        assert (picture[:h, w:] == 255).all()  # white beside a narrow map
        assert (picture[h:] == 255).all(-1).mean() > 0.5  # the bar, ticks and labels drawn on white


def test_depth_colours_at_known_metres_are_the_turbo_codes_of_inverse_depth():
    # 1/z halfway between 1/5 and 1/50 (z = 100/11 m) is the middle of the scale; beyond the ends, the ends.
    depth = np.array([[5.0, 50.0, 100.0 / 11.0, 2.0, 200.0, 0.0, -1.0, np.nan]])
    picture = depth_picture(depth, vis_range=(5.0, 50.0), invalid_color=(10, 20, 30))
    row = picture[0, :8]
    np.testing.assert_array_equal(row[[0, 1, 3, 4]], TURBO[[255, 0, 255, 0]])
    assert (row[2] == TURBO[127]).all() or (row[2] == TURBO[128]).all()
    np.testing.assert_array_equal(row[5:], [[10, 20, 30]] * 3)  # no depth: 0, negative, NaN


def test_std_colours_at_known_metres_and_the_lidar_over_them():
    std = np.array([[0.0, 0.5, 1.0, 2.0, -1.0]])
    lidar = np.array([[0.0, 0.0, 0.0, 0.0, 7.0]])
    picture = std_picture(std, vis_range=(0.0, 1.0), scale="linear", lidar=lidar, lidar_color=(255, 0, 0))
    row = picture[0, :5]
    np.testing.assert_array_equal(row[[0, 2, 3]], VIRIDIS[[0, 255, 255]])
    assert (row[1] == VIRIDIS[127]).all() or (row[1] == VIRIDIS[128]).all()
    np.testing.assert_array_equal(row[4], [255, 0, 0])  # a LiDAR point wins over an invalid std
    # The log scale: 0.01, 0.1 and 1 m are the bottom, middle and top.
    log = std_picture(np.array([[0.01, 0.1, 1.0]]), vis_range=(0.01, 1.0))[0, :3]
    np.testing.assert_array_equal(log[[0, 2]], VIRIDIS[[0, 255]])
    assert (log[1] == VIRIDIS[127]).all() or (log[1] == VIRIDIS[128]).all()


def test_tensors_of_any_leading_singleton_shape_give_the_numpy_picture():
    depth = np.linspace(3.0, 30.0, 12).reshape(3, 4)
    expected = depth_picture(depth)
    for shaped in (torch.from_numpy(depth), torch.from_numpy(depth)[None], torch.from_numpy(depth)[None, None]):
        np.testing.assert_array_equal(depth_picture(shaped), expected)
    # float32 against float64: a value on a colour boundary may round to the neighbouring level, never further
    single = std_picture(torch.from_numpy(depth).float()[None, None]).astype(np.int16)
    double = std_picture(depth).astype(np.int16)
    assert single.shape == double.shape and np.abs(single - double).max() <= 1


@pytest.mark.parametrize(("kind", "lo", "hi", "middle"), [
    ("inverse", 5.0, 50.0, 100.0 / 11.0),
    ("log", 0.01, 1.0, 0.1),
    ("linear", 0.0, 2.0, 1.0),
])
def test_bar_positions_and_metres_are_inverse_of_each_other(kind, lo, hi, middle):
    scale = figures._Scale(kind, lo, hi)
    np.testing.assert_allclose(scale.position(np.array([lo, middle, hi])), [0.0, 0.5, 1.0], atol=1e-12)
    positions = np.linspace(0.0, 1.0, 11)
    np.testing.assert_allclose(scale.position(scale.metres(positions)), positions, atol=1e-12)


def test_tick_candidates_are_round_metres_inside_the_range():
    assert figures._Scale("log", 0.5, 20.0).candidate_ticks() == pytest.approx([1, 10, 0.5, 5, 2, 20, 3])
    assert figures._Scale("inverse", 4.0, 50.0).candidate_ticks() == pytest.approx([10, 5, 50, 20, 30])
    assert figures._Scale("linear", 0.0, 1.0).candidate_ticks() == pytest.approx([0, 0.2, 0.4, 0.6, 0.8, 1.0])
    labels = [figures._format_metres(v) for v in (0.0, 0.25, 2.0, 12.0, 150.0)]
    assert labels == ["0 m", "0.25 m", "2 m", "12 m", "150 m"]


def test_an_end_of_the_bar_that_the_map_passes_is_labelled_open():
    """The default range is the 2nd to 98th percentile: a std map with a 12.7 m tail must not read as if its
    brightest colour were the 98th percentile's metres."""
    std = np.geomspace(0.1, 1.0, 400).reshape(20, 20)
    std[0, :5] = 0.05
    std[-1, :5] = 12.7
    lo, hi = std_range(std)
    labels = [label for _, label in figures._bar_labels(figures._Scale("log", lo, hi), std[std > 0])]
    assert labels[0].startswith("<=") and labels[1].startswith(">="), labels
    assert not any(label.startswith(("<", ">")) for label in labels[2:])
    closed = [label for _, label in figures._bar_labels(figures._Scale("log", 0.01, 20.0), std[std > 0])]
    assert not any(label.startswith(("<", ">")) for label in closed), closed
    # Only the labels differ: the map's pixels are those of the closed bar's range.
    open_picture, fixed = std_picture(std), std_picture(std, vis_range=(lo, hi))
    np.testing.assert_array_equal(open_picture[:20, :20], fixed[:20, :20])
    depth = np.linspace(5.0, 50.0, 400).reshape(20, 20)
    depth[0, :5], depth[-1, -5:] = 2.0, 90.0
    labels = [label for _, label in figures._bar_labels(figures._Scale("inverse", *depth_range(depth)), depth.ravel())]
    assert labels[:2] == [f"<={figures._format_metres(depth_range(depth)[0])}",
                          f">={figures._format_metres(depth_range(depth)[1])}"]


@pytest.mark.parametrize("width", [120, 1216])
def test_a_caption_panel_is_as_tall_as_a_colour_bar_and_its_text_fits(width):
    rgb = np.zeros((30, width, 3), np.uint8)
    picture = figures.captioned(rgb, "the depth in 3D, seen from 4 m above and 10 m behind the camera")
    assert picture.shape == depth_picture(np.full((30, width), 5.0)).shape[:1] + (width, 3)
    np.testing.assert_array_equal(picture[:30], rgb)
    ink = np.flatnonzero((picture[30:] < 128).all(-1).any(0))
    assert ink.size and ink[0] >= 4 and ink[-1] <= width - 4  # inside the picture, however narrow


def _targets(h: int = 4, w: int = 6) -> Targets:
    depth = np.zeros((h, w), np.float32)
    depth[1, 1], depth[2, 4] = 5.0, 50.0
    reason = np.zeros((h, w), np.uint8)
    reason[0, 0], reason[3, 5] = OCCLUDED, MOVED
    codes = np.array([KEPT, KEPT, OCCLUDED, MOVED, MOVED], np.uint8)
    return Targets(depth=depth, support=(depth > 0).astype(np.uint16), own=depth > 0, reason=reason,
                   point_reason=[codes], window=(3, 4, 5), index=4)


def test_targets_picture_colours_targets_reasons_and_darkens_the_rest():
    targets = _targets()
    image = np.full((4, 6, 3), 201, np.uint8)
    picture = targets_picture(image, targets, vis_range=(5.0, 50.0))
    assert picture.shape == (4 + 24, 6, 3) and picture.dtype == np.uint8
    np.testing.assert_array_equal(picture[[1, 2], [1, 4]], TURBO[[255, 0]])  # 5 m warm end, 50 m cold end
    np.testing.assert_array_equal(picture[0, 0], REASON_COLOURS[OCCLUDED])
    np.testing.assert_array_equal(picture[3, 5], REASON_COLOURS[MOVED])
    rest = (targets.depth == 0) & (targets.reason == KEPT)
    assert (picture[:4][rest] == 100).all()  # 201 // 2
    assert (picture[4:] != 255).any()  # the legend's text
    # A float image in [0, 1] is the same picture as its uint8 rounding.
    np.testing.assert_array_equal(targets_picture(image / 255.0, targets, vis_range=(5.0, 50.0)), picture)
    assert targets.density == pytest.approx(2 / 24) and targets.counts()["moved"] == 2


@pytest.mark.parametrize(("call", "name"), [
    (lambda: depth_picture(np.ones((2, 2)), invalid_color=(300, 0, 0)), "invalid_color"),
    (lambda: depth_picture(np.ones((2, 2)), invalid_color=(0, 0)), "invalid_color"),
    (lambda: depth_picture(np.ones((0, 3))), "depth"),
    (lambda: std_picture(np.ones((2, 2)), lidar=np.ones((2, 2)), lidar_color=(1, 2)), "lidar_color"),
    (lambda: std_picture(np.ones((2, 2)), lidar=np.ones((2, 2, 2))), "lidar"),
    (lambda: targets_picture(np.zeros((4, 6, 3), np.int32), _targets()), "image"),
    (lambda: targets_picture(np.zeros((4, 6)), _targets()), "image"),
    (lambda: targets_picture(np.zeros((4, 6, 3)), _targets(), vis_range=(50.0, 5.0)), "vis_range"),
])
def test_bad_input_is_one_line_naming_the_argument(call, name):
    with pytest.raises(InputError) as info:
        call()
    message = str(info.value)
    assert message.startswith(f"{name}: expected") and "\n" not in message, message
