"""The shipped model's gradients at its default solver settings on the synthetic scene (docs/design.md section 4).

The implicit gradient of a solve is exact only at ``A x = b``. Before the differentiated
forward solve was tightened (``grad_rtol``), the model's default ``rtol`` of 1e-5 gave
gradients up to 190% off on this very scene; here every solve and every adjoint must
converge at the defaults and the gradients must match tight-tolerance ones within 1%.
Fast: a 128x416 scene, about 3 s.
"""

from __future__ import annotations

import warnings

import pytest
import torch

from crfdepth.data.synthetic import make_scene
from crfdepth.errors import ConvergenceWarning
from crfdepth.model import CRFDepth

TIGHT = dict(rtol=1e-12, max_iter=100_000)


@pytest.fixture(scope="module")
def scene():
    s = make_scene(0, height=128, width=416)
    return (torch.from_numpy(s.image).permute(2, 0, 1)[None], torch.from_numpy(s.sparse)[None, None],
            torch.from_numpy(s.K)[None], torch.from_numpy(s.depth)[None, None])


def _gradients(scene, dtype, **overrides):
    """Parameter gradients of the masked squared depth error, and the solves' diagnostics."""
    image, sparse, K, target = (t.to(dtype) for t in scene)
    model = CRFDepth.from_pretrained("kitti", **overrides).to(dtype)
    with warnings.catch_warnings():
        warnings.simplefilter("error", ConvergenceWarning)  # non-convergence fails the test
        out = model(image, sparse, K)
        mask = target > 0
        ((out.depth - target)[mask] ** 2).mean().backward()
    grads = {name: p.grad for name, p in model.named_parameters()}
    return grads, out.info


@pytest.fixture(scope="module")
def tight_gradients(scene):
    return _gradients(scene, torch.float64, **TIGHT)[0]


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32], ids=["float64", "float32"])
def test_default_settings_give_converged_solves_and_tight_gradients(scene, tight_gradients, dtype):
    grads, infos = _gradients(scene, dtype)
    assert len(infos) >= 2
    for k, info in enumerate(infos):
        assert bool(info.converged.all()), f"solve {k}: {info.summary()}"
        assert info.adjoint is not None, f"solve {k}: no adjoint diagnostics"
        assert bool(info.adjoint.converged.all()), f"solve {k} adjoint: {info.adjoint.summary()}"
        assert float(info.adjoint.rel_residual.max()) <= info.adjoint.rtol
    errors = {}
    for name, ref in tight_gradients.items():
        got = grads[name]
        if ref is None or not bool(ref.any()):  # no gradient by design (e.g. the std scale)
            assert got is None or not bool(got.any()), f"{name}: {got} where the tight gradient is zero"
            continue
        assert got.dtype == dtype
        errors[name] = float((got.double() - ref).norm() / ref.norm())
    assert len(errors) >= 8, errors
    bad = {n: f"{e:.2e}" for n, e in errors.items() if e > 0.01}
    assert not bad, f"gradients off by more than 1% from tight-tolerance ones: {bad}"
