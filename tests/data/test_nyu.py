"""Tests of the NYU Depth v2 datasets, camera and protocol (crfdepth/data/nyu/).

Real frames from ../shared/data/nyu (the ``nyu_root`` fixture: skipped where absent, failing under CI);
every layout is also written into tmp_path from synthetic arrays, so that the tests run without them.
"""

from __future__ import annotations

import shutil
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch

from crfdepth.data import build_dataset
from crfdepth.data.nyu import NYU_K, NyuH5, NyuRawFilled, NyuSync, nyu_intrinsics
from crfdepth.data.sample import Sample
from crfdepth.data.sampling import Resize
from crfdepth.errors import InputError
from tests.refusals import refused

h5py = pytest.importorskip("h5py")

SHARED_NYU = Path(__file__).resolve().parents[2].parent / "shared" / "data" / "nyu"


def _synthetic_frame(height=480, width=640, seed=0, holes=0.3) -> tuple[np.ndarray, np.ndarray]:
    """(H, W, 3) uint8 RGB and (H, W) uint16 millimetres (0 = hole) of a room-like frame."""
    rng = np.random.default_rng(seed)
    rgb = rng.integers(0, 256, (height, width, 3), dtype=np.uint8)
    rows = np.linspace(1.0, 4.0, height)[:, None] + np.linspace(0.0, 1.0, width)[None, :]
    mm = np.round(rows * 1000).astype(np.uint16)
    mm[rng.random((height, width)) < holes] = 0
    return rgb, mm


def _write_sync(folder: Path, index: str, rgb: np.ndarray, mm: np.ndarray) -> None:
    folder.mkdir(parents=True, exist_ok=True)
    assert cv2.imwrite(str(folder / f"rgb_{index}.jpg"), cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR))
    assert cv2.imwrite(str(folder / f"sync_depth_{index}.png"), mm)


@pytest.fixture
def sync_root(tmp_path) -> Path:
    """A sync tree of two synthetic scenes, 640 x 480."""
    for scene, index, seed in [("kitchen_0001", "00001", 0), ("kitchen_0001", "00002", 1), ("office", "00007", 2)]:
        _write_sync(tmp_path / "sync" / scene, index, *_synthetic_frame(seed=seed))
    return tmp_path / "sync"


def _s2d_arrays() -> tuple[np.ndarray, np.ndarray]:
    """``rgb`` (3, 480, 640) uint8 and ``depth`` (480, 640) float32 metres: the real basement frame when
    ../shared/data/nyu is there, else synthetic arrays."""
    folder = SHARED_NYU / "official_test" / "basement"
    if folder.is_dir():
        rgb = cv2.cvtColor(cv2.imread(str(folder / "rgb_00000.jpg")), cv2.COLOR_BGR2RGB)
        mm = cv2.imread(str(folder / "sync_depth_00000.png"), cv2.IMREAD_UNCHANGED)
    else:
        rgb, mm = _synthetic_frame()
    return np.ascontiguousarray(rgb.transpose(2, 0, 1)), (mm / 1000.0).astype(np.float32)


def _write_h5(path: Path, **datasets) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    with h5py.File(path, "w") as f:
        for key, value in datasets.items():
            f.create_dataset(key, data=value)
    return path


@pytest.fixture
def h5_root(tmp_path) -> Path:
    """A Sparse-to-Dense tree: ``nyudepthv2/train/<2 scenes>/<n>.h5`` and ``nyudepthv2/val/official/00001.h5``."""
    rgb, depth = _s2d_arrays()
    root = tmp_path / "nyudepthv2"
    _write_h5(root / "train" / "basement_0001a" / "00001.h5", rgb=rgb, depth=depth)
    _write_h5(root / "train" / "basement_0001a" / "00006.h5", rgb=rgb[:, :, ::-1].copy(), depth=depth[:, ::-1].copy())
    _write_h5(root / "train" / "cafe_0001a" / "00001.h5", rgb=rgb, depth=depth * 1.5)
    _write_h5(root / "val" / "official" / "00001.h5", rgb=rgb, depth=depth)
    return root


