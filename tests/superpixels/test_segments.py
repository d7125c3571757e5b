"""Tests of crfdepth.superpixels.segments: SLIC segments, batched label layout, painting."""

from __future__ import annotations

import pytest
import torch
from skimage.measure import label as connected_components

from crfdepth.errors import InputError
from crfdepth.superpixels.segments import batch_segments, paint, slic_segments


def test_paint_is_piecewise_constant():
    labels = torch.tensor([[0, 0, 1], [2, 1, 1]])
    values = torch.tensor([1.5, 2.5, 3.5], requires_grad=True)
    out = paint(values, labels)
    assert out.tolist() == [[1.5, 1.5, 2.5], [3.5, 2.5, 2.5]]
    out.sum().backward()
    assert values.grad.tolist() == [2.0, 3.0, 1.0]  # gradient = pixel count per node
    rgb = paint(torch.eye(3), labels)
    assert rgb.shape == (3, 2, 3) and rgb[:, 1, 0].tolist() == [0.0, 0.0, 1.0]
    with pytest.raises(InputError, match="labels"):
        paint(torch.ones(2), labels)


def test_slic_segments_are_consecutive_connected_and_array_input_agrees():
    gen = torch.Generator().manual_seed(5)
    coarse = torch.rand(1, 3, 5, 7, generator=gen)
    image = torch.nn.functional.interpolate(coarse, size=(50, 70), mode="bilinear", align_corners=False)[0]
    labels = slic_segments(image, 60)
    assert labels.dtype == torch.int64 and labels.shape == (50, 70)
    s = int(labels.max()) + 1
    assert 0.5 * 60 <= s <= 1.5 * 60
    assert torch.equal(torch.unique(labels), torch.arange(s))
    # enforce_connectivity: each label is one 4-connected region.
    assert connected_components(labels.numpy() + 1, connectivity=1, background=0).max() == s
    assert torch.equal(slic_segments(image.permute(1, 2, 0).numpy(), 60), labels)




def test_batch_segments_renumbers_each_frame_consecutively_after_the_previous():
    labels = torch.tensor([[[5, 5, 9], [7, 9, 9]], [[0, 2, 2], [0, 0, 2]]])
    node, ptr = batch_segments(labels)
    assert ptr.tolist() == [0, 3, 5]
    assert node.tolist() == [[[0, 0, 2], [1, 2, 2]], [[3, 4, 4], [3, 3, 4]]]


def test_slic_batch_equals_each_frame_on_both_backends():
    from crfdepth.superpixels.segments import slic_batch

    generator = torch.Generator().manual_seed(2)
    images = torch.rand(2, 3, 40, 64, generator=generator)
    images[1, :, :, 32:] *= 0.3  # a second frame unlike the first
    for backend in ("torch", "skimage"):
        batch = slic_batch(images, 40, backend=backend)
        assert batch.shape == (2, 40, 64) and batch.dtype == torch.int64
        for k in range(2):
            assert torch.equal(batch[k], slic_segments(images[k], 40, backend=backend))
    with pytest.raises(InputError, match="backend"):
        slic_batch(images, 40, backend="opencv")
    with pytest.raises(InputError, match=r"image: expected a \(B, 3, H, W\)"):
        slic_batch(images[0], 40)
