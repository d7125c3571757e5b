"""The potentials' compiled paths (:mod:`crfdepth.native`, docs/design.md section 10): a round's affinities and the
pixel grid's system in a few passes where no gradient is needed, on the CPU. Each returns None where it cannot run
(a gradient wanted, another device or dtype, no kernels, a kernel that failed), and its caller in
:mod:`crfdepth.potentials.energy` then computes the same numbers with torch, the reference."""

from __future__ import annotations

import torch

from crfdepth.native import kernels

__all__ = ["fused_affinities", "fused_system"]

Pair = tuple[torch.Tensor, torch.Tensor]


def fused_affinities(image: torch.Tensor, K: torch.Tensor, geometry: torch.Tensor | None, weights,
                      colour: Pair | None = None) -> tuple[Pair, Pair | None, Pair | None] | None:
    """:func:`crfdepth.potentials.energy._affinities` by the compiled kernels (the normals and all three
    affinities in four passes instead of about sixty torch kernels) where they can compute them: no gradient
    needed, CPU tensors of one dtype, H, W >= 2; else None. ``colour``: that pair, given (then not computed)."""
    tensors = [image, K, weights.sigma_d, weights.sigma_n, weights.sigma_p] + ([] if geometry is None else [geometry])
    if torch.is_grad_enabled() and any(t.requires_grad for t in tensors):
        return None
    if any(t.device.type != "cpu" for t in tensors) or image.dtype not in (torch.float32, torch.float64):
        return None
    if min(image.shape[-2:]) < 2 or (geometry is not None and geometry.dtype != image.dtype):
        return None
    native = kernels()
    if native is None:
        return None
    normal_on = geometry is not None and weights.gamma is not None
    distance_on = geometry is not None and weights.delta is not None
    depth = image.new_empty(0) if geometry is None else geometry[:, 0].contiguous()
    sigmas = [float(sigma.detach()) ** 2 for sigma in (weights.sigma_d, weights.sigma_n, weights.sigma_p)]
    found = native.grid_affinities(image.contiguous(), depth, K.detach(), *sigmas, colour is None, normal_on,
                                   distance_on)
    if found is None:  # the kernel failed (told in a warning): torch computes them
        return None
    ch, cv, nh, nv, dh, dv = found
    return (ch, cv) if colour is None else colour, ((nh, nv) if normal_on else None), ((dh, dv) if distance_on else None)


def fused_system(t) -> tuple[torch.Tensor, ...] | None:
    """``(d, b, weight_h, weight_v)`` of :func:`crfdepth.potentials.energy.grid_system` for the round ``t``
    (:class:`~crfdepth.potentials.energy.GridTerms`) in one pass per map, or None (torch builds it)."""
    maps = [t.w, t.z, t.prior, *t.colour]
    for pair in (t.normal, t.distance, t.edge_factor):
        maps += [] if pair is None else list(pair)
    scales = [s for s in (t.alpha, t.beta, t.gamma, t.delta, t.eps) if s is not None]
    if torch.is_grad_enabled() and any(x.requires_grad for x in maps + scales):
        return None
    dtype = t.w.dtype
    if dtype not in (torch.float32, torch.float64) or any(x.device.type != "cpu" or x.dtype != dtype for x in maps):
        return None
    native = kernels()
    if native is None:
        return None
    none = t.w.new_empty(0)

    def pair(p):
        return (none, none) if p is None else (p[0].contiguous(), p[1].contiguous())

    factor = [float(s) for s in (t.alpha, t.beta, t.gamma if t.gamma is not None else 0.0,
                                 t.delta if t.delta is not None else 0.0, t.eps)]
    return native.grid_system(t.w.contiguous(), t.z.contiguous(), t.prior.contiguous(), *pair(t.colour),
                              *pair(t.normal), *pair(t.distance), *pair(t.edge_factor), *factor)