# --------------------------------------------------------------------------- camera


def test_nyu_intrinsics_at_the_shipped_sizes():
    assert torch.equal(nyu_intrinsics(640, 480), NYU_K) and NYU_K.dtype == torch.float32
    crop = nyu_intrinsics(560, 425)  # the labeled set's crop, top-left (40, 44)
    assert crop[0, 2].item() == pytest.approx(285.58, abs=1e-4) and crop[1, 2].item() == pytest.approx(209.74, abs=1e-4)
    assert crop[0, 0].item() == pytest.approx(518.86, abs=1e-4)
    quarter = nyu_intrinsics(160, 120)
    assert quarter[0, 0].item() == pytest.approx(518.86 / 4, abs=1e-4)
    assert quarter[1, 1].item() == pytest.approx(519.47 / 4, abs=1e-4)
    assert quarter[0, 2].item() == pytest.approx((325.58 + 0.5) / 4 - 0.5, abs=1e-4)  # pixel centres
    shifted = nyu_intrinsics(600, 400, crop=(10, 20))
    assert shifted[0, 2].item() == pytest.approx(315.58, abs=1e-4) and shifted[1, 2].item() == pytest.approx(233.74, abs=1e-4)


def test_nyu_intrinsics_agree_with_the_protocol_resize():
    frame = Sample(image=torch.zeros(3, 480, 640), sparse=torch.zeros(1, 480, 640), target=torch.zeros(1, 480, 640),
                   K=NYU_K.clone(), name="f")
    torch.testing.assert_close(Resize(240, 320)(frame).K, nyu_intrinsics(320, 240), atol=1e-4, rtol=0)


def test_nyu_intrinsics_of_an_unknown_size_arerefused():
    refused(lambda: nyu_intrinsics(500, 400), "width, height: expected a NYU v2 frame of 640x480", "got 500x400")
    refused(lambda: nyu_intrinsics(600, 400, crop=(50, 0)), "crop: expected (left, top) of a 600x400 window",
             "got (50, 0)")


# --------------------------------------------------------------------------- NyuSync


def test_sync_real_frames(nyu_root):
    ds = NyuSync(nyu_root / "official_test")
    assert ds.names == ["basement_00000", "basement_00050", "basement_00100"] and len(ds) == 3
    s = ds[0]
    assert s.size == (480, 640) and torch.equal(s.K, NYU_K)
    codes = cv2.imread(str(nyu_root / "official_test" / "basement" / "sync_depth_00000.png"), cv2.IMREAD_UNCHANGED)
    torch.testing.assert_close(s.target[0], torch.from_numpy(codes / 1000.0).float(), atol=1e-6, rtol=0)
    assert torch.equal(s.sparse, s.target) and 0.70 < (s.sparse > 0).float().mean().item() < 0.76
    assert 0.0 <= s.image.min() and s.image.max() <= 1.0 and s.image.std() > 0.05


def test_sync_scaled_frames_get_a_scaled_k(nyu_root, tmp_path):
    tiny = nyu_root / "tiny"
    scene = tmp_path / "bookstore"
    scene.mkdir()
    shutil.copy(tiny / "bookstore_0001d_00001.jpg", scene / "rgb_00001.jpg")
    shutil.copy(tiny / "bookstore_0001d_00001.png", scene / "sync_depth_00001.png")
    s = NyuSync(tmp_path)[0]
    assert s.name == "bookstore_00001" and s.size == (120, 160)
    torch.testing.assert_close(s.K, nyu_intrinsics(160, 120))
    assert s.K[0, 0].item() == pytest.approx(518.86 * 0.25, abs=1e-4)


def test_sync_synthetic_tree(sync_root):
    ds = NyuSync(sync_root)
    assert ds.names == ["kitchen_0001_00001", "kitchen_0001_00002", "office_00007"]
    s = ds[2]
    _, mm = _synthetic_frame(seed=2)
    torch.testing.assert_close(s.target[0], torch.from_numpy(mm / 1000.0).float(), atol=1e-6, rtol=0)
    assert NyuSync(sync_root / "office").names == ["office_00007"]  # a scene folder as the root


