"""draw_points and render_point_cloud (the demo's pictures)."""

import numpy as np
import pytest

from crfdepth.errors import InputError
from crfdepth.visualize import draw_points, render_point_cloud


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
