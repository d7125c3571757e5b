"""The compiled CPU kernels (crfdepth.native) against the eager torch path, their reference.

Where the kernels cannot be built on this machine (no compiler, no Python headers), the tests that
need them skip with the logged reason; the fallback tests run everywhere.
"""

import os
import subprocess
import sys
import textwrap

import numpy as np
import pytest
import torch
from scipy.ndimage import distance_transform_edt

from crfdepth import native
from crfdepth.fill.nearest import nearest_fill
from crfdepth.geometry.nearest import nearest_valid
from crfdepth.linalg import solve_grid_laplacian
from tests.grid_oracle import dense_grid_solution


def _grid_system(seed: int, batch: int, h: int, w: int, dtype, anchored: float = 0.05):
    g = torch.Generator().manual_seed(seed)
    b = torch.randn(batch, h, w, generator=g, dtype=dtype)
    d = (torch.rand(batch, h, w, generator=g, dtype=dtype) < anchored).to(dtype) * 3.0 + 1e-3
    wh = torch.rand(batch, h, w - 1, generator=g, dtype=dtype) ** 3  # weights over three decades
    wv = torch.rand(batch, h - 1, w, generator=g, dtype=dtype) ** 3
    return b, d, wh, wv


@pytest.mark.parametrize("seed, batch, h, w", [(0, 1, 17, 23), (1, 3, 9, 31), (2, 2, 1, 12), (3, 1, 14, 1), (4, 1, 2, 2)])
def test_compiled_cg_solves_like_the_eager_loop(kernels, seed, batch, h, w):
    b, d, wh, wv = _grid_system(seed, batch, h, w, torch.float64)
    oracle = dense_grid_solution(b, d, wh, wv)
    x_native, info_native = solve_grid_laplacian(b, d, wh, wv, rtol=1e-11, preconditioner="jacobi", max_iter=5000)
    with native.eager():
        x_eager, info_eager = solve_grid_laplacian(b, d, wh, wv, rtol=1e-11, preconditioner="jacobi", max_iter=5000)
    scale = oracle.abs().max()
    assert bool(info_native.converged.all()) and bool(info_eager.converged.all())
    assert float((x_native - oracle).abs().max()) <= 1e-8 * scale
    assert float((x_native - x_eager).abs().max()) <= 1e-8 * scale
    # the same recurrences: the iteration counts (at checks every 8) agree within one check
    assert (info_native.iterations - info_eager.iterations).abs().max() <= 8
    assert float(info_native.rel_residual.max()) <= 1e-11


def test_compiled_cg_in_float32_meets_the_tolerance_from_a_warm_start(kernels):
    b, d, wh, wv = _grid_system(5, 2, 40, 60, torch.float32)
    x0 = torch.full_like(b, 0.3)
    x, info = solve_grid_laplacian(b, d, wh, wv, x0=x0, rtol=1e-5, preconditioner="jacobi")
    with native.eager():
        x_eager, info_eager = solve_grid_laplacian(b, d, wh, wv, x0=x0, rtol=1e-5, preconditioner="jacobi")
    assert x.dtype == torch.float32 and bool(info.converged.all())
    assert float(info.rel_residual.max()) <= 1e-5  # the true residual, recomputed after the loop
    assert (info.iterations - info_eager.iterations).abs().max() <= 8
    oracle = dense_grid_solution(b, d, wh, wv).float()
    # both stop at rtol 1e-5: neither is much closer to the solution than the other
    err_native, err_eager = (x - oracle).abs().max(), (x_eager - oracle).abs().max()
    assert float(err_native) <= 2 * float(err_eager) + 1e-5


def test_compiled_cg_reports_a_singular_system_like_the_eager_loop(kernels):
    b, d, wh, wv = _grid_system(6, 1, 6, 7, torch.float64)
    d = torch.zeros_like(d)  # nothing anchors the Laplacian: caught before iterating
    from crfdepth.errors import InputError

    with pytest.raises(InputError, match="positive definite"):
        solve_grid_laplacian(b, d, wh, wv, preconditioner="jacobi")


def test_gradients_through_the_compiled_jacobi_solve_pass_gradcheck(kernels):
    b, d, wh, wv = _grid_system(7, 1, 4, 5, torch.float64, anchored=0.3)
    inputs = tuple(t.clone().requires_grad_(True) for t in (b, d + 0.5, wh + 0.1, wv + 0.1))

    def solve(b_, d_, wh_, wv_):
        return solve_grid_laplacian(b_, d_, wh_, wv_, rtol=1e-12, grad_rtol=1e-12, preconditioner="jacobi")[0]

    assert torch.autograd.gradcheck(solve, inputs, atol=1e-7, rtol=1e-5)


@pytest.mark.parametrize("seed", range(24))
def test_compiled_nearest_search_is_scipys_exact_answer(kernels, seed):
    g = np.random.default_rng(seed)
    h, w = (int(v) for v in g.integers(1, 70, 2))
    valid = g.random((h, w)) < [0.002, 0.01, 0.1, 0.6][seed % 4]
    valid[g.integers(h), g.integers(w)] = True
    index, squared = kernels.nearest_valid(torch.from_numpy(valid)[None].contiguous())
    rows, cols = distance_transform_edt(~valid, return_distances=False, return_indices=True)
    # the same pixel, ties included (the lowest row, then the lowest column, as SciPy's)
    assert np.array_equal(index[0].numpy(), rows * w + cols)
    r, c = np.indices((h, w))
    assert np.array_equal(squared[0].numpy(), (rows - r) ** 2 + (cols - c) ** 2)
    eager_index, eager_squared = nearest_valid(torch.from_numpy(valid)[None])
    assert torch.equal(squared, eager_squared)