# --------------------------------------------------------------------------- the protocol


@pytest.mark.parametrize("layout, folder", [("nyu_sync", "official_test"), ("nyu_raw", "labeled_crop")])
def test_protocol_on_real_frames(nyu_root, layout, folder):
    ds = build_dataset(layout, nyu_root / folder, samples=500, seed=0)
    full = build_dataset(layout, nyu_root / folder)
    for i in range(len(ds)):
        s, whole = ds[i], full[i]
        assert s.size == (228, 304) and whole.size[0] > 228
        drawn = s.sparse > 0
        assert int(drawn.sum()) == 500
        assert torch.equal(s.sparse[drawn], s.target[drawn])  # every sample is a ground-truth depth
        assert float(s.target.gt(0).float().mean()) > 0.6  # the target is kept whole


def test_protocol_k_and_pixels_follow_resize_and_crop(nyu_root):
    s = build_dataset("nyu_sync", nyu_root / "official_test", samples=500)[0]
    expected = NYU_K.clone().double()
    expected[:2] *= 0.5
    expected[0, 2] = (325.58 + 0.5) * 0.5 - 0.5 - 8
    expected[1, 2] = (253.74 + 0.5) * 0.5 - 0.5 - 6
    torch.testing.assert_close(s.K.double(), expected, atol=1e-4, rtol=0)
    whole = NyuSync(nyu_root / "official_test")[0]
    # nearest: output pixel (r, c) of the crop is input pixel (2 (r + 6) + 1, 2 (c + 8) + 1)
    torch.testing.assert_close(s.target[0], whole.target[0, 13:13 + 2 * 228:2, 17:17 + 2 * 304:2])


def test_protocol_draws_are_deterministic_per_seed_and_frame(sync_root):
    a = build_dataset("nyu_sync", sync_root, samples=100, seed=0)
    b = build_dataset("nyu_sync", sync_root, samples=100, seed=0)
    c = build_dataset("nyu_sync", sync_root, samples=100, seed=1)
    assert torch.equal(a[0].sparse, b[0].sparse) and torch.equal(a[1].sparse, b[1].sparse)
    assert not torch.equal(a[0].sparse > 0, c[0].sparse > 0)
    assert not torch.equal(a[0].sparse > 0, a[1].sparse > 0)  # another frame, another draw


def test_samples_without_the_protocol_keep_the_full_frame(sync_root):
    s = build_dataset("nyu_sync", sync_root, samples=200, protocol=False)[0]
    assert s.size == (480, 640) and int((s.sparse > 0).sum()) == 200
    cropped = build_dataset("nyu_sync", sync_root, protocol=True)[0]  # resize and crop, the depth as stored
    assert cropped.size == (228, 304) and torch.equal(cropped.sparse, cropped.target)


def test_more_samples_than_valid_pixels_isrefused(sync_root):
    ds = build_dataset("nyu_sync", sync_root, samples=10**6)
    refused(lambda: ds[0], "samples: expected at most the ", "got 1000000")


def test_seed_without_samples_isrefused(sync_root):
    refused(lambda: build_dataset("nyu_sync", sync_root, seed=3), "seed: expected together with samples")


# --------------------------------------------------------------------------- NyuRawFilled


def test_raw_filled_real_crop(nyu_root):
    ds = NyuRawFilled(nyu_root / "labeled_crop")
    assert ds.names == ["labeled_crop"]
    s = ds[0]
    assert s.size == (425, 560)
    assert s.K[0, 2].item() == pytest.approx(285.58, abs=1e-4) and s.K[1, 2].item() == pytest.approx(209.74, abs=1e-4)
    assert 0.82 < (s.sparse > 0).float().mean().item() < 0.85 and bool((s.target > 0).all())
    assert NyuRawFilled(nyu_root).names == ["labeled_crop"]  # found under a parent folder


