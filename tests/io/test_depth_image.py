"""Tests of crfdepth.io.depth_image: RGB-D depth PNGs read into metres, and every refusal naming the argument."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from crfdepth.io.depth_image import (
    CODES_PER_METRE,
    DEPTH_UNITS,
    check_depth_matches_image,
    check_depth_units,
    read_depth_image,
)
from tests.refusals import refused


def _png(path, array) -> str:
    assert cv2.imwrite(str(path), array)
    return str(path)


def _room(shape=(48, 64), seed=0, low=0.8, high=6.0, holes=0.3) -> np.ndarray:
    """Depth of an indoor scene in metres (0 = hole), like a Kinect frame."""
    rng = np.random.default_rng(seed)
    depth = rng.uniform(low, high, shape)
    depth[rng.random(shape) < holes] = 0.0
    return depth


# --------------------------------------------------------------------------- reading


@pytest.mark.parametrize("units", DEPTH_UNITS)
def test_codes_are_read_in_each_unit(tmp_path, units):
    depth = _room(high=60.0 if units == "m" else 6.0)
    codes = np.round(depth * CODES_PER_METRE[units]).astype(np.uint16)
    metres = read_depth_image(_png(tmp_path / "d.png", codes), units)
    assert metres.dtype == np.float32 and metres.shape == codes.shape
    np.testing.assert_allclose(metres, codes / CODES_PER_METRE[units], rtol=1e-6, atol=0)
    assert np.array_equal(metres == 0, codes == 0)  # holes stay 0


def test_real_nyu_depth_reads_as_millimetres(nyu_root):
    path = nyu_root / "official_test" / "basement" / "sync_depth_00000.png"
    depth = read_depth_image(path)
    codes = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    assert depth.shape == (480, 640)
    np.testing.assert_allclose(depth, codes / 1000.0, rtol=1e-6)
    assert float(np.median(depth[depth > 0])) == pytest.approx(3.258, abs=1e-3)
    assert 0.70 < np.mean(depth > 0) < 0.76  # the Kinect's holes kept as 0


def test_a_constant_depth_on_a_multiple_of_257_is_not_a_picture(tmp_path):
    codes = np.full((8, 8), 2570, np.uint16)  # 2.57 m: one level, not a visualisation
    assert read_depth_image(_png(tmp_path / "d.png", codes)) == pytest.approx(np.full((8, 8), 2.57), abs=1e-6)


# --------------------------------------------------------------------------- refusals


def test_files_that_cannot_be_read_name_the_argument(tmp_path):
    refused(lambda: read_depth_image(tmp_path / "none.png", argument="--depth"), "--depth: ", "none.png")
    refused(lambda: read_depth_image(tmp_path, argument="--depth"), "--depth: ")
    text = tmp_path / "notes.png"
    text.write_text("not an image")
    refused(lambda: read_depth_image(text, argument="--depth"), "--depth: ", "does not decode")
    empty = tmp_path / "empty.png"
    empty.write_bytes(b"")
    refused(lambda: read_depth_image(empty, argument="--depth"), "--depth: ", "0 bytes")


@pytest.mark.parametrize("array", [
    np.full((8, 8), 120, np.uint8),  # an 8-bit grey picture
    np.full((8, 8, 3), 120, np.uint8),  # a colour-mapped picture
    np.full((8, 8, 3), 3000, np.uint16),  # 16 bits, but three channels
], ids=["8-bit", "rgb", "16-bit-rgb"])
def test_pictures_arerefused(tmp_path, array):
    path = _png(tmp_path / "vis.png", array)
    refused(lambda: read_depth_image(path, argument="--depth"), "--depth: expected a single-channel 16-bit",
             "a visualisation, not depth codes")


def test_an_8_bit_visualisation_saved_as_16_bits_isrefused(tmp_path):
    grey = np.linspace(1, 255, 64 * 48).reshape(48, 64).astype(np.uint16)
    path = _png(tmp_path / "vis16.png", grey)
    message = refused(lambda: read_depth_image(path, "mm", argument="--depth"), "--depth: ",
                       "an 8-bit visualisation saved as 16 bits", "--depth-units m")
    assert "largest 255" in message
    scaled = _png(tmp_path / "vis257.png", (grey * 257).astype(np.uint16))  # 8 bits stretched to 16
    for units in DEPTH_UNITS:
        refused(lambda: read_depth_image(scaled, units, argument="--depth"), "--depth: ", "multiple of 257")


def test_whole_metres_read_as_whole_metres_are_accepted(tmp_path):
    codes = np.round(_room()).astype(np.uint16)  # 1..6: whole metres, every code <= 255
    assert read_depth_image(_png(tmp_path / "m.png", codes), "m").max() == pytest.approx(6.0)


def test_no_valid_pixel_isrefused(tmp_path):
    path = _png(tmp_path / "zero.png", np.zeros((8, 8), np.uint16))
    refused(lambda: read_depth_image(path, argument="--depth"), "--depth: ", "at least one valid (non-zero) pixel",
             "none of its 64 pixel(s)")


def test_millimetres_read_as_metres_name_millimetres(tmp_path):
    codes = np.round(_room() * 1000).astype(np.uint16)
    path = _png(tmp_path / "mm.png", codes)
    message = refused(lambda: read_depth_image(path, "m", argument="--depth"), "--depth: expected depth in whole metres",
                       "that looks like millimetres: pass --depth-units mm")
    assert message.index("--depth-units mm") < message.index("--depth-units kitti")  # both fit; mm named first


def test_whole_metres_read_as_millimetres_name_metres(tmp_path):
    codes = np.round(_room(low=1.0, high=9.0)).astype(np.uint16)
    refused(lambda: read_depth_image(_png(tmp_path / "m.png", codes), "mm", argument="--depth"),
             "--depth: ", "whole metres, pass --depth-units m")


def test_real_nyu_depth_read_as_metres_isrefused(nyu_root):
    path = nyu_root / "labeled_crop" / "rawdepth.png"
    refused(lambda: read_depth_image(path, "m", argument="--depth"), "--depth: ", "median of 3161 m",
             "that looks like millimetres: pass --depth-units mm")


def test_unknown_units_name_the_option(tmp_path):
    path = _png(tmp_path / "d.png", np.full((8, 8), 3000, np.uint16))
    refused(lambda: read_depth_image(path, "cm"), "--depth-units: expected one of 'mm', 'm', 'kitti', got 'cm'")


# --------------------------------------------------------------------------- the array check


def test_check_depth_units_on_metres():
    depth = _room().astype(np.float32)
    check_depth_units(depth, "mm", "depth")  # floats are metres already: 0.8-6 m passes
    message = refused(lambda: check_depth_units(depth * 1000, "m", "depth", units_argument=None),
                       "depth: expected depth in whole metres", "that looks like millimetres")
    assert "pass" not in message  # no option to name
    refused(lambda: check_depth_units(depth / 1000, "m", "depth"), "depth: ", "check the unit and scale")
    nan = np.full((4, 4), np.nan, np.float32)
    refused(lambda: check_depth_units(nan, "m", "depth"), "depth: ", "at least one valid")


def test_check_depth_units_on_the_range_edges():
    check_depth_units(np.full((2, 2), 0.2), "m", "depth")
    check_depth_units(np.full((2, 2), 80.0), "m", "depth")
    refused(lambda: check_depth_units(np.full((2, 2), 0.19), "m", "depth"), "depth: ", "median of 0.19 m")
    refused(lambda: check_depth_units(np.full((2, 2), 81.0), "m", "depth"), "depth: ", "median of 81 m")


# --------------------------------------------------------------------------- sizes


def test_depth_and_image_of_different_sizes_name_both():
    check_depth_matches_image((480, 640), (480, 640, 3))
    message = refused(lambda: check_depth_matches_image((240, 320), (480, 640, 3)),
                       "--depth: expected the size of --image, 480x640 (HxW), got 240x320")
    assert message.startswith("--depth")
    refused(lambda: check_depth_matches_image((4, 5), (4, 6), "a/depth.png", "a/rgb.jpg"), "a/depth.png: ", "a/rgb.jpg")
