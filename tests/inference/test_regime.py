"""The default model's indoor regime: few scattered returns at a room's depths go to the indoor weights
(crfdepth/inference/regime.py, docs/design.md section 17)."""

from __future__ import annotations

import pytest
import torch

from crfdepth.data.nyu.layouts import build_nyu_dataset
from crfdepth.inference.coarse import returns_layout
from crfdepth.inference.regime import INDOOR_RANGE, near_returns
from crfdepth.model import CRFDepth
from tests.scenes import table4_frames


def _scattered(depths, count=150, h=120, w=200, seed=0):
    """(1, 1, h, w): ``count`` random returns whose depths cycle through ``depths`` (metres)."""
    g = torch.Generator().manual_seed(seed)
    sparse = torch.zeros(1, 1, h, w)
    pick = torch.randperm(h * w, generator=g)[:count]
    sparse.view(-1)[pick] = torch.tensor(depths, dtype=torch.float32).repeat(count // len(depths) + 1)[:count]
    return sparse


def _frame(sparse, seed=0):
    h, w = sparse.shape[2:]
    g = torch.Generator().manual_seed(seed)
    image = torch.rand(1, 3, h, w, generator=g) * 0.05 + 0.4
    image[..., w // 2:] += 0.3
    K = torch.tensor([[150.0, 0.0, w / 2], [0.0, 150.0, h / 2], [0.0, 0.0, 1.0]])[None]
    return image, sparse, K


def test_near_returns_reads_the_90th_percentile_of_the_depths():
    # 10 depths a frame: the 90th percentile is the 9th smallest
    rows = torch.ones(4, dtype=torch.bool)
    frames = torch.cat([_scattered([2.0] * 9 + [80.0]),  # one far return in ten: a window, still a room
                        _scattered([2.0] * 8 + [30.0, 80.0]),  # two in ten: outdoors
                        _scattered([INDOOR_RANGE] * 10),  # at the range: near
                        _scattered([INDOOR_RANGE + 0.5] * 10)])
    assert near_returns(frames, rows).tolist() == [True, False, True, False]
    # only the frames asked about are read
    assert near_returns(frames, torch.tensor([False, True, True, False])).tolist() == [False, False, True, False]


def test_indoor_regime_is_the_nyu_weights_and_only_in_the_adaptive_default():
    model = CRFDepth.from_pretrained()
    nyu = CRFDepth.from_pretrained("nyu")
    assert model.indoor_regime is not None and not model.indoor_regime.training
    assert model.indoor_regime.config == nyu.config
    assert model.indoor_regime.weights() == pytest.approx(nyu.weights(), rel=1e-6)
    assert CRFDepth.from_pretrained(adaptive=False).indoor_regime is None
    assert CRFDepth.from_pretrained(mode="superpixel").indoor_regime is None
    assert nyu.indoor_regime is None and CRFDepth.from_pretrained("paper").indoor_regime is None
    assert set(model.state_dict()) == set(CRFDepth.from_pretrained(adaptive=False).state_dict())
    model.double()
    assert all(p.dtype == torch.float64 for p in model.indoor_regime.parameters())


def test_each_frame_of_a_batch_goes_to_its_regime():
    model = CRFDepth.from_pretrained()
    room = _scattered([1.5, 2.5, 3.5, 4.5, 6.0])
    street = _scattered([5.0, 12.0, 20.0, 35.0, 60.0], seed=1)
    assert returns_layout(room)[0].item() and not returns_layout(room)[1].item()
    image, _, K = _frame(room)
    with torch.no_grad():
        assert torch.equal(model(image, room, K).depth, model.indoor_regime(image, room, K).depth)
        assert torch.equal(model(image, street, K).depth, model.sparse_regime(image, street, K).depth)
        both = model(torch.cat([image, image]), torch.cat([street, room]), K[0], return_std=True)
        alone = model.indoor_regime(image, room, K, return_std=True)
    assert torch.allclose(both.depth[1], alone.depth[0], rtol=1e-5, atol=1e-5)
    assert torch.allclose(both.std[1], alone.std[0], rtol=1e-5, atol=1e-5)
    # the indoor weights and the scattered regime's hand-set ones give different maps
    assert not torch.allclose(both.depth[0], model.indoor_regime(image, street, K).depth[0], rtol=1e-3)


def test_real_frames_go_to_the_regime_of_their_sensor(nyu_root, kitti_root):
    nyu = build_nyu_dataset("nyu_sync", nyu_root / "official_test", samples=500, seed=0)
    for s in nyu:
        sparse = s.sparse[None]
        few, lines = returns_layout(sparse)
        assert bool(few) and not bool(lines)
        assert bool(near_returns(sparse, few))
    for n in (500, 200):
        for t in table4_frames(kitti_root, n, step=3):
            assert not bool(near_returns(t.sparse[None], torch.ones(1, dtype=torch.bool))), (t.name, n)


@pytest.mark.parametrize("samples", [500, 200])
def test_default_completes_real_indoor_frames_with_the_indoor_weights(nyu_root, samples):
    frames = build_nyu_dataset("nyu_sync", nyu_root / "official_test", samples=samples, seed=0)
    default, nyu = CRFDepth.from_pretrained(), CRFDepth.from_pretrained("nyu")
    for s in frames:
        with torch.no_grad():
            assert torch.equal(default(s.image[None], s.sparse[None], s.K[None]).depth,
                               nyu(s.image[None], s.sparse[None], s.K[None]).depth)


def test_each_part_is_told_the_layout_block_shape_would_read():
    from crfdepth.inference.coarse import line_scan
    from crfdepth.inference.regime import assign

    model = CRFDepth.from_pretrained()
    rings = torch.zeros(1, 1, 120, 200)
    rings[..., 4::24, :] = 20.0
    room, street = _scattered([1.5, 2.5, 4.0]), _scattered([5.0, 20.0, 40.0], seed=1)
    dense = torch.zeros(1, 1, 120, 200)
    dense[..., ::2, ::2] = 20.0
    batch = torch.cat([dense, street, room, rings])
    got = {id(m): (rows.tolist(), lines) for rows, m, lines in assign(model, batch)}
    assert got == {id(model): ([0], None), id(model.sparse_regime): ([1], False),
                   id(model.indoor_regime): ([2], False), id(model.line_regime): ([3], True)}
    # without a line regime the rings go to the scattered regime, which is told they are rings (tall blocks)
    model.line_regime = None
    parts = assign(model, torch.cat([rings, rings]))
    assert [(rows.tolist(), m is model.sparse_regime, lines) for rows, m, lines in parts] == [([0, 1], True, True)]
    assert bool(line_scan(rings).all())
