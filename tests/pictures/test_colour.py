"""crfdepth.pictures.colour and crfdepth.pictures.figures: depth and std colouring, colour bars, LiDAR points on the image, the point-cloud view."""

import cv2
import numpy as np
import pytest
import torch

from crfdepth.errors import InputError
from crfdepth.pictures import figures as pictures
from crfdepth.pictures.colour import (
    colorize_depth,
    colorize_std,
    depth_range,
    draw_points,
    render_point_cloud,
    std_range,
)
from crfdepth.pictures.figures import depth_picture, std_picture


def _lut(colormap: int) -> np.ndarray:
    """(256, 3) RGB colours of an OpenCV colour map, index = code."""
    codes = np.arange(256, dtype=np.uint8)[None]
    return cv2.cvtColor(cv2.applyColorMap(codes, colormap), cv2.COLOR_BGR2RGB)[0]


def _bar_codes(panel: np.ndarray, colormap: int) -> np.ndarray:
    """Colour-map codes, left to right, of the panel row holding the most colours of the map."""
    lut = _lut(colormap).astype(int)
    codes = np.full(panel.shape[:2], -1)
    for y in range(panel.shape[0]):
        match = (panel[y][:, None, :].astype(int) == lut[None]).all(-1)  # (W, 256)
        found = match.any(1)
        codes[y, found] = match[found].argmax(1)
    row = codes[(codes >= 0).sum(1).argmax()]
    return row[row >= 0]


def _synthetic_std(h: int = 60, w: int = 90) -> np.ndarray:
    """A posterior-std-like map: small on LiDAR rows (every 6th row of the lower two thirds),
    growing between them, and large above the top scan line (0.014 to 2.3 m)."""
    rows = np.arange(h)[:, None]
    between = np.abs((rows % 6) - 3).astype(float)  # 3 on a scan line, 0 halfway
    wobble = 1 + 0.3 * np.sin(np.arange(w) / 7.0)[None]
    covered = 0.02 * (1 + 3 - between) * wobble
    above = 0.1 * 1.17 ** (20 - rows) * wobble
    return np.where(rows >= 20, covered, above)


def test_draw_points_marks_exactly_the_lidar_squares():
    rgb = np.full((20, 30, 3), 200, np.uint8)
    sparse = np.zeros((20, 30))
    sparse[10, 15] = 5.0
    out = draw_points(rgb, sparse, radius=1)
    changed = (out != 100).any(-1)  # background darkened to half
    assert changed.sum() == 9 and changed[9:12, 14:17].all()
    with pytest.raises(InputError, match="rgb: expected a"):
        draw_points(rgb[:10], sparse)


def test_render_point_cloud_of_a_wall_is_a_band_of_its_colour():
    K = np.array([[50.0, 0, 32], [0, 50.0, 24], [0, 0, 1]])
    depth = np.full((48, 64), 20.0)
    rgb = np.zeros((48, 64, 3), np.uint8)
    rgb[..., 0] = 255
    out = render_point_cloud(depth, rgb, K, lift_m=0.0, back_m=0.0, pitch_deg=0.0)
    # Seen from the same camera the wall covers the picture and keeps its colour.
    assert (out[..., 0] == 255).mean() > 0.95 and out[..., 1].max() == 0
    far = render_point_cloud(depth, rgb, K, max_depth=10.0)
    assert far.max() == 0  # everything beyond max_depth is left out


def test_colorize_depth_near_is_warm_and_invalid_black():
    depth = np.array([[2.0, 5.0, 80.0, 0.0, np.nan]])
    before = depth.copy()
    rgb = colorize_depth(depth)
    assert rgb.shape == (1, 5, 3) and rgb.dtype == np.uint8
    assert rgb[0, 0, 0] > rgb[0, 0, 2]  # nearest: red
    assert rgb[0, 2, 2] > rgb[0, 2, 0]  # farthest: blue
    assert (rgb[0, 3:] == 0).all()  # no depth: black
    np.testing.assert_array_equal(depth, before, strict=True)
    # Ends of the TURBO map at vmin / vmax; a tensor with leading singleton dims works too.
    turbo = _lut(cv2.COLORMAP_TURBO)[[0, 255]][None]
    np.testing.assert_array_equal(colorize_depth(torch.tensor([[[[2.0, 80.0]]]]))[0], turbo[0, ::-1])
    # A fixed range: depths beyond it are clipped to its ends; vis_range is the same as vmin/vmax.
    np.testing.assert_array_equal(colorize_depth(depth, vmin=5.0, vmax=10.0)[0, :3], turbo[0, [1, 1, 0]])
    np.testing.assert_array_equal(colorize_depth(depth, vis_range=(5.0, 10.0)), colorize_depth(depth, 5.0, 10.0))