def test_raw_filled_synthetic_folders(tmp_path):
    for name, seed in [("a", 0), ("b", 1)]:
        rgb, mm = _synthetic_frame(240, 320, seed=seed)
        (tmp_path / name).mkdir()
        cv2.imwrite(str(tmp_path / name / "images.png"), rgb)
        cv2.imwrite(str(tmp_path / name / "rawdepth.png"), mm)
        cv2.imwrite(str(tmp_path / name / "depth.png"), np.where(mm > 0, mm, 2500).astype(np.uint16))
    ds = NyuRawFilled(tmp_path)
    assert ds.names == ["a", "b"]
    s = ds[1]
    torch.testing.assert_close(s.K, nyu_intrinsics(320, 240))
    assert bool((s.target > 0).all()) and (s.sparse == 0).any()
    (tmp_path / "b" / "depth.png").unlink()
    refused(lambda: NyuRawFilled(tmp_path), "root: expected images.png, rawdepth.png, depth.png together in",
             "got no depth.png")


# --------------------------------------------------------------------------- NyuH5


def test_h5_tree_splits_and_names(h5_root):
    train = NyuH5(h5_root, split="train")
    assert train.names == ["basement_0001a_00001", "basement_0001a_00006", "cafe_0001a_00001"]
    assert NyuH5(h5_root, split="val").names == ["official_00001"]
    assert NyuH5(h5_root).names == [*train.names, "official_00001"]
    assert NyuH5(h5_root / "train").names == train.names == NyuH5(h5_root / "train", split="train").names
    rgb, depth = _s2d_arrays()
    s = train[0]
    assert s.size == (480, 640) and torch.equal(s.K, NYU_K)
    torch.testing.assert_close(s.image, torch.from_numpy(rgb).float() / 255)
    torch.testing.assert_close(s.target[0], torch.from_numpy(depth))
    assert torch.equal(s.sparse, s.target)


def test_h5_protocol_through_the_factory(h5_root):
    ds = build_dataset("nyu_h5", h5_root, split="val", samples=500, seed=0)
    s = ds[0]
    assert s.size == (228, 304) and int((s.sparse > 0).sum()) == 500
    drawn = s.sparse > 0
    assert torch.equal(s.sparse[drawn], s.target[drawn])


def test_h5_bad_split(h5_root):
    refused(lambda: NyuH5(h5_root, split="test"), "split: expected one of 'train', 'val' or None, got 'test'")
    refused(lambda: NyuH5(h5_root / "train", split="val"), "split: expected 'train' or None")
    shutil.rmtree(h5_root / "val")
    refused(lambda: NyuH5(h5_root, split="val"), "split: expected a val/ folder in")


@pytest.mark.parametrize("datasets, words", [
    ({"rgb": np.zeros((3, 480, 640), np.uint8)}, ["'depth'", "(480, 640)", "got the keys ['rgb']"]),
    ({"depth": np.ones((480, 640), np.float32)}, ["'rgb'", "(3, 480, 640)"]),
    ({"rgb": np.zeros((480, 640, 3), np.uint8), "depth": np.ones((480, 640), np.float32)},
     ["expected 'rgb' of shape (3, 480, 640)", "got shape (480, 640, 3) uint8"]),
    ({"rgb": np.zeros((3, 480, 640), np.uint8), "depth": np.ones((240, 320), np.float32)},
     ["expected 'depth' of shape (480, 640)", "got shape (240, 320) float32"]),
    ({"rgb": np.zeros((3, 480, 640), np.float32), "depth": np.ones((480, 640), np.float32)},
     ["expected 'rgb' of shape (3, 480, 640) (uint8 RGB)", "float32"]),
    ({"rgb": np.zeros((3, 480, 640), np.uint8), "depth": np.zeros((480, 640), np.float32)},
     ["'depth': expected a depth image with at least one valid"]),
    ({"rgb": np.zeros((3, 480, 640), np.uint8), "depth": np.full((480, 640), 3000.0, np.float32)},
     ["'depth': expected depth in whole metres", "that looks like millimetres"]),
], ids=["no-depth", "no-rgb", "rgb-hwc", "depth-small", "rgb-float", "depth-empty", "depth-mm"])
def test_bad_h5_files_name_the_file_and_key(tmp_path, datasets, words):
    file = _write_h5(tmp_path / "val" / "official" / "00001.h5", **datasets)
    ds = NyuH5(tmp_path / "val")
    refused(lambda: ds[0], str(file), *words)


