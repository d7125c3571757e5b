"""The CRF in full precision under ``torch.autocast`` and on half-precision inputs
(docs/design.md section 4, "Mixed precision").

Under ``torch.autocast`` the ops autocast lists (matmul, convolutions, einsum, ...) run in
bfloat16 or float16. In the CRF that would put 8 bits of mantissa (bfloat16: a depth of
50 m to +-0.2 m, a relative residual that cannot go below about 4e-3) into the
superpixel clustering, the learned head's factors, the edge weights and the linear
system, and a solve in that precision is useless. The CRF is therefore to autocast what
autocast's own float32 ops (norms, softmax, losses) are: its entry points
(:func:`crfdepth.linalg.adjoint.solve_system`, :func:`crfdepth.layer.crf_refine`, the
model's pipelines, :func:`crfdepth.superpixels.slic.slic_torch`) run with autocast off
and take float16 / bfloat16 tensors as float32; the surrounding network keeps its
autocast. Float32 and float64 inputs are computed exactly as without autocast.
"""

from __future__ import annotations

import contextlib
import functools
from collections.abc import Callable, Iterator
from typing import Any, TypeVar

import torch

#: The dtypes computed as float32.
HALF = (torch.float16, torch.bfloat16)

F = TypeVar("F", bound=Callable[..., Any])


def widen(value: Any) -> Any:
    """``value`` as float32 if it is a float16 / bfloat16 tensor (differentiably), else unchanged."""
    if isinstance(value, torch.Tensor) and value.dtype in HALF:
        return value.float()
    return value


def full_dtype(dtype: torch.dtype) -> torch.dtype:
    """The dtype the CRF computes in for inputs of ``dtype``: float32 for half precision, else ``dtype``."""
    return torch.float32 if dtype in HALF else dtype


@contextlib.contextmanager
def autocast_off(*tensors: Any) -> Iterator[None]:
    """Autocast disabled, inside the block, for the device types of ``tensors`` (non-tensors are
    skipped; the CPU when there is none)."""
    kinds = {t.device.type for t in tensors if isinstance(t, torch.Tensor)} or {"cpu"}
    with contextlib.ExitStack() as stack:
        for kind in sorted(kinds):
            if torch.amp.is_autocast_available(kind):
                stack.enter_context(torch.autocast(kind, enabled=False))
        yield


def full_precision(fn: F) -> F:
    """Decorate ``fn`` to run with autocast off (:func:`autocast_off` on its tensor arguments) and with
    its float16 / bfloat16 tensor arguments, positional or keyword, as float32 (:func:`widen`)."""

    @functools.wraps(fn)
    def wrapper(*args: Any, **kwargs: Any) -> Any:
        args = tuple(widen(a) for a in args)
        kwargs = {k: widen(v) for k, v in kwargs.items()}
        with autocast_off(*args, *kwargs.values()):
            return fn(*args, **kwargs)

    return wrapper  # type: ignore[return-value]


__all__ = ["HALF", "autocast_off", "full_dtype", "full_precision", "widen"]