def test_colorize_std_is_sequential():
    std = np.array([[0.0, 0.5, 1.0, 3.0, -1.0]])
    rgb = colorize_std(std, vmax=1.0)
    viridis = _lut(cv2.COLORMAP_VIRIDIS)[[0, 255]]
    np.testing.assert_array_equal(rgb[0, [0, 2, 3]], viridis[[0, 1, 1]])
    brightness = rgb[0, :3].astype(int).sum(1)
    assert brightness[0] < brightness[1] < brightness[2]
    assert (rgb[0, 4] == 0).all()  # negative: no value
    # Default top of the scale: the 99th percentile, not the outlier.
    many = np.concatenate([np.linspace(0, 1, 999), [100.0]])[None]
    assert colorize_std(many)[0, 998].astype(int).sum() > 400
    # Log scale: 0.01, 0.1, 1 m are the bottom, middle (code 127.5) and top; 0 is painted the bottom.
    log = colorize_std(np.array([[0.01, 1.0, 0.0, 0.1]]), vis_range=(0.01, 1.0), scale="log")
    viridis = _lut(cv2.COLORMAP_VIRIDIS)
    np.testing.assert_array_equal(log[0, :3], viridis[[0, 255, 0]])
    assert (log[0, 3] == viridis[127]).all() or (log[0, 3] == viridis[128]).all()


def test_depth_picture_has_a_colour_bar_in_metres_below_the_map():
    depth = np.tile(np.linspace(3.0, 60.0, 400), (40, 1))
    depth[:5, :5] = 0.0  # no depth
    picture = depth_picture(depth, vis_range=(4.0, 50.0))
    # The map is on top, pixel for pixel the bare colour map; the bar adds rows below it.
    assert picture.dtype == np.uint8 and picture.shape[1] == 400 and picture.shape[0] >= 40 + 30
    np.testing.assert_array_equal(picture[:40], colorize_depth(depth, vis_range=(4.0, 50.0)))
    panel = picture[40:]
    # The bar shows the whole TURBO scale in order: near (warm, code 255) at the left, far at the right.
    codes = _bar_codes(panel, cv2.COLORMAP_TURBO)
    assert len(codes) > 250 and codes[0] == 255 and codes[-1] == 0
    assert (np.diff(codes) <= 0).all()
    assert len(np.unique(codes)) > 200
    # A tick at 10 m: below the bar column painted like 10 m, a black tick mark, labelled "10 m".
    ten = colorize_depth(np.array([[10.0]]), vis_range=(4.0, 50.0))[0, 0]
    lut = (panel == ten).all(-1)
    bar_row = lut.sum(1).argmax()
    columns = np.flatnonzero(lut[bar_row])
    tick_rows = np.flatnonzero(lut[:, columns[0]])[-1] + 2
    assert (panel[tick_rows, columns[0] - 1:columns[-1] + 2] == 0).all(-1).any()
    text = "10 m"
    (tw, th), base = cv2.getTextSize(text, pictures._FONT, pictures._FONT_SCALE, 1)
    template = np.full((th + base + 4, tw + 4, 3), 255, np.uint8)
    cv2.putText(template, text, (2, th + 2), pictures._FONT, pictures._FONT_SCALE, (0, 0, 0), 1, cv2.LINE_AA)
    score = cv2.matchTemplate(panel, template, cv2.TM_SQDIFF)
    _, _, (x, _), _ = cv2.minMaxLoc(score)
    assert score.min() == 0 and abs(x + 2 + tw / 2 - columns.mean()) <= 2


def test_pictures_of_small_maps_get_a_bar_wide_enough_to_read():
    picture = std_picture(np.array([[0.1, 1.0], [0.5, 2.0]]))
    assert picture.shape[1] >= 300 and picture.shape[0] > 2 + 30
    assert (picture[:2, 2:] == 255).all()  # white beside the narrow map


def test_fixed_range_gives_the_same_colours_for_the_same_metres_in_two_frames():
    near = np.tile(np.linspace(2.0, 30.0, 200), (20, 1))
    far = np.tile(np.linspace(10.0, 90.0, 200), (20, 1))
    near[:, 7] = far[:, 150] = 12.5  # the same depth in both frames, at different places
    for picture, kwargs in ((depth_picture, {}), (std_picture, {}), (std_picture, {"scale": "linear"})):
        a, b = picture(near, vis_range=(5.0, 60.0), **kwargs), picture(far, vis_range=(5.0, 60.0), **kwargs)
        np.testing.assert_array_equal(a[0, 7], b[0, 150])
        np.testing.assert_array_equal(a[20:], b[20:])  # and the same colour bar
        # The per-frame default scales them differently.
        c, d = picture(near, **kwargs), picture(far, **kwargs)
        assert (c[0, 7] != d[0, 150]).any()


