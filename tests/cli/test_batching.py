"""Batched folder inference: ``--batch-size`` and ``--workers`` of ``crfdepth complete
--input-dir`` and ``crfdepth evaluate`` (crfdepth.runs.batches.frame_batches and crfdepth.api.complete_checked).

The frames are built-in synthetic street scenes (:func:`crfdepth.data.synthetic.make_scene`,
16 beams) of two sizes, written to ``tmp_path`` in the ``val_selection_cropped`` layout so
that both commands read them. Tolerances between batch sizes are the measured maxima
with a margin (module constants).
"""

from __future__ import annotations

import csv
import functools
import json
import pickle
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch
from torch.utils.data import Dataset, Subset

from crfdepth.api import complete_depth
from crfdepth.data.factory import build_dataset
from crfdepth.data.kitti import KittiValSelection
from crfdepth.data.sample import Sample
from crfdepth.data.synthetic import make_scene, selection_stem, write_selection_folder
from crfdepth.errors import InputError
from crfdepth.io.kitti import write_depth_png
from crfdepth.metrics import METRICS
from crfdepth.runs import folder_frames as complete_folder
from crfdepth.runs.batches import _CheckedFrames, check_sample, frame_batches
from crfdepth.runs.resume import RUN_RECORD
from tests.cli.frames import run

# Frame sizes (H, W) in folder order: batches of 3 are [A A A] [A] [B B] (cap, then size change).
A, B = (64, 224), (56, 192)
SIZES = (A, A, A, A, B, B)
DRIVE = "2011_09_26_drive_0001_sync"
# Measured between --batch-size 1 and --batch-size 3 --workers 2 (shipped model), here and on
# the two KITTI validation frames (batch of 2): depth PNG codes differ by at most 1 (1/256 m);
# std codes by one code plus at most 0.04% of the std; per-frame metrics by at most 1.1e-6
# relative. The tolerances: the depth bound itself, about 5x and 10x the others.
DEPTH_CODES = 1
STD_RELATIVE = 2e-3
METRIC_RELATIVE = 1e-5




def _stem(kind: str, index: int) -> str:
    return selection_stem(kind, index, DRIVE)


def _write_folder(root: Path, sizes=SIZES) -> Path:
    """Synthetic scenes 0, 1, ... of ``sizes`` as a ``val_selection_cropped`` folder."""
    return write_selection_folder(root, (make_scene(index, h, w, beams=16) for index, (h, w) in enumerate(sizes)))


@pytest.fixture(scope="module")
def folder(tmp_path_factory) -> Path:
    return _write_folder(tmp_path_factory.mktemp("frames") / "val_selection_cropped")


def _files(folder: Path) -> list[str]:
    """Every file under ``folder`` (hidden temporary files included), relative, sorted."""
    return sorted(str(p.relative_to(folder)) for p in folder.rglob("*") if p.is_file())


def _codes(path: Path) -> np.ndarray:
    return cv2.imread(str(path), cv2.IMREAD_UNCHANGED).astype(np.int64)


# --------------------------------------------------------------------------- frame_batches


class _Frames(Dataset):
    """Tiny in-memory frames of the given sizes (module level: picklable for workers)."""

    def __init__(self, sizes, bad: int | None = None):
        self.sizes, self.bad = list(sizes), bad

    def __len__(self) -> int:
        return len(self.sizes)

    def __getitem__(self, index: int) -> Sample:
        if index == self.bad:
            raise FileNotFoundError(f"image: no such file: frame{index}.png")
        h, w = self.sizes[index]
        sparse = torch.zeros(1, h, w)
        sparse[0, ::3, ::3] = 5.0 + index
        K = torch.tensor([[50.0, 0, w / 2], [0, 50.0, h / 2], [0, 0, 1]])
        return Sample(torch.full((3, h, w), 0.5), sparse, torch.zeros(1, h, w), K, f"f{index}")


@pytest.mark.parametrize("workers", [0, 2])
def test_frame_batches_group_consecutive_frames_of_one_size(workers):
    sizes = [(8, 12)] * 4 + [(6, 10)] * 2 + [(8, 12)]
    batches = list(frame_batches(_Frames(sizes), batch_size=3, workers=workers))
    assert [b.names for b in batches] == [["f0", "f1", "f2"], ["f3"], ["f4", "f5"], ["f6"]]
    assert [tuple(b.image.shape) for b in batches] == [(3, 3, 8, 12), (1, 3, 8, 12), (2, 3, 6, 10), (1, 3, 8, 12)]
    assert float(batches[2].sparse[1].max()) == 10.0  # frame 5's own data, in order


