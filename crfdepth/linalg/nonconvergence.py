"""How a solve that did not reach its tolerance is told: a :class:`~crfdepth.errors.ConvergenceWarning` at the
user's line, a :class:`~crfdepth.errors.ConvergenceError`, or nothing (``on_nonconvergence``), with the advice that
fits the cause (docs/design.md section 4)."""

from __future__ import annotations

import os
import sys
import warnings
from typing import TYPE_CHECKING

import torch

from crfdepth.errors import ConvergenceError, ConvergenceWarning

if TYPE_CHECKING:
    from crfdepth.linalg.adjoint import SolveInfo, SolverSettings

__all__ = ["report_nonconvergence"]


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
