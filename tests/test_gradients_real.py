"""Every parameter's gradient on a real KITTI frame against finite differences (docs/design.md section 4).

The shipped model (``CRFDepth.from_pretrained("kitti")``) and the paper's superpixel
configuration (with and without fitted normals) in float64, on a 352x320
bottom-centre crop of the official val frame (full height, so the LiDAR-free top rows,
where the solves are hardest, are in it). The analytic gradient is taken at the model's
DEFAULT solver settings; the reference is central finite differences of a copy with
``rtol`` 1e-12. Every entry of ``model.named_parameters()`` is checked, so parameters
added later are covered: scalars (and tensors of up to 4 elements) entry by entry,
larger tensors along one seeded random unit direction.

- Loss: mean squared depth error over the ground-truth pixels.
- Parameters that do not affect the depth (the std scale ``s``, the weights of a
  potential that is off) must have a zero gradient and a zero finite difference; they
  are then checked on the Gaussian negative log-likelihood of ``return_std=True``.
  Only such parameters: the posterior variance carries no gradient by design (section 5),
  so finite differences of the NLL in any other parameter would differ.
- Step: ``STEP * max(|theta|, 1)`` on the unconstrained parameter (logit or log).
  Central differences at 1e-4 and 1e-5 agreed to 1e-5 relative or better in development.
- Tolerance: 1% relative.
"""

from __future__ import annotations

import warnings

import pytest
import torch

from crfdepth.data.factory import build_dataset
from crfdepth.data.transforms import BottomCenterCrop
from crfdepth.errors import ConvergenceWarning
from crfdepth.model import CRFDepth

CROP = (352, 320)  # (height, width) in pixels
STEP = 1e-5
TOLERANCE = 0.01
TIGHT = dict(rtol=1e-12, max_iter=100_000)

@pytest.fixture(scope="module")
def frame(kitti_root):
    root = kitti_root / "depth_selection" / "val_selection_cropped"
    sample = build_dataset("val_selection", root, transform=BottomCenterCrop(*CROP))[0]
    return tuple(t[None].double() for t in (sample.image, sample.sparse, sample.K, sample.target))


def _depth_loss(out, target):
    mask = target > 0
    return ((out.depth - target)[mask] ** 2).mean()


def _nll(out, target):
    mask = target > 0
    err, std = (out.depth - target)[mask], out.std[mask]
    return (0.5 * (err / std) ** 2 + std.log()).mean()


def _directions(p: torch.Tensor, generator: torch.Generator) -> list[torch.Tensor]:
    if p.numel() <= 4:
        return [torch.zeros_like(p).view(-1).index_fill_(0, torch.tensor([i]), 1.0).view_as(p)
                for i in range(p.numel())]
    v = torch.randn(p.shape, generator=generator, dtype=p.dtype)
    return [v / v.norm()]


def _analytic(model, frame, loss_fn, return_std):
    image, sparse, K, target = frame
    model.zero_grad(set_to_none=True)
    with warnings.catch_warnings():
        warnings.simplefilter("error", ConvergenceWarning)  # every solve and adjoint converges
        out = model(image, sparse, K, return_std=return_std)
        loss = loss_fn(out, target)
        loss.backward()
    for k, info in enumerate(out.info):
        assert bool(info.converged.all()) and bool(info.adjoint.converged.all()), (
            f"solve {k}: {info.summary()}; adjoint: {info.adjoint.summary()}")
    grads = {n: None if p.grad is None else p.grad.clone() for n, p in model.named_parameters()}
    return grads, float(loss.detach())


def _central_difference(reference, frame, loss_fn, return_std, param, direction, h):
    image, sparse, K, target = frame
    values = []
    with torch.no_grad():
        start = param.clone()
        for sign in (1.0, -1.0):
            param.copy_(start + sign * h * direction)
            values.append(float(loss_fn(reference(image, sparse, K, return_std=return_std), target)))
        param.copy_(start)
    return (values[0] - values[1]) / (2 * h)


@pytest.mark.kitti
@pytest.mark.slow
@pytest.mark.parametrize("weights, overrides", [
    pytest.param("kitti", {}, id="shipped"),
    # The paper's superpixel graph, whose nodes without LiDAR take normals fitted to the
    # first pass's points (graph_normals, differentiated where the plane is well defined).
    pytest.param("paper", {}, id="paper-superpixel-fitted-normals"),
    pytest.param("paper", {"potentials": ("colour", "distance")}, id="paper-without-normals"),
])
def test_every_parameter_gradient_matches_finite_differences(frame, weights, overrides):
    model = CRFDepth.from_pretrained(weights, **overrides).double()
    reference = CRFDepth.from_pretrained(weights, **overrides, **TIGHT).double()
    reference.load_state_dict(model.state_dict())
    ref_params = dict(reference.named_parameters())
    depth_grads, depth_loss = _analytic(model, frame, _depth_loss, return_std=False)
    std_grads = None
    generator = torch.Generator().manual_seed(0)
    rows, failures = [], []
    for name, p in model.named_parameters():
        h = STEP * max(float(p.detach().abs().max()), 1.0)
        for i, v in enumerate(_directions(p.detach(), generator)):
            label = name if p.numel() == 1 else f"{name}[{i if p.numel() <= 4 else 'random'}]"
            grad = depth_grads[name]
            analytic = 0.0 if grad is None else float((grad * v).sum())
            fd = _central_difference(reference, frame, _depth_loss, False, ref_params[name], v, h)
            loss_name = "depth"
            if analytic == 0.0:
                # No effect on the depth: the loss must not move at all, then the std's NLL.
                if abs(fd) * h > 1e-12 * abs(depth_loss):
                    rows.append(f"{label:24s} depth analytic 0 (none)  fd {fd: .6e}: not zero")
                    failures.append(rows[-1])
                    continue
                if std_grads is None:
                    std_grads, _ = _analytic(model, frame, _nll, return_std=True)
                grad = std_grads[name]
                analytic = 0.0 if grad is None else float((grad * v).sum())
                fd = _central_difference(reference, frame, _nll, True, ref_params[name], v, h)
                loss_name = "nll"
            rel = abs(analytic - fd) / abs(fd) if fd != 0.0 else abs(analytic)
            rows.append(f"{label:24s} {loss_name:5s} analytic {analytic: .6e}  fd {fd: .6e}  rel {rel:.1e}")
            if rel > TOLERANCE:
                failures.append(rows[-1])
    print("\n" + "\n".join(rows))
    assert not failures, "gradient off by more than 1% (or a zero that is not):\n" + "\n".join(failures)
    assert len(rows) == sum(p.numel() if p.numel() <= 4 else 1 for p in model.parameters())