def test_compiled_nearest_search_of_a_frame_without_returns(kernels):
    valid = torch.zeros(2, 5, 6, dtype=torch.bool)
    valid[1, 4, 0] = True
    index, squared = kernels.nearest_valid(valid)
    assert bool((index[0] == -1).all()) and bool((squared[0] == (5 + 6) ** 2 + 1).all())
    assert int(index[1, 0, 5]) == 4 * 6 and int(squared[1, 0, 5]) == 16 + 25


def test_nearest_fill_is_the_same_map_with_and_without_the_kernels(kernels, kitti_root):
    from crfdepth.data.kitti import KittiValSelection

    sparse = KittiValSelection(kitti_root / "depth_selection" / "val_selection_cropped")[0].sparse[None]
    filled = nearest_fill(sparse)
    with native.eager():
        reference = nearest_fill(sparse)
    assert torch.equal(filled, reference)


_FALLBACK = textwrap.dedent("""
    import logging, torch
    from crfdepth import native
    from crfdepth.fill.nearest import nearest_fill
    sparse = torch.zeros(1, 1, 6, 8); sparse[0, 0, 2, 3] = 5.0; sparse[0, 0, 5, 7] = 9.0
    first, second = nearest_fill(sparse), nearest_fill(sparse)
    print("module", native.kernels())
    print("filled", float(first[0, 0, 0, 0]), float(first[0, 0, 5, 6]))
""")


@pytest.mark.parametrize("env, reason", [({"CRFDEPTH_NATIVE": "0"}, None),
                                         ({"CXX": "/bin/false"}, "compiled CPU kernels unavailable")])
def test_without_the_kernels_the_eager_path_runs_and_says_so_once(tmp_path, env, reason):
    environ = {k: v for k, v in os.environ.items() if k not in ("CRFDEPTH_NATIVE", "CXX")}
    environ.update(CRFDEPTH_CACHE=str(tmp_path / "cache"), **env)
    done = subprocess.run([sys.executable, "-c", _FALLBACK], capture_output=True, text=True, env=environ, timeout=300)
    assert done.returncode == 0, done.stderr
    assert "module None" in done.stdout and "filled 5.0 9.0" in done.stdout
    lines = [line for line in done.stderr.splitlines() if "crfdepth" in line]
    if reason is None:
        assert lines == []  # turned off by the user: nothing to say
    else:
        assert len([line for line in lines if reason in line]) == 1, done.stderr
        assert not any(p.suffix == ".so" for p in (tmp_path / "cache").rglob("*"))  # no half-built library left


def test_a_kernel_that_fails_at_run_time_gives_the_eager_answer_with_one_warning(monkeypatch):
    """A compiled kernel that raises (here every one: a stand-in module) is told once, the kernels are off for the
    rest of the process, and the model's answer is the eager path's."""
    from crfdepth.data.synthetic import make_scene
    from crfdepth.model import CRFDepth

    class Broken:
        __file__ = "broken.so"

        def __getattr__(self, name):
            def fail(*args):
                raise RuntimeError(f"{name}: simulated failure")
            return fail

    scene = make_scene(1).to_tensors()
    image, sparse, K = scene["image"][None], scene["sparse"][None], scene["K"][None]
    model = CRFDepth.from_pretrained("kitti").eval()
    with torch.inference_mode(), native.eager():
        reference = model(image, sparse, K).depth
    monkeypatch.setitem(native._state, "module", None)
    monkeypatch.setitem(native._state, "module", native._Guarded(Broken()))
    with pytest.warns(RuntimeWarning, match="compiled kernel .* failed") as caught, torch.inference_mode():
        depth = model(image, sparse, K).depth
        again = model(image, sparse, K).depth
    assert len([w for w in caught if "compiled kernel" in str(w.message)]) == 1
    assert native.kernels() is None
    assert torch.equal(depth, reference) and torch.equal(again, reference)


@pytest.mark.parametrize("failing", ["nearest_fill", "grid_affinities", "grid_system", "grid_solve", "predictive_std"])
def test_any_one_kernel_failing_mid_forward_gives_the_eager_answer_with_one_warning(kernels, monkeypatch, failing):
    """One kernel raises while the ones before it in the forward ran: one warning naming it, the kernels are off
    from there, and the depth and std are the eager path's to the solves' tolerance."""
    from crfdepth.data.synthetic import make_scene
    from crfdepth.model import CRFDepth

    class OneBroken:
        __file__ = "one_broken.so"

        def __getattr__(self, name):
            if name != failing:
                return getattr(kernels._module, name)

            def fail(*args):
                raise RuntimeError(f"{name}: simulated failure")
            return fail

    scene = make_scene(2).to_tensors()
    image, sparse, K = scene["image"][None], scene["sparse"][None], scene["K"][None]
    model = CRFDepth.from_pretrained("kitti").eval()
    with torch.inference_mode(), native.eager():
        reference = model(image, sparse, K, return_std=True)
    monkeypatch.setitem(native._state, "module", native._Guarded(OneBroken()))
    with pytest.warns(RuntimeWarning, match=f"compiled kernel {failing} failed") as caught, torch.inference_mode():
        out = model(image, sparse, K, return_std=True)
    assert len([w for w in caught if "compiled kernel" in str(w.message)]) == 1
    assert native.kernels() is None
    difference = (out.depth - reference.depth).abs()
    assert float(difference.max()) < 0.05 and float(difference.quantile(0.99)) < 0.005
    relative = ((out.std - reference.std).abs() / reference.std).flatten()
    assert float(relative.quantile(0.99)) < 0.01
