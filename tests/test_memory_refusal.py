"""Frames too large for the memory: refused up front from the shape alone (the API, the model)
or the file header (the CLI), before anything is converted or decoded, and allocator failures
turned into the same kind of one-line error (issue 25, item 6).

No test allocates a large array: the huge images are numpy broadcasts / torch expands of one
pixel (only the shape is large) or PNG headers without pixel data, and the available memory
is monkeypatched where a test needs it small.
"""

from __future__ import annotations

import struct
import time
import tracemalloc
import zlib
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch

from crfdepth import api, cli, memory
from crfdepth import model as model_module
from crfdepth.errors import InputError
from crfdepth.inference import PIPELINES
from crfdepth.io.image_size import read_image_size
from crfdepth.io.kitti import write_depth_png
from crfdepth.memory import MemoryRefusal, available_memory, estimate_bytes
from crfdepth.model import CRFDepth

H, W = 48, 64
K = [[60.0, 0.0, 32.0], [0.0, 60.0, 24.0], [0.0, 0.0, 1.0]]
ALLOCATOR_FAILURE = ("DefaultCPUAllocator: can't allocate memory: you tried to allocate 96000000000 bytes. "
                     "Error code 12 (Cannot allocate memory)")


@pytest.fixture
def main(monkeypatch):
    monkeypatch.setattr(cli, "_COMMANDS", ("crfdepth.cli.complete",))
    return cli.main


