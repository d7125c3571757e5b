"""One frame from ``crfdepth complete`` to the conjugate-gradient loop (docs/design.md section 8): at most 8
calls deep, converted to the model's tensors once on the way in and to arrays once on the way out, and each
input checked once; a folder (``--input-dir``) at most 10 calls deep. Measured by profiling real runs on small
synthetic frames."""

from __future__ import annotations

import collections
import sys
from pathlib import Path

import pytest

from crfdepth import cli
from tests.cli.frames import png, stem, write_folder

# Where a frame crosses between arrays and tensors: the CLI, the API and the modules they read and check with
# (the model's own stages may view a tensor's memory as an array, e.g. the CG loop's BLAS calls, without a copy).
BOUNDARY = ("crfdepth/cli/", "crfdepth/runs/", "crfdepth/io/", "crfdepth/api.py", "crfdepth/inputs.py", "crfdepth/checks.py",
            "crfdepth/plausibility.py", "crfdepth/model.py")
# The CG loop: torch's, or the compiled solve's entry (crfdepth.native, where it is built).
CG_LOOPS = ("conjugate_gradient", "_native_solve")
CHECKS = ("check_intrinsics", "check_sparse_plausible", "check_frames", "image_to_numpy", "sparse_to_numpy",
          "check_frame_size", "check_model_memory")


def _profile(argv: list[str]) -> tuple[list[str], collections.Counter, collections.Counter]:
    """(the crfdepth functions from ``cli.main`` to the first CG loop (:data:`CG_LOOPS`), calls per crfdepth
    function, calls of torch.from_numpy and Tensor.numpy per (boundary function, callee))."""
    path: list[str] = []
    calls: collections.Counter = collections.Counter()
    conversions: collections.Counter = collections.Counter()

    def profile(frame, event, arg):
        code = frame.f_code
        if f"{Path('crfdepth')}/" not in code.co_filename.replace("\\", "/"):
            return
        if event == "call":
            calls[code.co_name] += 1
            if code.co_name in CG_LOOPS and not path:
                stack, f = [], frame
                while f is not None and f.f_code.co_name != "main":
                    stack.append(f.f_code.co_name)
                    f = f.f_back
                path.extend(reversed(stack))
        elif event == "c_call" and getattr(arg, "__name__", "") in ("from_numpy", "numpy") and \
                any(part in code.co_filename.replace("\\", "/") for part in BOUNDARY):
            # a generator's or crfdepth.checks.to_numpy's conversion is its caller's
            caller = frame.f_back.f_code.co_name if code.co_name in ("<genexpr>", "to_numpy") else code.co_name
            conversions[(caller, arg.__name__)] += 1

    sys.setprofile(profile)
    try:
        assert cli.main(argv) == 0
    finally:
        sys.setprofile(None)
    return path, calls, conversions


@pytest.fixture(scope="module")
def one_frame(tmp_path_factory):
    root = write_folder(tmp_path_factory.mktemp("frame") / "val_selection_cropped", 1)
    out = root.parent / "depth.png"
    argv = ["complete", "--image", str(root / "image" / f"{stem('image', 0)}.png"),
            "--sparse", str(root / "velodyne_raw" / png(0)),
            "--intrinsics", str(root / "intrinsics" / f"{stem('image', 0)}.txt"), "--out", str(out), "--quiet"]
    return _profile(argv)


def test_complete_reaches_the_cg_loop_in_at_most_8_calls(one_frame):
    path, _, _ = one_frame
    # run, complete_depth, _complete_on_model, pixel_forward, pixel_solve, solve_system, _krylov_solve,
    # conjugate_gradient (or solve_system, _native_solve)
    assert path[-1] in CG_LOOPS and "complete_depth" in path, path
    assert len(path) <= 8, path


def test_the_frame_is_converted_once_each_way(one_frame):
    _, _, conversions = one_frame
    # image, sparse and K become the model's tensors together; depth alone comes back (no --out-std)
    assert conversions == {("_on_model", "from_numpy"): 3, ("complete_depth", "numpy"): 1}, conversions


def test_each_input_is_checked_once(one_frame):
    _, calls, _ = one_frame
    assert {name: calls[name] for name in CHECKS} == {
        "check_intrinsics": 1, "check_sparse_plausible": 1, "check_frames": 0, "image_to_numpy": 1,
        "sparse_to_numpy": 1, "check_frame_size": 1, "check_model_memory": 1}


@pytest.fixture(scope="module")
def folder_run(tmp_path_factory):
    root = write_folder(tmp_path_factory.mktemp("folder") / "val_selection_cropped", 2)
    return _profile(["complete", "--input-dir", str(root), "--out-dir", str(root.parent / "out"), "--quiet"])


def test_a_folder_run_reaches_the_cg_loop_in_at_most_10_calls(folder_run):
    path, _, _ = folder_run
    # run, complete_folder, complete_frames, complete_checked, _complete_on_model, pixel_forward, pixel_solve,
    # solve_system, _krylov_solve, conjugate_gradient
    assert path[-1] in CG_LOOPS and "_complete_on_model" in path, path
    assert len(path) <= 10, path


def test_a_folder_run_converts_each_batch_once_on_the_way_out(folder_run):
    _, _, conversions = folder_run
    # in: the data set's tensors go to the model as they are (no from_numpy at the API); the checks read them as
    # arrays (a view) each time a frame is read; out: the depth of each batch (of one frame) once. run_record
    # hashes the weights, not a frame; check_intrinsics reads each frame's 3 x 3 K.
    frames = {key: n for key, n in conversions.items() if key[0] != "run_record"}
    assert frames == {("image_to_numpy", "numpy"): 4, ("sparse_to_numpy", "numpy"): 4, ("check_intrinsics", "numpy"): 4,
                      ("_write_batch", "numpy"): 2}, conversions


def test_a_folder_run_checks_each_frame_once_per_read_and_the_api_none_again(folder_run):
    _, calls, _ = folder_run
    # each of the 2 frames is read and checked twice: by the check pass (before anything is written) and again as
    # the completion pass reads it (the file may have changed since); the API checks nothing again and its memory
    # check runs once per batch
    assert {name: calls[name] for name in CHECKS} == {
        "check_intrinsics": 4, "check_sparse_plausible": 4, "check_frames": 0, "image_to_numpy": 4,
        "sparse_to_numpy": 4, "check_frame_size": 4, "check_model_memory": 2}
