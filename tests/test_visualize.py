"""crfdepth.visualize: depth and std colouring, LiDAR points on the image, the point-cloud view."""

import cv2
import numpy as np
import pytest
import torch

from crfdepth.errors import InputError
from crfdepth.visualize import colorize_depth, colorize_std, draw_points, render_point_cloud


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
    turbo = cv2.cvtColor(cv2.applyColorMap(np.array([[0, 255]], np.uint8), cv2.COLORMAP_TURBO), cv2.COLOR_BGR2RGB)
    np.testing.assert_array_equal(colorize_depth(torch.tensor([[[[2.0, 80.0]]]]))[0], turbo[0, ::-1])
    # A fixed range: depths beyond it are clipped to its ends.
    np.testing.assert_array_equal(colorize_depth(depth, vmin=5.0, vmax=10.0)[0, :3], turbo[0, [1, 1, 0]])


def test_colorize_std_is_sequential():
    std = np.array([[0.0, 0.5, 1.0, 3.0, -1.0]])
    rgb = colorize_std(std, vmax=1.0)
    viridis = cv2.cvtColor(cv2.applyColorMap(np.array([[0, 255]], np.uint8), cv2.COLORMAP_VIRIDIS),
                           cv2.COLOR_BGR2RGB)[0]
    np.testing.assert_array_equal(rgb[0, [0, 2, 3]], viridis[[0, 1, 1]])
    brightness = rgb[0, :3].astype(int).sum(1)
    assert brightness[0] < brightness[1] < brightness[2]
    assert (rgb[0, 4] == 0).all()  # negative: no value
    # Default top of the scale: the 99th percentile, not the outlier.
    many = np.concatenate([np.linspace(0, 1, 999), [100.0]])[None]
    assert colorize_std(many)[0, 998].astype(int).sum() > 400


def test_colorize_bad_input():
    with pytest.raises(InputError, match="depth"):
        colorize_depth(np.ones((2, 3, 4)))
    with pytest.raises(InputError, match="vmin"):
        colorize_depth(np.ones((2, 2)), vmin=-1.0, vmax=3.0)
    with pytest.raises(InputError, match="vmin, vmax"):
        colorize_std(np.ones((2, 2)), vmin=2.0, vmax=1.0)