@pytest.mark.parametrize("workers", [0, 2])
def test_frame_batches_yield_the_frames_before_a_bad_one_then_raise_its_error(workers):
    batches = frame_batches(_Frames([(8, 12)] * 5, bad=3), batch_size=4, workers=workers)
    assert next(batches).names == ["f0", "f1", "f2"]
    with pytest.raises(FileNotFoundError) as info:
        next(batches)
    assert str(info.value) == "image: no such file: frame3.png"  # the worker's message, no traceback


def test_check_sample_refuses_what_complete_depth_refuses():
    good = _Frames([(8, 12)])[0]
    check_sample(good)
    bad_K = torch.tensor([[50.0, 0, 600], [0, 50, 4], [0, 0, 1]])
    cases = [
        ("sparse: every pixel is 0 (no LiDAR point)", {"sparse": torch.zeros(1, 8, 12)}),
        ("sparse: expected finite depth >= 0", {"sparse": torch.full((1, 8, 12), -1.0)}),
        ("sparse: expected finite depth >= 0", {"sparse": torch.full((1, 8, 12), float("inf"))}),
        ("sparse: expected depth in metres", {"sparse": torch.full((1, 8, 12), 2560.0)}),
        ("image: expected float RGB in [0, 1]", {"image": torch.full((3, 8, 12), 2.0)}),
        ("image: expected float RGB in [0, 1]", {"image": good.image.index_put((torch.tensor(0),),
                                                                               torch.tensor(float("nan")))}),
        ("K: expected the principal point", {"K": bad_K}),
        ("K: expected the principal point", {"K": bad_K, "sparse": torch.zeros(1, 8, 12)}),  # K is checked first
    ]
    for words, change in cases:
        fields = {"image": good.image, "sparse": good.sparse, "target": good.target, "K": good.K, **change}
        sample = Sample(name="bad", **fields)
        with pytest.raises(InputError) as ours:
            check_sample(sample)
        with pytest.raises(InputError) as api:  # refused before any model is built
            complete_depth(sample.image, sparse=sample.sparse[0], K=sample.K)
        assert str(ours.value) == str(api.value) and str(ours.value).startswith(words)


# --------------------------------------------------------------------------- results


@pytest.fixture(scope="module")
def completed(folder, tmp_path_factory) -> dict[str, Path]:
    """``complete --input-dir`` with --batch-size 1 (default, no workers) and with --batch-size 3 --workers 2."""
    root = tmp_path_factory.mktemp("complete")
    runs = {"one": [], "three": ["--batch-size", 3, "--workers", 2]}
    for key, extra in runs.items():
        code, _, err = run(["complete", "--input-dir", folder, "--out-dir", root / key / "depth",
                             "--out-std-dir", root / key / "std", "--quiet", *extra])
        assert code == 0, err
    return {key: root / key for key in runs}


def test_complete_batches_write_the_same_files(completed):
    names = [f"{_stem('velodyne_raw', i)}.png" for i in range(len(SIZES))]
    for key, batch_size in (("one", 1), ("three", 3)):
        assert _files(completed[key]) == [f"depth/{RUN_RECORD}"] + [f"depth/{n}" for n in names] + [
            f"std/{n}" for n in names]
        record = json.loads((completed[key] / "depth" / RUN_RECORD).read_text())
        assert record["batch_size"] == batch_size and record["finished"] is True
    for name, size in zip(names, SIZES):
        assert _codes(completed["three"] / "depth" / name).shape == size


def test_complete_batched_depth_within_one_png_unit_of_batch_one(completed):
    worst_depth, worst_std = 0, 0.0
    for png in sorted((completed["one"] / "depth").glob("*.png")):
        one, three = _codes(png), _codes(completed["three"] / "depth" / png.name)
        assert one.min() > 0 and three.min() > 0
        worst_depth = max(worst_depth, int(np.abs(one - three).max()))
        std_one = _codes(completed["one"] / "std" / png.name)
        std_three = _codes(completed["three"] / "std" / png.name)
        unclipped = (std_one < 65535) & (std_three < 65535)
        relative = np.abs(std_one - std_three)[unclipped] / std_one[unclipped]
        # one PNG code is a relative step of 1/code: compare beyond the quantisation
        worst_std = max(worst_std, float(np.max(relative - 1.0 / std_one[unclipped])))
    assert worst_depth <= DEPTH_CODES
    assert worst_std <= STD_RELATIVE


