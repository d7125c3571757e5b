"""Tests for Sample, Batch and collate_samples (crfdepth/data/sample.py)."""

from __future__ import annotations

import dataclasses

import pytest
import torch
from torch.utils.data import DataLoader

from crfdepth.data.sample import Batch, collate_samples
from crfdepth.errors import InputError


def test_sample_rejects_mismatched_shapes(make_sample):
    s = make_sample(8, 10)
    with pytest.raises(InputError, match=r"Sample.sparse: expected a \(1, 8, 10\)"):
        dataclasses.replace(s, sparse=torch.zeros(1, 8, 11))
    with pytest.raises(InputError, match=r"Sample.image: expected a \(3, H, W\)"):
        dataclasses.replace(s, image=torch.zeros(1, 8, 10))
    with pytest.raises(InputError, match=r"Sample.K: expected a \(3, 3\)"):
        dataclasses.replace(s, K=torch.eye(4))
    assert s.size == (8, 10)


def test_collate_stacks_and_dataloader_uses_it(make_sample):
    samples = [make_sample(16, 24, name=f"f{i}", seed=i) for i in range(3)]
    samples[2] = dataclasses.replace(samples[2], target=torch.zeros(1, 16, 24), has_target=False)
    batch = collate_samples(samples)
    assert isinstance(batch, Batch) and len(batch) == 3
    assert batch.image.shape == (3, 3, 16, 24) and batch.sparse.shape == (3, 1, 16, 24)
    assert batch.target.shape == (3, 1, 16, 24) and batch.K.shape == (3, 3, 3)
    assert batch.K.dtype == torch.float32
    assert batch.names == ["f0", "f1", "f2"]
    assert batch.has_target.tolist() == [True, True, False]
    torch.testing.assert_close(batch.sparse[1], samples[1].sparse, rtol=0, atol=0)

    loader = DataLoader(samples, batch_size=2, collate_fn=collate_samples)
    sizes = [len(b) for b in loader]
    assert sizes == [2, 1]
    moved = batch.to(torch.float64)
    assert moved.image.dtype == torch.float64 and moved.has_target.dtype == torch.bool


def test_collate_errors_name_sizes(make_sample):
    with pytest.raises(InputError, match="empty list"):
        collate_samples([])
    with pytest.raises(InputError, match=r"'a' is \(8, 10\) but 'b' is \(8, 12\)"):
        collate_samples([make_sample(8, 10, name="a"), make_sample(8, 12, name="b")])
