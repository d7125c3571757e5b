"""The learned potential head (crfdepth/potentials/head.py)."""

from __future__ import annotations

import torch

from crfdepth.potentials.head import PotentialHead


def _inputs(h=12, w=16):
    g = torch.Generator().manual_seed(0)
    image = torch.rand(2, 3, h, w, generator=g)
    sparse = torch.where(torch.rand(2, 1, h, w, generator=g) < 0.2, 10.0, 0.0)
    return image, sparse, torch.full((2, 1, h, w), 10.0)


def test_a_fresh_head_changes_nothing():
    data, edge = PotentialHead()(*_inputs())
    assert data.shape == (2, 1, 12, 16) and edge.shape == (2, 2, 12, 16)
    assert bool((data == 1).all()) and bool((edge == 1).all())


def test_factors_stay_within_exp_of_the_limit_whatever_the_weights():
    head = PotentialHead(limit=2.0)
    with torch.no_grad():
        for p in head.parameters():
            p.normal_(std=50.0, generator=torch.Generator().manual_seed(1))
    data, edge = head(*_inputs())
    for f in (data, edge):
        assert float(f.min()) >= torch.exp(torch.tensor(-2.0)) - 1e-6
        assert float(f.max()) <= torch.exp(torch.tensor(2.0)) + 1e-5
    assert float(torch.cat([data.flatten(), edge.flatten()]).std()) > 0.1