def _scene() -> tuple[np.ndarray, np.ndarray]:
    rows, cols = np.mgrid[0:H, 0:W]
    rgb = np.zeros((H, W, 3), np.uint8)
    rgb[:, : W // 2] = (200, 40, 40)
    rgb[:, W // 2:] = (40, 60, 200)
    sparse = np.zeros((H, W), np.float32)
    sparse[4::5, 2::4] = np.where(cols < W // 2, 8.0 + 0.05 * rows, 20.0 - 0.1 * rows)[4::5, 2::4]
    return rgb, sparse


def _frame(folder: Path, image_name: str = "rgb.png") -> dict[str, Path]:
    folder.mkdir(parents=True, exist_ok=True)
    rgb, sparse = _scene()
    paths = {"image": folder / image_name, "sparse": folder / "sparse.png", "intrinsics": folder / "K.txt"}
    assert cv2.imwrite(str(paths["image"]), cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR))
    write_depth_png(paths["sparse"], sparse)
    paths["intrinsics"].write_text("60 0 32\n0 60 24\n0 0 1\n")
    return paths


def _png_header_only(path: Path, width: int, height: int) -> Path:
    """A PNG signature and IHDR chunk of an 8-bit RGB image of this size, with no pixel data."""
    ihdr = struct.pack(">IIBBBBB", width, height, 8, 2, 0, 0, 0)
    chunk = struct.pack(">I", len(ihdr)) + b"IHDR" + ihdr + struct.pack(">I", zlib.crc32(b"IHDR" + ihdr))
    path.write_bytes(b"\x89PNG\r\n\x1a\n" + chunk)
    return path


def _args(frame: dict, out: Path, *extra) -> list[str]:
    return ["complete", "--image", str(frame["image"]), "--sparse", str(frame["sparse"]), "--intrinsics",
            str(frame["intrinsics"]), "--out", str(out), "--quiet", *map(str, extra)]


def _first_line(capsys) -> str:
    return capsys.readouterr().err.splitlines()[0]


# --------------------------------------------------------------------------- the estimate and the limit


def test_available_memory_is_positive_and_at_most_the_machine():
    available = available_memory(torch.device("cpu"))
    assert available is not None and 0 < available <= memory.device_memory(torch.device("cpu"))


def test_limit_is_the_available_memory_unless_memory_limit_gb_is_set(monkeypatch):
    monkeypatch.setattr(memory, "available_memory", lambda device: 2e9)
    with pytest.raises(MemoryRefusal, match=r"more than the memory available on cpu \(2\.0 GB\)"):
        memory.check_memory("pixel", 1, 4000, 3000, False, "predictive", torch.float32, torch.device("cpu"), None)
    # memory_limit_gb is the caller's own limit, used instead of the available memory
    estimate = memory.check_memory("pixel", 1, 4000, 3000, False, "predictive", torch.float32,
                                   torch.device("cpu"), 4.0)
    assert estimate == estimate_bytes("pixel", 12_000_000, False, "predictive") < 4e9
    monkeypatch.setattr(memory, "available_memory", lambda device: None)  # unknown: no check
    assert memory.check_memory("pixel", 1, 40000, 30000, False, "predictive", torch.float32,
                               torch.device("cpu"), None) > 1e11


# --------------------------------------------------------------------------- the Python API


def test_complete_depth_refuses_a_huge_image_before_converting_it(monkeypatch):
    """20000x15000: refused from the shape, before the float conversion (3.6 GB) or any check allocates."""
    monkeypatch.setattr(memory, "available_memory", lambda device: 16e9)
    image = np.broadcast_to(np.zeros((1, 1, 3), np.uint8), (15000, 20000, 3))  # 3 bytes of data
    sparse = np.broadcast_to(np.ones((1, 1), np.float32), (15000, 20000))
    K_big = [[1e4, 0, 1e4], [0, 1e4, 7500], [0, 0, 1]]
    tracemalloc.start()
    try:
        start = time.perf_counter()
        with pytest.raises(InputError) as err:
            api.complete_depth(image, sparse=sparse, K=K_big)
        seconds = time.perf_counter() - start
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    message = str(err.value)
    estimate = estimate_bytes("pixel", 20000 * 15000, True, "predictive")  # the default model, with the std
    assert message.startswith("image: a frame of 20000x15000 pixels needs about ")
    assert f"about {estimate / 1e9:.1f} GB" in message and "(16.0 GB)" in message
    assert "memory_limit_gb" in message and "smaller image" in message and "\n" not in message
    assert peak < 20e6  # bytes traced by Python and numpy: nothing per pixel (the image alone is 900 MB)
    assert seconds < 5.0


def test_complete_depth_refuses_from_memory_limit_gb_before_any_check(monkeypatch):
    def converted(*args, **kwargs):  # pragma: no cover - must not be reached
        raise AssertionError("the image was converted before the memory check")

    monkeypatch.setattr(api, "image_to_numpy", converted)
    rgb, sparse = _scene()
    model = CRFDepth(mode="pixel", memory_limit_gb=0.1)  # below the fixed overhead of any frame
    with pytest.raises(MemoryRefusal, match=r"^image: a frame of 64x48 pixels needs about 0\.3 GB .*more than "
                                            r"memory_limit_gb \(0\.1 GB\)"):
        api.complete_depth(rgb, sparse=sparse, K=K, model=model)


def test_complete_depth_tensor_image_is_measured_in_either_layout(monkeypatch):
    monkeypatch.setattr(memory, "available_memory", lambda device: 1e9)
    for shape in ((3, 15000, 20000), (15000, 20000, 3)):
        image = torch.zeros(1, 1, 1).expand(*shape)
        with pytest.raises(MemoryRefusal, match="image: a frame of 20000x15000 pixels"):
            api.complete_depth(image, sparse=torch.zeros(1, 1).expand(15000, 20000), K=K)


def _run_instead(monkeypatch, forward) -> None:
    """``forward(model, image, sparse, K, return_std)`` runs in place of the model's pipeline in every mode."""
    for mode in PIPELINES:
        monkeypatch.setitem(PIPELINES, mode, forward)


def test_model_forward_refuses_before_its_input_checks(monkeypatch):
    def checked(*args, **kwargs):  # pragma: no cover - must not be reached
        raise AssertionError("check_frames ran before the memory check")

    monkeypatch.setattr(model_module, "check_frames", checked)
    monkeypatch.setattr(memory, "available_memory", lambda device: 8e9)
    image = torch.zeros(1, 1, 1, 1).expand(2, 3, 4000, 6000)
    sparse = torch.zeros(1, 1, 1, 1).expand(2, 1, 4000, 6000)
    with pytest.raises(MemoryRefusal) as err:
        CRFDepth()(image, sparse, torch.eye(3))
    estimate = estimate_bytes("superpixel", 2 * 6000 * 4000, False, "predictive")
    assert str(err.value).startswith(f"image: a batch of 2 frame(s) of 6000x4000 pixels needs about "
                                     f"{estimate / 1e9:.1f} GB (superpixel mode, float32: about 350 bytes per pixel)")
    assert err.value.estimate == estimate and err.value.limit == 8e9


@pytest.mark.parametrize("failure", [RuntimeError(ALLOCATOR_FAILURE),
                                     torch.cuda.OutOfMemoryError("CUDA out of memory. Tried to allocate 2.00 GiB"),
                                     MemoryError()])
def test_allocator_failure_in_the_forward_is_one_line(monkeypatch, failure):
    def forward(self, *args, **kwargs):
        raise failure

    _run_instead(monkeypatch, forward)
    rgb, sparse = _scene()
    with pytest.raises(MemoryRefusal) as err:
        api.complete_depth(rgb, sparse=sparse, K=K)
    message = str(err.value)
    assert message.startswith("image: a frame of 64x48 pixels ran out of memory on cpu (estimated about 0.3 GB; ")
    assert "GB available on cpu now" in message and "\n" not in message
    assert (str(failure) or "MemoryError") in message


def test_other_runtime_errors_are_not_taken_for_memory(monkeypatch):
    def forward(self, *args, **kwargs):
        raise RuntimeError("some other failure")

    _run_instead(monkeypatch, forward)
    rgb, sparse = _scene()
    with pytest.raises(RuntimeError, match="some other failure") as err:
        api.complete_depth(rgb, sparse=sparse, K=K)
    assert not isinstance(err.value, InputError)


# --------------------------------------------------------------------------- the CLI


def test_image_size_from_png_and_jpeg_headers(tmp_path):
    rgb, _ = _scene()
    for name in ("a.png", "a.jpg"):
        assert cv2.imwrite(str(tmp_path / name), rgb)
        assert read_image_size(tmp_path / name) == (H, W)
    assert read_image_size(_png_header_only(tmp_path / "big.png", 20000, 15000)) == (15000, 20000)
    (tmp_path / "text.png").write_text("not an image")
    assert read_image_size(tmp_path / "text.png") is None and read_image_size(tmp_path / "missing.png") is None


@pytest.mark.parametrize("size, available", [((6000, 4000), 4e9), ((20000, 15000), 64e9)])
def test_cli_refuses_a_huge_png_from_its_header_before_decoding(main, capsys, tmp_path, monkeypatch, size,
                                                                  available):
    monkeypatch.setattr(memory, "available_memory", lambda device: available)
    frame = _frame(tmp_path / "in")
    frame["image"] = _png_header_only(tmp_path / "in" / "huge.png", *size)  # no pixel data: decoding would fail
    out = tmp_path / "depth.png"
    assert main(_args(frame, out)) == 2
    width, height = size
    estimate = estimate_bytes("pixel", width * height, False, "predictive")  # the lightest mode, no std
    assert _first_line(capsys) == (
        f"crfdepth complete: error: --image {frame['image']}: a frame of {width}x{height} pixels needs about "
        f"{estimate / 1e9:.1f} GB (pixel mode, float32: about 250 bytes per pixel), more than the memory available "
        f"on cpu ({available / 1e9:.1f} GB); use a smaller image or --device cuda")
    assert not out.exists() and sorted(p.name for p in tmp_path.iterdir()) == ["in"]


def test_cli_refuses_after_decoding_a_format_without_a_header_check(main, capsys, tmp_path, monkeypatch):
    """A BMP's size is not read from its header; the API's check refuses it after decoding, under the flag."""
    monkeypatch.setattr(memory, "available_memory", lambda device: 0.2e9)  # below the fixed overhead
    frame = _frame(tmp_path / "in", "rgb.bmp")
    out = tmp_path / "depth.png"
    assert main(_args(frame, out, "--mode", "superpixel")) == 2
    assert _first_line(capsys) == (
        f"crfdepth complete: error: --image {frame['image']}: a frame of 64x48 pixels needs about 0.3 GB "
        f"(superpixel mode, float32: about 350 bytes per pixel), more than the memory available on cpu (0.2 GB); "
        f"use a smaller image or --device cuda")
    assert not out.exists()


def test_cli_allocator_failure_exits_2_with_one_line(main, capsys, tmp_path, monkeypatch):
    def forward(self, *args, **kwargs):
        raise RuntimeError(ALLOCATOR_FAILURE)

    _run_instead(monkeypatch, forward)
    frame = _frame(tmp_path / "in")
    out = tmp_path / "depth.png"
    assert main(_args(frame, out, "--mode", "pixel")) == 2
    err = capsys.readouterr().err
    assert len(err.strip().splitlines()) == 1 and "Traceback" not in err
    line = err.splitlines()[0]
    assert line.startswith(f"crfdepth complete: error: --image {frame['image']}: a frame of 64x48 pixels ran out "
                           f"of memory on cpu (estimated about 0.3 GB; ")
    assert line.endswith(f"{ALLOCATOR_FAILURE}); use a smaller image or --device cuda")
    assert not out.exists()


@pytest.mark.parametrize("batch_size, advice", [(1, "use smaller images or --device cuda"),
                                                (2, "use smaller images, --batch-size 1 or --device cuda")])
def test_cli_folder_mode_refusal_is_one_line_with_the_folder_fix(main, capsys, tmp_path, monkeypatch, batch_size,
                                                                 advice):
    monkeypatch.setattr(memory, "available_memory", lambda device: 0.2e9)  # below the fixed overhead
    root = tmp_path / "folder"
    for sub in ("image", "velodyne_raw", "intrinsics"):
        (root / sub).mkdir(parents=True)
    for name in ("0000000000", "0000000001"):
        frame = _frame(tmp_path / "tmp")
        frame["image"].rename(root / "image" / f"{name}.png")
        frame["sparse"].rename(root / "velodyne_raw" / f"{name}.png")
        frame["intrinsics"].rename(root / "intrinsics" / f"{name}.txt")
    out_dir = tmp_path / "out"
    code = main(["complete", "--input-dir", str(root), "--out-dir", str(out_dir), "--mode", "pixel", "--quiet",
                 "--batch-size", str(batch_size)])
    assert code == 2
    frames = "a frame of 64x48 pixels" if batch_size == 1 else "a batch of 2 frame(s) of 64x48 pixels"
    line = _first_line(capsys)
    assert line.startswith(f"crfdepth complete: error: image: {frames} needs about 0.3 GB (pixel mode, float32: "
                           f"about 250 bytes per pixel), more than the memory available on cpu (0.2 GB); {advice} "
                           f"[stopped at ")
    assert line.endswith(f"0 of 2 frame(s) written to {out_dir}; --resume completes the others]")
    assert not out_dir.exists()  # the run created it and removes it again when nothing was written