def test_complete_batch_of_one_equals_the_one_frame_path(folder, completed, tmp_path):
    """The folder path with --batch-size 1 gives exactly the depth of ``--image ... --out``."""
    index = 4  # the first frame of size B
    out = tmp_path / "one.png"
    code, _, err = run(["complete", "--image", folder / "image" / f"{_stem('image', index)}.png",
                         "--sparse", folder / "velodyne_raw" / f"{_stem('velodyne_raw', index)}.png",
                         "--intrinsics", folder / "intrinsics" / f"{_stem('image', index)}.txt", "--out", out,
                         "--quiet"])
    assert code == 0, err
    folder_png = completed["one"] / "depth" / f"{_stem('velodyne_raw', index)}.png"
    np.testing.assert_array_equal(_codes(out), _codes(folder_png))


def _read_csv(path: Path) -> list[dict[str, str]]:
    with open(path, newline="") as handle:
        return list(csv.DictReader(handle))


def test_evaluate_batches_agree_per_frame(folder, tmp_path):
    rows = {}
    for key, extra in {"one": [], "three": ["--batch-size", 3, "--workers", 2]}.items():
        code, _, err = run(["evaluate", "--layout", "val_selection", "--data", folder, "--quiet",
                             "--out-dir", tmp_path / key, *extra])
        assert code == 0, err
        rows[key] = _read_csv(tmp_path / key / "per_frame.csv")
    assert [r["name"] for r in rows["one"]] == [_stem("velodyne_raw", i) for i in range(len(SIZES))]
    assert [r["name"] for r in rows["three"]] == [r["name"] for r in rows["one"]]
    for one, three in zip(rows["one"], rows["three"]):
        assert one["pixels"] == three["pixels"]
        for m in METRICS:
            assert float(three[m]) == pytest.approx(float(one[m]), rel=METRIC_RELATIVE, abs=1e-9), (one["name"], m)


# --------------------------------------------------------------------------- bad input


@pytest.mark.parametrize("command", ["complete", "evaluate"])
@pytest.mark.parametrize("option, value, expected", [
    ("--batch-size", "0", "expected an integer in [1, 1024], got '0'"),
    ("--batch-size", "1.5", "expected an integer in [1, 1024], got '1.5'"),
    ("--batch-size", "two", "expected an integer in [1, 1024], got 'two'"),
    ("--workers", "-1", "expected an integer in [0, 64], got '-1'"),
    ("--workers", "2.0", "expected an integer in [0, 64], got '2.0'"),
    ("--workers", "400", "expected an integer in [0, 64], got '400'"),
])
def test_bad_batch_options_exit_2_with_one_line(command, option, value, expected, folder, tmp_path):
    argv = (["complete", "--input-dir", folder, "--out-dir", tmp_path / "out"] if command == "complete" else
            ["evaluate", "--layout", "val_selection", "--data", folder, "--out-dir", tmp_path / "out"])
    code, stdout, stderr = run([*argv, option, value])
    assert code == 2 and stdout == ""
    assert stderr == f"crfdepth {command}: error: {option}: {expected}\n"
    assert not (tmp_path / "out").exists()


@pytest.mark.parametrize("option, value", [("--batch-size", 2), ("--workers", 1)])
def test_one_frame_mode_refuses_batch_options(folder, tmp_path, option, value):
    code, _, stderr = run(["complete", "--image", folder / "image" / f"{_stem('image', 0)}.png",
                            "--sparse", folder / "velodyne_raw" / f"{_stem('velodyne_raw', 0)}.png",
                            "--intrinsics", folder / "intrinsics" / f"{_stem('image', 0)}.txt",
                            "--out", tmp_path / "d.png", option, value])
    assert code == 2 and stderr == f"crfdepth complete: error: {option}: folder options need --input-dir; " \
                                   f"for one frame use --out / --out-std\n"
    assert not (tmp_path / "d.png").exists()