def test_default_ranges_are_robust_percentiles():
    depth = np.tile(np.linspace(10.0, 20.0, 100), (10, 1))
    depth[0, :5] = 1000.0  # 0.5 % far outliers
    depth[1, :5] = 0.1  # and near ones
    lo, hi = depth_range(depth)
    valid = depth[depth > 0]
    assert (lo, hi) == pytest.approx(tuple(np.percentile(valid, [2, 98])))
    assert 10.0 <= lo < hi <= 20.0
    std = np.concatenate([np.zeros(10), np.geomspace(0.01, 1.0, 1000)])[None]
    assert std_range(std) == pytest.approx(tuple(np.percentile(std[std > 0], [2, 98])))
    assert std_range(np.full((3, 3), 2.0)) == pytest.approx((1.6, 2.5))  # constant: a range around it


def test_log_std_scale_spreads_a_realistic_map_over_many_more_colours():
    std = _synthetic_std()
    assert std.max() / std.min() > 100
    covered = np.broadcast_to(np.arange(std.shape[0])[:, None] >= 20, std.shape)

    def colours(rgb, where=None):
        pixels = rgb.reshape(-1, 3) if where is None else rgb[where]
        return len(np.unique(pixels, axis=0))

    linear = colorize_std(std, vis_range=std_range(std), scale="linear")
    log = colorize_std(std, scale="log")  # default range: std_range
    linear_picture, log_picture = std_picture(std, scale="linear"), std_picture(std)
    # Where the LiDAR is (two thirds of the pixels) the linear scale has a handful of colours
    # (12), the log scale five times as many (70); above it both use most of the scale.
    assert colours(linear, covered) <= 20 and colours(log, covered) >= 5 * colours(linear, covered)
    assert colours(log, ~covered) > 120 and colours(linear, ~covered) > 120
    h, w = std.shape
    np.testing.assert_array_equal(log_picture[:h, :w], log)
    assert colours(log_picture[:h, :w], covered) >= 4 * colours(linear_picture[:h, :w], covered)


def test_std_picture_marks_the_lidar_pixels():
    std = _synthetic_std()
    lidar = np.zeros_like(std)
    lidar[30, 10:20] = 5.0
    picture = std_picture(std, lidar=lidar)
    white = (picture[:std.shape[0], :std.shape[1]] == 255).all(-1)
    assert white.sum() == 10 and white[30, 10:20].all()


@pytest.mark.parametrize(("call", "name"), [
    (lambda: depth_picture(np.ones((2, 2)), vis_range=(5.0,)), "vis_range"),
    (lambda: depth_picture(np.ones((2, 2)), vis_range=(5.0, 2.0)), "vis_range"),
    (lambda: depth_picture(np.ones((2, 2)), vis_range=(5.0, 5.0)), "vis_range"),
    (lambda: depth_picture(np.ones((2, 2)), vis_range=(0.0, 5.0)), "vis_range"),
    (lambda: depth_picture(np.ones((2, 2)), vis_range=(np.nan, 5.0)), "vis_range"),
    (lambda: depth_picture(np.ones((2, 2)), vis_range="5,10"), "vis_range"),
    (lambda: depth_picture(np.ones((2, 2)), vis_range=(True, 5.0)), "vis_range"),
    (lambda: std_picture(np.ones((2, 2)), vis_range=(0.0, 1.0)), "vis_range"),  # log needs min > 0
    (lambda: std_picture(np.ones((2, 2)), vis_range=(-1.0, 1.0), scale="linear"), "vis_range"),
    (lambda: colorize_std(np.ones((2, 2)), vis_range=(0.0, 1.0), scale="log"), "vis_range"),
    (lambda: colorize_depth(np.ones((2, 2)), 1.0, vis_range=(1.0, 2.0)), "vis_range"),
    (lambda: depth_picture(np.ones((2, 3, 4))), "depth"),
    (lambda: depth_picture(np.zeros((2, 2))), "depth"),  # no valid depth to choose a range from
    (lambda: std_picture(np.zeros((2, 2))), "std"),
    (lambda: std_picture(np.array([["a", "b"]])), "std"),
    (lambda: std_picture(np.ones((2, 2)), lidar=np.ones((3, 2))), "lidar"),
    (lambda: std_picture(np.ones((2, 2)), scale="cubic"), "scale"),
    (lambda: colorize_std(np.ones((2, 2)), scale="exp"), "scale"),
    (lambda: depth_range(np.ones((2, 2)), percentiles=(98, 2)), "percentiles"),
])
def test_picture_bad_input_names_the_argument_in_one_line(call, name):
    with pytest.raises(InputError) as info:
        call()
    message = str(info.value)
    assert message.startswith(f"{name}: expected") and "\n" not in message, message


def test_colorize_bad_input():
    with pytest.raises(InputError, match="depth"):
        colorize_depth(np.ones((2, 3, 4)))
    with pytest.raises(InputError, match="vmin"):
        colorize_depth(np.ones((2, 2)), vmin=-1.0, vmax=3.0)
    with pytest.raises(InputError, match="vmin, vmax"):
        colorize_std(np.ones((2, 2)), vmin=2.0, vmax=1.0)
    with pytest.raises(InputError, match="vmin: expected a std > 0"):
        colorize_std(np.ones((2, 2)), vmin=0.0, vmax=1.0, scale="log")
