"""Synthetic indoor rooms at NYU's protocol size (crfdepth/data/synthetic/rooms.py)."""

from __future__ import annotations

import pytest
import torch

from crfdepth.data.nyu.camera import nyu_intrinsics
from crfdepth.data.synthetic.rooms import KINECT_DISPARITY_SCALE, ROOM_SIZE, make_room
from crfdepth.errors import InputError


def test_a_room_is_seeded_and_has_the_protocol_size_and_camera():
    room, again, other = make_room(3), make_room(3), make_room(4)
    assert torch.equal(room.image, again.image) and torch.equal(room.target, again.target)
    assert not torch.equal(room.target, other.target)
    assert room.image.shape == (3, *ROOM_SIZE) and room.target.shape == (1, *ROOM_SIZE)
    assert float(room.image.min()) >= 0.0 and float(room.image.max()) <= 1.0
    # NYU's camera at 320 x 240, centre-cropped to 304 x 228 (what the protocol's transforms give)
    expected = nyu_intrinsics(320, 240)
    expected[0, 2] -= 8
    expected[1, 2] -= 6
    assert torch.allclose(room.K, expected) and room.name == "room-seed3"


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_room_depth_is_dense_indoor_and_quantised_like_a_kinect(seed):
    room = make_room(seed)
    depth = room.target[0]
    assert torch.equal(room.sparse, room.target) and bool((depth > 0).all())
    assert 0.1 <= float(depth.min()) and float(depth.max()) <= 10.0
    steps = KINECT_DISPARITY_SCALE / depth.double()  # whole disparity steps
    assert torch.allclose(steps, steps.round(), atol=1e-3)
    # a room has depth edges (furniture before walls) and smooth surfaces
    jump = (depth[:, 1:] - depth[:, :-1]).abs()
    assert float((jump > 0.3).float().mean()) > 1e-3 and float((jump < 0.05).float().mean()) > 0.8


def test_rooms_have_colour_edges_that_are_not_depth_edges():
    found = 0
    for seed in range(6):
        room = make_room(seed)
        colour = (room.image[:, :, 1:] - room.image[:, :, :-1]).abs().sum(0)
        depth = (room.target[0, :, 1:] - room.target[0, :, :-1]).abs()
        found += int(((colour > 0.3) & (depth < 0.05)).sum())
    assert found > 100  # pictures, doors, rugs and floor boards


@pytest.mark.parametrize("seed", [-1, 1.5, True, "0"])
def test_a_bad_seed_is_refused_naming_it(seed):
    with pytest.raises(InputError, match="^seed: expected"):
        make_room(seed)