def _broken_copy(folder: Path, root: Path, index: int, how: str) -> Path:
    """A copy of ``folder`` whose frame ``index`` has an unreadable image or an all-zero LiDAR map."""
    copy = root / "val_selection_cropped"
    for sub in ("image", "velodyne_raw", "groundtruth_depth", "intrinsics"):
        (copy / sub).mkdir(parents=True)
        for path in (folder / sub).iterdir():
            (copy / sub / path.name).write_bytes(path.read_bytes())
    if how == "unreadable image":
        (copy / "image" / f"{_stem('image', index)}.png").write_bytes(b"not a png")
    else:
        write_depth_png(copy / "velodyne_raw" / f"{_stem('velodyne_raw', index)}.png", np.zeros(SIZES[index]))
    return copy


@pytest.mark.parametrize("how, words", [
    ("unreadable image", ["is not a readable image (9 bytes)"]),
    ("all-zero sparse", ["(velodyne_raw/", "every pixel is 0 (no LiDAR point)"]),
])
def test_complete_bad_frame_in_a_worker_reads_as_without_workers(folder, tmp_path, how, words):
    data = _broken_copy(folder, tmp_path / "data", 2, how)
    errors = {}
    for key, extra in {"plain": [], "workers": ["--batch-size", 3, "--workers", 2]}.items():
        out = tmp_path / key
        code, stdout, errors[key] = run(["complete", "--input-dir", data, "--out-dir", out, "--quiet", *extra])
        assert code == 2 and stdout == ""
        assert not out.exists()  # every frame is checked first: not even the two before the bad one are written
    err = errors["plain"]
    assert errors["workers"] == err
    assert err.startswith(f"crfdepth complete: error: frame 3/6 {_stem('velodyne_raw', 2)}")
    assert err.count("\n") == 1 and "Traceback" not in err
    assert f"[1 of 6 frame(s) of --input-dir {data} bad; nothing written;" in err
    assert all(w in err for w in words), err


def test_evaluate_bad_frame_in_a_worker_reads_as_without_workers(folder, tmp_path):
    data = _broken_copy(folder, tmp_path / "data", 4, "unreadable image")
    errors = []
    for extra in ([], ["--batch-size", 2, "--workers", 2]):
        code, stdout, stderr = run(["evaluate", "--layout", "val_selection", "--data", data,
                                     "--out-dir", tmp_path / "out", "--quiet", *extra])
        assert code == 2 and stdout == ""
        errors.append(stderr)
    assert errors[0] == errors[1]
    assert errors[0].startswith(f"crfdepth evaluate: error: frame 5 of 6 ({_stem('velodyne_raw', 4)}): image: ")
    assert errors[0].count("\n") == 1 and "not a readable image" in errors[0]
    assert not (tmp_path / "out").exists()  # no CSV, no JSON


# --------------------------------------------------------------------------- workers


def _same_items(dataset, copy) -> None:
    assert len(copy) == len(dataset)
    first, again = dataset[0], copy[0]
    assert again.name == first.name
    for field in ("image", "sparse", "target", "K"):
        assert torch.equal(getattr(again, field), getattr(first, field)), field


def test_datasets_of_the_workers_pickle(folder):
    """Workers started by spawn or forkserver (macOS, Windows, Python >= 3.14) get the dataset
    pickled: the wrapped dataset, the complete command's check and evaluate's --limit Subset."""
    dataset = KittiValSelection(folder)
    wrapped = _CheckedFrames(Subset(dataset, range(3)),
                             functools.partial(complete_folder._check_frame, total=3))
    _same_items(wrapped, pickle.loads(pickle.dumps(wrapped)))
    synthetic = build_dataset("synthetic", None, count=2, seed=5)
    copy = pickle.loads(pickle.dumps(synthetic))
    assert copy.names == synthetic.names == ["synthetic-seed5", "synthetic-seed6"]


@pytest.mark.kitti
@pytest.mark.parametrize("layout, folder_name", [
    ("val_selection", "depth_selection/val_selection_cropped"),
    ("depth_completion", "depth_completion"),
    ("raw", "raw"),
    ("object", "object/training"),
])
def test_kitti_layouts_pickle(kitti_root, layout, folder_name):
    dataset = build_dataset(layout, kitti_root / folder_name)
    copy = pickle.loads(pickle.dumps(dataset))
    assert copy.names == dataset.names
    _same_items(dataset, copy)

