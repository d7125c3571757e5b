"""Peak memory of a forward, estimated up front (docs/design.md section 10).

Every configuration's peak memory grows linearly with the pixels of the batch: the
per-pixel maps of the fills, potentials, solves and std, the SLIC and graph buffers, and
chunked loops elsewhere (the LiDAR normals' neighbour gathers, the posterior std's sample
solves under their own budget, :data:`crfdepth.uncertainty.MEMORY_BUDGET_BYTES`). The
bytes per pixel below are measured peaks of one float32 forward by ``benchmarks/speed.py``
(growth of the resident set on the CPU) at 4000 x 3000, rounded up with a margin of about
25%; the CUDA allocator's peaks are lower. :func:`check_memory` refuses a forward whose
estimate exceeds the limit before anything is allocated, with the estimate in the message,
instead of letting the operating system kill the process half-way.
"""

from __future__ import annotations

import os

import torch

from crfdepth.errors import InputError
from crfdepth.uncertainty import MEMORY_BUDGET_BYTES

__all__ = ["BYTES_PER_PIXEL", "OVERHEAD_BYTES", "check_memory", "device_memory", "estimate_bytes"]

BYTES_PER_PIXEL = {
    ("pixel", False): 250,
    ("pixel", True): 300,
    ("superpixel", False): 350,
    ("superpixel", True): 400,
}
"""Peak bytes per pixel of a float32 forward by (graph, ``return_std``), the refinement and any
std included (a float64 input doubles it)."""
OVERHEAD_BYTES = 256 * 2**20
"""Fixed part: buffers that do not grow with the image, allocator slack."""


def estimate_bytes(mode: str, pixels: int, return_std: bool, uncertainty: str, element_size: int = 4) -> int:
    """Estimated peak bytes of a forward over ``pixels`` pixels in all (batch x height x width)."""
    per_pixel = BYTES_PER_PIXEL[(mode, bool(return_std))] * element_size / 4
    extra = MEMORY_BUDGET_BYTES if return_std and uncertainty == "posterior" else 0
    return int(OVERHEAD_BYTES + per_pixel * pixels + extra)


def device_memory(device: torch.device) -> int | None:
    """Total memory of ``device`` in bytes: the GPU's, or this machine's physical memory; None if unknown."""
    if device.type == "cuda":
        return int(torch.cuda.get_device_properties(device).total_memory)
    try:
        return int(os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES"))
    except (ValueError, OSError, AttributeError):
        return None


def check_memory(mode: str, batch: int, height: int, width: int, return_std: bool, uncertainty: str,
                 dtype: torch.dtype, device: torch.device, limit_gb: float | None) -> int:
    """Raise :class:`~crfdepth.errors.InputError` when the estimate exceeds the limit; return the estimate.

    ``limit_gb`` None means the device's memory (:func:`device_memory`).
    """
    estimate = estimate_bytes(mode, batch * height * width, return_std, uncertainty,
                              torch.finfo(dtype).bits // 8)
    limit = device_memory(device) if limit_gb is None else limit_gb * 1e9
    if limit is not None and estimate > limit:
        what = "memory_limit_gb" if limit_gb is not None else f"the {device.type} device's memory"
        raise InputError(
            f"image: a batch of {batch} frame(s) of {width}x{height} pixels needs about {estimate / 1e9:.1f} GB "
            f"({mode} mode{', with the std' if return_std else ''}: about "
            f"{BYTES_PER_PIXEL[(mode, bool(return_std))]} bytes per pixel in float32), more than {what} "
            f"({limit / 1e9:.1f} GB); use smaller batches or images, or raise CRFDepth(memory_limit_gb=...)")
    return estimate
