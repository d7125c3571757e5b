"""Peak memory of a forward, estimated up front (docs/design.md section 10).

Every configuration's peak memory grows linearly with the pixels of the batch: the
per-pixel maps of the fills, potentials, solves and std, the SLIC and graph buffers, and
chunked loops elsewhere (the LiDAR normals' neighbour gathers, the posterior std's sample
solves under their own budget, :data:`crfdepth.uncertainty.posterior.MEMORY_BUDGET_BYTES`). The
bytes per pixel below are the measured peaks of one float32 forward by ``benchmarks/speed.py``
(growth of the resident set on the CPU; the table of docs/design.md section 10), rounded
up; at 4000 x 3000 the measured peaks are about half of them, and the CUDA allocator's
are lower: the estimate is an upper bound.

:func:`check_memory` refuses a forward whose estimate exceeds the limit before anything
is allocated, with the estimate in the message (a :class:`MemoryRefusal`), instead of
letting the allocator fail or the operating system kill the process half-way. The limit
is ``CRFDepth(memory_limit_gb=...)`` when set (the caller's own limit, also to run
closer to the memory than the estimate allows), else the memory the device has
*available* now (:func:`available_memory`: ``MemAvailable`` of ``/proc/meminfo`` and the
room left under a cgroup limit on the CPU, ``torch.cuda.mem_get_info`` on CUDA).
:func:`crfdepth.api.complete_depth` checks right after the image's shape is known,
before converting anything; ``crfdepth complete`` checks the image file's header before
decoding it (:func:`check_image_file`); :func:`out_of_memory` turns an allocator failure
that still happens into the same kind of one-line error.
"""

from __future__ import annotations

import os
from pathlib import Path

import torch

from crfdepth.errors import InputError
from crfdepth.uncertainty.posterior import MEMORY_BUDGET_BYTES

__all__ = ["BYTES_PER_PIXEL", "OVERHEAD_BYTES", "MemoryRefusal", "available_memory", "check_frame_size",
           "check_image_file", "check_memory", "check_model_memory", "device_memory", "estimate_bytes", "is_out_of_memory",
           "out_of_memory"]

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
MIN_SIZE = 2
"""Smallest height and width of a frame: the CRF's 4-neighbour edges and the LiDAR normals need 2 rows and 2
columns."""
API_ADVICE = ("use a smaller image (or batch), a device with more memory (device='cuda'), or "
              "CRFDepth(memory_limit_gb=...) to set the limit yourself")
"""The likely fix of a memory refusal in the Python API (the CLI names its own options)."""


class MemoryRefusal(InputError):
    """A forward refused (or failed) for lack of memory; one line, like every :class:`InputError`.

    Made by :meth:`build`; ``MemoryRefusal(message)`` alone (as callers re-raise an
    ``InputError`` with more text) keeps the message. Attributes: ``estimate`` and ``limit``
    (bytes, or None), ``what`` (the user's name of the image), ``size`` ((batch, height,
    width)), ``reason`` (the message after the size, without the advice): enough for
    :meth:`retold` to say it again with another name and another fix (the CLI's flags).
    """

    what: str = "image"
    size: tuple[int, int, int] | None = None
    reason: str = ""
    estimate: int | None = None
    limit: float | None = None

    @classmethod
    def build(cls, what: str, size: tuple[int, int, int], reason: str, advice: str, estimate: int | None = None,
              limit: float | None = None) -> "MemoryRefusal":
        batch, height, width = size
        frames = f"a frame of {width}x{height} pixels" if batch == 1 else \
            f"a batch of {batch} frame(s) of {width}x{height} pixels"
        refusal = cls(f"{what}: {frames} {reason}; {advice}")
        refusal.what, refusal.size, refusal.reason, refusal.estimate, refusal.limit = what, size, reason, estimate, limit
        return refusal

    def retold(self, what: str, advice: str) -> "MemoryRefusal":
        """The same refusal naming the image ``what`` and advising ``advice`` (itself when it was not built)."""
        if self.size is None:
            return self
        return MemoryRefusal.build(what, self.size, self.reason, advice, self.estimate, self.limit)


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


