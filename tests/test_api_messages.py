"""Messages that named an internal value or leaked a library's error (issue 25, poor messages):
a 1x1 image, ``device='tpu'``, a channel mismatch in ``CRFRefine``."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
import torch

from crfdepth import api, cli
from crfdepth.errors import InputError
from crfdepth.io.kitti import write_depth_png
from crfdepth.layer import CRFRefine, crf_refine
from crfdepth.model import CRFDepth

SIZE_MESSAGE = ("expected at least 2x2 pixels (the CRF's 4-neighbour edges and the LiDAR normals need 2 rows and 2 "
                "columns), got {w}x{h} (WxH)")


@pytest.fixture
def main(monkeypatch):
    monkeypatch.setattr(cli, "_COMMANDS", ("crfdepth.cli.complete",))
    return cli.main


def _frame(h: int, w: int) -> tuple[np.ndarray, np.ndarray, list]:
    rgb = np.full((h, w, 3), 120, np.uint8)
    sparse = np.zeros((h, w), np.float32)
    sparse[0, 0] = 5.0
    return rgb, sparse, [[50.0, 0.0, w / 2], [0.0, 50.0, h / 2], [0.0, 0.0, 1.0]]


# --------------------------------------------------------------------------- image size


@pytest.mark.parametrize("h, w", [(1, 1), (1, 7), (7, 1)])
def test_complete_depth_too_small_image_names_image_and_minimum(h, w):
    rgb, sparse, K = _frame(h, w)
    with pytest.raises(InputError) as err:
        api.complete_depth(rgb, sparse=sparse, K=K)
    assert str(err.value) == "image: " + SIZE_MESSAGE.format(w=w, h=h)
    assert "depth" not in str(err.value).split(":")[0]


def test_smallest_image_is_accepted():
    rgb, sparse, K = _frame(2, 2)
    depth, std = api.complete_depth(rgb, sparse=sparse, K=K)
    assert depth.shape == (2, 2) and float(depth.min()) > 0 and std.shape == (2, 2)


@pytest.mark.parametrize("mode", ["superpixel", "pixel"])
def test_model_forward_too_small_image_names_image(mode):
    with pytest.raises(InputError) as err:
        CRFDepth(mode=mode)(torch.rand(1, 3, 1, 1), torch.ones(1, 1, 1, 1), torch.eye(3))
    assert str(err.value) == "image: " + SIZE_MESSAGE.format(w=1, h=1)


def test_cli_one_pixel_image_names_the_image_flag(main, capsys, tmp_path):
    rgb, sparse, _ = _frame(1, 1)
    image, sparse_png, K = tmp_path / "rgb.png", tmp_path / "sparse.png", tmp_path / "K.txt"
    assert cv2.imwrite(str(image), rgb)
    write_depth_png(sparse_png, sparse)
    K.write_text("50 0 0.5\n0 50 0.5\n0 0 1\n")
    out = tmp_path / "depth.png"
    code = main(["complete", "--image", str(image), "--sparse", str(sparse_png), "--intrinsics", str(K),
                 "--out", str(out), "--quiet"])
    assert code == 2
    assert capsys.readouterr().err.splitlines()[0] == (
        f"crfdepth complete: error: --image {image}: " + SIZE_MESSAGE.format(w=1, h=1))
    assert not out.exists()


# --------------------------------------------------------------------------- device


@pytest.mark.parametrize("device", ["tpu", "cuda:x", "meta", 3.5])
def test_unknown_device_names_device_and_lists_the_accepted(device):
    rgb, sparse, K = _frame(8, 8)
    with pytest.raises(InputError) as err:
        api.complete_depth(rgb, sparse=sparse, K=K, device=device)
    message = str(err.value)
    assert message.startswith("device: expected 'cpu', 'cuda', 'cuda:N' or 'mps' (a str or torch.device; "
                              "available here: 'cpu'")
    assert message.endswith(f"got {device!r}")


def test_device_torch_device_and_cpu_string_are_accepted():
    rgb, sparse, K = _frame(8, 8)
    a, _ = api.complete_depth(rgb, sparse=sparse, K=K, device=torch.device("cpu"), return_std=False)
    b, _ = api.complete_depth(rgb, sparse=sparse, K=K, device="cpu", return_std=False)
    assert a.shape == (8, 8) and np.allclose(a, b, rtol=0, atol=1e-6)


@pytest.mark.skipif(torch.cuda.is_available(), reason="checks the message of a machine without CUDA")
def test_cuda_without_cuda_says_so():
    rgb, sparse, K = _frame(8, 8)
    with pytest.raises(InputError, match=r"^device: CUDA is not available .*use device='cpu'$"):
        api.complete_depth(rgb, sparse=sparse, K=K, device="cuda:0")


# --------------------------------------------------------------------------- CRFRefine channels


def _refine_inputs(channels: int):
    torch.manual_seed(0)
    depth = 5.0 + torch.rand(1, 1, 6, 7)
    return depth, torch.ones_like(depth), torch.rand(1, channels, 6, 7)


def test_crfrefine_channel_mismatch_names_features_and_the_layers_channels():
    layer = CRFRefine(16)
    with pytest.raises(InputError) as err:
        layer(*_refine_inputs(8))
    assert str(err.value) == ("features: expected 16 channels (CRFRefine(in_channels=16)), got 8 (shape (1, 8, 6, 7) "
                              "float32); build the layer with in_channels=8 or give it 16-channel features")
    out = layer(*_refine_inputs(16))
    assert out.depth.shape == (1, 1, 6, 7) and bool(torch.isfinite(out.depth).all())


def test_crf_refine_channel_mismatch_names_features_and_projection_shape():
    depth, confidence, features = _refine_inputs(8)
    with pytest.raises(InputError) as err:
        crf_refine(depth, confidence, features, torch.rand(4, 16))
    assert str(err.value).startswith("features: expected 16 channels, the C of projection_weight (E, C) = (4, 16), "
                                     "got 8 (features shape (1, 8, 6, 7) float32)")