def test_a_file_that_is_not_hdf5(tmp_path):
    (tmp_path / "scene").mkdir()
    (tmp_path / "scene" / "1.h5").write_text("not hdf5")
    refused(lambda: NyuH5(tmp_path)[0], str(tmp_path / "scene" / "1.h5"), "does not open")


def test_h5_without_h5py_names_the_extra(h5_root, monkeypatch):
    monkeypatch.setitem(sys.modules, "h5py", None)  # import h5py now raises ImportError
    refused(lambda: NyuH5(h5_root), 'pip install "crfdepth[nyu]"')


# --------------------------------------------------------------------------- roots and bad files


@pytest.mark.parametrize("layout", ["nyu_sync", "nyu_raw", "nyu_h5"])
def test_roots_without_frames_name_root(tmp_path, layout):
    missing = tmp_path / "nope"
    refused(lambda: build_dataset(layout, missing), "root: expected a folder of the", str(missing), "does not exist")
    (tmp_path / "empty").mkdir()
    refused(lambda: build_dataset(layout, tmp_path / "empty"), "root: expected a folder of the", "got no frame in")
    (tmp_path / "file").write_text("x")
    refused(lambda: build_dataset(layout, tmp_path / "file"), "root: ", "got a file")


def test_sync_image_without_depth_and_depth_without_image(tmp_path):
    _write_sync(tmp_path / "s", "00001", *_synthetic_frame(48, 64))
    (tmp_path / "s" / "sync_depth_00001.png").rename(tmp_path / "s" / "sync_depth_00002.png")
    message = refused(lambda: NyuSync(tmp_path), "root: expected sync_depth_00001.png beside")
    assert "rgb_00001.jpg" in message
    (tmp_path / "s" / "rgb_00001.jpg").unlink()
    refused(lambda: NyuSync(tmp_path), "root: expected rgb_00002.jpg beside", "sync_depth_00002.png")


def test_sync_depth_of_another_size_names_both_files(tmp_path):
    rgb, mm = _synthetic_frame()
    _write_sync(tmp_path / "s", "00001", rgb, mm[::2, ::2].copy())
    depth, image = tmp_path / "s" / "sync_depth_00001.png", tmp_path / "s" / "rgb_00001.jpg"
    refused(lambda: NyuSync(tmp_path)[0], f"{depth}: expected the size of {image}, 480x640 (HxW), got 240x320")


@pytest.mark.parametrize("depth, words", [
    (lambda mm: np.round(mm / 1000.0).astype(np.uint16), ["codes all <= 255", "whole metres"]),  # whole metres
    (lambda mm: (mm // 40).astype(np.uint8), ["single-channel 16-bit", "a visualisation, not depth codes"]),
    (lambda mm: ((mm // 40).clip(0, 255) * 257).astype(np.uint16), ["multiple of 257"]),
    (lambda mm: np.zeros_like(mm), ["at least one valid (non-zero) pixel"]),
    (lambda mm: mm // 18, ["expected depth in millimetres with a median of 0.2 to 80 m", "got a median of 0.1",
                           "that looks like KITTI codes"]),  # 1.8 cm codes: nearer than a Kinect sees
], ids=["whole-metres", "8-bit", "x257", "empty", "too-shallow"])
def test_sync_depth_files_not_in_millimetres_arerefused(tmp_path, depth, words):
    rgb, mm = _synthetic_frame(48, 64)
    _write_sync(tmp_path / "s", "00001", rgb, depth(mm))
    with pytest.raises(InputError) as info:
        NyuSync(tmp_path)[0]
    message = str(info.value)
    assert message.startswith(str(tmp_path / "s" / "sync_depth_00001.png")), message
    for word in words:
        assert word in message, (word, message)
    assert "--depth-units" not in message  # the layout fixes the unit: no option to name
