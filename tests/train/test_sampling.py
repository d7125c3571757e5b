"""train.sampling: the training order (shuffled per epoch, dealt to ranks, resumable) and the frames'
random draws as functions of (seed, epoch, frame)."""

from __future__ import annotations

import pytest
import torch
from torch.utils.data import DistributedSampler

from crfdepth.errors import InputError
from train.data import CRFDataModule
from train.sampling import Draw, EpochOrder, draw_seed, seeded_draws

SMALL = {"height": 40, "width": 96}


def test_two_ranks_share_the_epoch_as_distributed_sampler_deals_it():
    frames = list(range(7))
    shares = []
    for rank in (0, 1):
        order = EpochOrder(frames, num_replicas=2, rank=rank, seed=5)
        order.set_epoch(3)
        reference = DistributedSampler(frames, num_replicas=2, rank=rank, seed=5)
        reference.set_epoch(3)
        items = list(order)
        assert [d.index for d in items] == list(reference)
        assert all(d.seed == draw_seed(5, 3, d.index) for d in items)
        shares.append([d.index for d in items])
    assert len(shares[0]) == len(shares[1]) == 4
    assert set(shares[0]) | set(shares[1]) == set(frames)  # one frame repeated to even the shares
    assert len(set(shares[0]) & set(shares[1])) == 1


def test_a_resumed_epoch_starts_after_its_trained_frames_and_the_next_starts_whole():
    order = EpochOrder(list(range(10)), seed=1)
    order.set_epoch(2)
    whole = list(order)
    order.resume(2, 6)
    assert list(order) == whole[6:]
    order.set_epoch(3)
    assert len(list(order)) == 10
    order.set_epoch(2)
    assert len(list(order)) == 4  # only the epoch it stopped in


def test_the_order_and_the_draws_change_with_the_epoch_and_the_seed():
    order = EpochOrder(list(range(20)), seed=0)
    first = list(order)
    order.set_epoch(1)
    assert [d.index for d in order] != [d.index for d in first]
    assert draw_seed(0, 0, 4) != draw_seed(0, 1, 4) != draw_seed(1, 1, 4)


def test_seeded_draws_repeat_and_leave_the_generator_as_it_was():
    torch.manual_seed(123)
    before = torch.default_generator.get_state()
    with seeded_draws(7):
        a = torch.rand(3)
    with seeded_draws(7):
        b = torch.rand(3)
    assert torch.equal(a, b)
    assert torch.equal(torch.default_generator.get_state(), before)


def _batches(workers: int, epoch: int) -> list:
    data = CRFDataModule(train_options={"count": 4, **SMALL}, val_options={"count": 1, "seed": 1000, **SMALL},
                         flip=0.5, crop=[32, 80], thin=[0.3, 0.9], batch_size=2, num_workers=workers, seed=11)
    data.setup("fit")
    loader = data.train_dataloader()
    loader.sampler.set_epoch(epoch)
    return [(b.names, b.image, b.sparse, b.K) for b in loader]


def test_the_draws_do_not_depend_on_the_number_of_workers():
    alone, workers = _batches(0, 0), _batches(2, 0)
    assert len(alone) == 2
    for (names, image, sparse, K), (names2, image2, sparse2, K2) in zip(alone, workers):
        assert names == names2
        assert torch.equal(image, image2) and torch.equal(sparse, sparse2) and torch.equal(K, K2)
    # and they change from epoch to epoch: another order, other crops or thinning
    later = _batches(0, 1)
    assert any(not torch.equal(a[2], b[2]) for a, b in zip(alone, later))


def test_a_checkpoint_of_another_training_set_is_refused_naming_what_differs():
    data = CRFDataModule(train_options={"count": 4, **SMALL}, val_options={"count": 1, "seed": 1000, **SMALL},
                         batch_size=2)
    data.setup("fit")
    loader = data.train_dataloader()
    state = loader.state_dict()
    assert state == {"epoch": 0, "batches": 0, "seed": loader.sampler.seed, "shuffle": True, "frames": 4,
                     "batch_size": 2, "processes": 1}
    loader.load_state_dict({**state, "epoch": 1, "batches": 1, "seed": 9})
    assert loader.sampler.seed == 9 and loader.sampler.resume_at == (1, 2)
    with pytest.raises(InputError, match=r"--ckpt_path: .*frames 6 then, 4 now, batch_size 1 then, 2 now"):
        loader.load_state_dict({**state, "frames": 6, "batch_size": 1})


def test_loader_items_are_draws():
    data = CRFDataModule(train_options={"count": 3, **SMALL}, val_options={"count": 1, "seed": 1000, **SMALL})
    data.setup("fit")
    items = list(data.train_dataloader().sampler)
    assert all(isinstance(d, Draw) for d in items) and sorted(d.index for d in items) == [0, 1, 2]
