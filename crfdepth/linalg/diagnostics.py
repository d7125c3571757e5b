"""What a solve is asked (:class:`SolverSettings`) and what it reports (:class:`SolveInfo`), and how a solve that
did not reach its tolerance is told: a :class:`~crfdepth.errors.ConvergenceWarning` at the user's line, a
:class:`~crfdepth.errors.ConvergenceError`, or nothing (``on_nonconvergence``), with the advice that fits the cause
(docs/design.md section 4)."""

from __future__ import annotations

import os
import sys
import warnings
from dataclasses import dataclass, field

import torch

from crfdepth.errors import ConvergenceError, ConvergenceWarning

__all__ = ["GRAD_RTOL", "SolveInfo", "SolverSettings", "report_nonconvergence"]


@dataclass
class SolveInfo:
    """Diagnostics of one batched solve; tensors have one entry per graph (G,).

    Attributes:
        method: "cg" or "cgs".
        iterations: int64 iterations taken per graph (over all restarts).
        rel_residual: ``||b - A x|| / ||b||`` per graph, recomputed from the returned x
            (0 for a graph with ``b = 0``).
        converged: ``rel_residual <= rtol`` and x finite, per graph (never True for NaN/inf).
        rtol: the tolerance asked for.
        adjoint: diagnostics of the adjoint solve, filled in when backward runs.
    """

    method: str
    iterations: torch.Tensor
    rel_residual: torch.Tensor
    converged: torch.Tensor
    rtol: float
    adjoint: "SolveInfo | None" = field(default=None, repr=False)

    def summary(self) -> str:
        return (f"{self.method}: iterations {self.iterations.tolist()}, relative residual "
                f"{[f'{r:.2e}' for r in self.rel_residual.tolist()]} (rtol {self.rtol:g}), "
                f"converged {self.converged.tolist()}")


# Forward tolerance of a solve that will be differentiated (docs/design.md section 4). The
# shipped model's gradients (L1 loss, adjoint at rtol 1e-5) against tight-tolerance ones,
# worst parameter, float64, forward rtol 1e-5 / 1e-7 / 1e-8 / 1e-9: 18% / 0.7% / 0.03% /
# 0.02% on the real KITTI val frame, 210% / 4.6% / 0.5% / 0.05% on the synthetic scene.
# The pixel-grid weights shipped later (data confidence 2802, 1/z unknown, fitted normals)
# needed more: log_sigma_d 3.7% off at 1e-8, 0.12% at 1e-10 (tests/test_gradients_real.py).
GRAD_RTOL = 1e-10


@dataclass
class SolverSettings:
    """Checked solve settings (:func:`crfdepth.linalg.solver_settings` documents them)."""

    method: str
    rtol: float
    max_iter: int | None
    check_every: int
    on_nonconvergence: str
    restarts: int = 3
    grad_rtol: float = GRAD_RTOL
    preconditioner: str = "auto"
    singular_hint: str = ""
    """What the caller's user can change when the system turns out numerically singular (a solve
    that gives NaN/inf or a residual larger than ``||b||``), said in the user's own argument names;
    empty: a generic sentence about ``d``."""


def report_nonconvergence(info: SolveInfo, settings: SolverSettings, what: str) -> None:
    """Warn, raise or stay quiet (``on_nonconvergence``) about graphs that did not converge.

    A graph whose solution is not finite (a numerically singular system broke the iteration)
    is told even under "ignore", and the message says the system is singular rather than
    suggesting more iterations."""
    if bool(info.converged.all()):
        return
    broken = ~torch.isfinite(info.rel_residual) | (info.rel_residual > 1)
    if settings.on_nonconvergence == "ignore" and not bool((~torch.isfinite(info.rel_residual)).any()):
        return
    bad = torch.nonzero(~info.converged).flatten().tolist()
    details = ", ".join(f"graph {g}: {int(info.iterations[g])} iterations, relative residual "
                        f"{float(info.rel_residual[g]):.3e}" for g in bad[:8])
    msg = (f"{what} ({settings.method}) did not reach rtol={settings.rtol:g} for {len(bad)} of "
           f"{info.converged.numel()} graph(s): {details}. ")
    if bool(broken[bad].any()):
        hint = settings.singular_hint or ("a diagonal d too small, against the edge weights, where nothing else "
                                          "anchors x: raise d (e.g. a small positive prior)")
        msg += (f"A residual that is NaN/inf or larger than ||b|| means the system is numerically singular: "
                f"{hint}.")
    else:
        msg += "Raise max_iter, loosen rtol, or pass a warm start x0."
    if settings.on_nonconvergence == "raise":
        raise ConvergenceError(msg)
    warnings.warn(msg, ConvergenceWarning, stacklevel=_caller_level())


# the folders of crfdepth (two above this file) and of torch: the frames _caller_level passes over
_LIBRARY_DIRS = (os.path.dirname(os.path.dirname(os.path.abspath(__file__))) + os.sep,
                 os.path.dirname(os.path.abspath(torch.__file__)) + os.sep)


def _caller_level() -> int:
    """The ``stacklevel`` of ``warnings.warn`` in :func:`report_nonconvergence` that names the first frame outside crfdepth and
    torch: the user's call, however deep in the library (model, layer, public solve, autograd's backward) the
    solve ran."""
    frame, level = sys._getframe(2), 2  # the frame that called report_nonconvergence is level 2 of warnings.warn
    while frame is not None and frame.f_code.co_filename.startswith(_LIBRARY_DIRS):
        frame, level = frame.f_back, level + 1
    return level if frame is not None else 1