def _read_int(path: Path) -> int | None:
    try:
        text = path.read_text().split()[0]
    except (OSError, IndexError):
        return None
    return int(text) if text.isdigit() else None  # "max" (cgroup v2: no limit) is not a number


def _meminfo_available() -> int | None:
    """``MemAvailable`` of ``/proc/meminfo`` in bytes (Linux), else the free physical pages; None if unknown."""
    try:
        for line in Path("/proc/meminfo").read_text().splitlines():
            if line.startswith("MemAvailable:"):
                return int(line.split()[1]) * 1024
    except (OSError, ValueError, IndexError):
        pass
    try:
        return int(os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_AVPHYS_PAGES"))
    except (ValueError, OSError, AttributeError):
        return None


def _cgroup_room() -> int | None:
    """Bytes left under this process's cgroup memory limit (v2 or v1), reclaimable page cache counted as
    free; None without a limit. In a container ``/proc/meminfo`` shows the host's memory, not the limit."""
    for limit_file, usage_file, stat_file in (
            (Path("/sys/fs/cgroup/memory.max"), Path("/sys/fs/cgroup/memory.current"),
             Path("/sys/fs/cgroup/memory.stat")),
            (Path("/sys/fs/cgroup/memory/memory.limit_in_bytes"), Path("/sys/fs/cgroup/memory/memory.usage_in_bytes"),
             Path("/sys/fs/cgroup/memory/memory.stat"))):
        limit, usage = _read_int(limit_file), _read_int(usage_file)
        if limit is None or usage is None or limit >= 2**60:  # no limit (v1 writes a huge number)
            continue
        cache = 0
        try:
            for line in stat_file.read_text().splitlines():
                key, _, value = line.partition(" ")
                if key in ("inactive_file", "total_inactive_file"):
                    cache = int(value)
        except (OSError, ValueError):
            pass
        return max(limit - usage + cache, 0)
    return None


def available_memory(device: torch.device) -> int | None:
    """Bytes ``device`` can still give a forward now; None if unknown (no check then).

    CPU: ``MemAvailable`` (what the kernel can hand out without swapping, page cache
    included), or the room left under the cgroup limit when that is smaller. CUDA: the
    device's free memory (``torch.cuda.mem_get_info``) plus what PyTorch's caching
    allocator holds unused. Other devices: unknown.
    """
    device = torch.device(device)
    if device.type == "cuda":
        if not torch.cuda.is_available():
            return None
        index = device.index if device.index is not None else torch.cuda.current_device()
        free, _ = torch.cuda.mem_get_info(index)
        return int(free + torch.cuda.memory_reserved(index) - torch.cuda.memory_allocated(index))
    if device.type != "cpu":
        return None
    known = [v for v in (_meminfo_available(), _cgroup_room()) if v is not None]
    return min(known) if known else None


def check_frame_size(what: str, height: int, width: int) -> None:
    """Refuse a frame smaller than :data:`MIN_SIZE` x :data:`MIN_SIZE` pixels, naming the image ``what``."""
    if height < MIN_SIZE or width < MIN_SIZE:
        raise InputError(f"{what}: expected at least {MIN_SIZE}x{MIN_SIZE} pixels (the CRF's 4-neighbour edges and "
                         f"the LiDAR normals need {MIN_SIZE} rows and {MIN_SIZE} columns), got {width}x{height} (WxH)")


def _mode_text(mode: str, return_std: bool, dtype: torch.dtype) -> str:
    per_pixel = BYTES_PER_PIXEL[(mode, bool(return_std))] * (torch.finfo(dtype).bits // 8) // 4
    name = str(dtype).replace("torch.", "")
    return f"{mode} mode{', with the std' if return_std else ''}, {name}: about {per_pixel} bytes per pixel"


def check_memory(mode: str, batch: int, height: int, width: int, return_std: bool, uncertainty: str,
                 dtype: torch.dtype, device: torch.device, limit_gb: float | None, *, what: str = "image",
                 advice: str = API_ADVICE) -> int:
    """Raise :class:`MemoryRefusal` when the estimate exceeds the limit; return the estimate.

    ``limit_gb`` None means the memory ``device`` has available now (:func:`available_memory`;
    no check when that is unknown); a number is the caller's limit, used instead. ``what``
    names the image in the message, ``advice`` is its likely fix.
    """
    estimate = estimate_bytes(mode, batch * height * width, return_std, uncertainty, torch.finfo(dtype).bits // 8)
    device = torch.device(device)
    if limit_gb is not None:
        limit, source = limit_gb * 1e9, "memory_limit_gb"
    else:
        limit, source = available_memory(device), f"the memory available on {device}"
    if limit is not None and estimate > limit:
        raise MemoryRefusal.build(what, (batch, height, width),
                            f"needs about {estimate / 1e9:.1f} GB ({_mode_text(mode, return_std, dtype)}), more than "
                            f"{source} ({limit / 1e9:.1f} GB)", advice, estimate, limit)
    return estimate


def check_model_memory(model, batch: int, height: int, width: int, return_std: bool, *, what: str = "image",
                       advice: str = API_ADVICE) -> int:
    """:func:`check_memory` for a forward of ``model`` (a :class:`~crfdepth.model.CRFDepth`) on its device and
    dtype, under its ``memory_limit_gb``."""
    param, settings = next(model.parameters()), model.settings
    return check_memory(settings.structure.mode, batch, height, width, return_std, settings.uncertainty.kind,
                        param.dtype, param.device, settings.solver.memory_limit_gb, what=what, advice=advice)


def check_image_file(path, what: str, *, device: str | torch.device, dtype: torch.dtype | str, return_std: bool,
                     mode: str | None = None, advice: str = API_ADVICE) -> None:
    """Refuse an image file too large for the memory from its header, before decoding it.

    The size comes from the PNG / JPEG header (:func:`crfdepth.io.image_size.read_image_size`;
    other formats, unreadable files and unknown devices pass, and are checked after decoding).
    With ``mode`` None (not chosen yet) the lightest mode is assumed, so only a frame that
    fits in no mode is refused here; the model's own check follows with its mode.
    """
    from crfdepth.io.image_size import read_image_size

    size = read_image_size(path)
    try:
        device = torch.device(device)
    except (RuntimeError, TypeError):
        return
    dtype = getattr(torch, dtype) if isinstance(dtype, str) else dtype
    if size is None or available_memory(device) is None:
        return
    modes = [mode] if mode is not None else sorted(("pixel", "superpixel"),
                                                   key=lambda m: BYTES_PER_PIXEL[(m, bool(return_std))])
    check_memory(modes[0], 1, *size, return_std, "predictive", dtype, device, None, what=what, advice=advice)


def is_out_of_memory(exc: BaseException) -> bool:
    """Whether ``exc`` is an allocator's failure: ``torch.cuda.OutOfMemoryError``, a ``MemoryError`` (numpy) or
    the CPU allocator's ``RuntimeError`` ("DefaultCPUAllocator: can't allocate memory")."""
    if isinstance(exc, MemoryError):
        return True
    oom = getattr(torch.cuda, "OutOfMemoryError", None)
    if oom is not None and isinstance(exc, oom):
        return True
    text = str(exc)
    return isinstance(exc, RuntimeError) and ("can't allocate memory" in text or "out of memory" in text.lower())


def out_of_memory(exc: BaseException, size: tuple[int, int, int], device: torch.device, *, what: str = "image",
                  estimate: int | None = None, advice: str = API_ADVICE) -> MemoryRefusal:
    """The one-line :class:`MemoryRefusal` for an allocator failure ``exc`` during the forward of ``size``
    ((batch, height, width)) frames on ``device``: the allocator's first line, the estimate, the memory
    available now."""
    first = (str(exc).strip().splitlines() or [type(exc).__name__])[0]
    available = available_memory(device)
    known = [f"estimated about {estimate / 1e9:.1f} GB"] if estimate is not None else []
    if available is not None:
        known.append(f"{available / 1e9:.1f} GB available on {device} now")
    return MemoryRefusal.build(what, size, f"ran out of memory on {device} ({'; '.join(known + [first])})", advice,
                         estimate, available)
