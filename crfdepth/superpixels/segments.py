"""Superpixels: SLIC segmentation, label maps, and painting node values back to pixels (docs/design.md section 2).

Conventions: ``labels`` is an (H, W) int64 map of node indices ``0 .. S-1`` in which every
index occurs; a batch of frames is laid out as one graph by :func:`batch_segments`
(global node indices, node offsets ``ptr``).
"""

from __future__ import annotations

from numbers import Integral
from typing import Literal

import numpy as np
import torch

from crfdepth.checks import check_choice, describe
from crfdepth.errors import InputError
from crfdepth.superpixels.slic import slic_torch

__all__ = ["SlicBackend", "batch_segments", "paint", "slic_batch", "slic_segments"]

#: Implementation of :func:`slic_segments`: ``"torch"`` (:func:`crfdepth.superpixels.slic.slic_torch`,
#: on the image's device), ``"skimage"`` (:func:`skimage.segmentation.slic`, on the CPU)
#: or ``"auto"`` (see :func:`slic_segments`).
SlicBackend = Literal["auto", "torch", "skimage"]
_BACKENDS = ("auto", "torch", "skimage")

#: The backend ``"auto"`` picks for CPU images: the faster one at 1216x352 (see
#: :func:`slic_segments`).
_CPU_BACKEND = "torch"


def image_tensor(image: torch.Tensor | np.ndarray, name: str = "image") -> torch.Tensor:
    """(3, H, W) tensor from a (3, H, W) tensor or an (H, W, 3) array; checked finite, [0, 1]."""
    if isinstance(image, np.ndarray):
        if image.ndim != 3 or image.shape[2] != 3:
            raise InputError(f"{name}: expected an (H, W, 3) RGB array in [0, 1], got {describe(image)}")
        tensor = torch.from_numpy(np.ascontiguousarray(image)).permute(2, 0, 1)
    elif isinstance(image, torch.Tensor):
        if image.ndim != 3 or image.shape[0] != 3:
            raise InputError(f"{name}: expected a (3, H, W) RGB tensor in [0, 1], got {describe(image)}")
        tensor = image
    else:
        raise InputError(f"{name}: expected a (3, H, W) tensor or an (H, W, 3) array, got {describe(image)}")
    if not tensor.is_floating_point():
        raise InputError(f"{name}: expected floating-point RGB in [0, 1], got dtype {tensor.dtype}")
    if tensor.shape[1] < 1 or tensor.shape[2] < 1:
        raise InputError(f"{name}: expected a non-empty image, got {describe(image)}")
    if not bool(torch.isfinite(tensor).all()):
        raise InputError(f"{name}: expected finite RGB values in [0, 1], got NaN or inf")
    lo, hi = float(tensor.min()), float(tensor.max())
    if lo < 0.0 or hi > 1.0:
        raise InputError(f"{name}: expected RGB values in [0, 1], got range [{lo:.4g}, {hi:.4g}]")
    return tensor


def _check_n_segments(n_segments: object) -> int:
    if isinstance(n_segments, bool) or not isinstance(n_segments, Integral) or int(n_segments) < 1:
        raise InputError(f"n_segments: expected an integer >= 1, got {n_segments!r}")
    return int(n_segments)


def labels_tensor(
    labels: torch.Tensor | np.ndarray, size: tuple[int, int] | None, name: str = "labels"
) -> torch.Tensor:
    """(H, W) int64 labels, relabelled to consecutive ``0 .. S-1`` if they are not already."""
    if isinstance(labels, np.ndarray):
        labels = torch.from_numpy(np.ascontiguousarray(labels))
    if not isinstance(labels, torch.Tensor) or labels.ndim != 2:
        raise InputError(f"{name}: expected an (H, W) integer tensor, got {describe(labels)}")
    if size is not None and tuple(labels.shape) != tuple(size):
        raise InputError(f"{name}: expected shape {tuple(size)} (the image size), got {describe(labels)}")
    if labels.dtype.is_floating_point or labels.dtype == torch.bool or labels.is_complex():
        raise InputError(f"{name}: expected an integer tensor, got dtype {labels.dtype}")
    if labels.numel() == 0:
        raise InputError(f"{name}: expected a non-empty label map, got {describe(labels)}")
    labels = labels.to(torch.int64)
    if int(labels.min()) < 0:
        raise InputError(f"{name}: expected labels >= 0, got minimum {int(labels.min())}")
    num = int(labels.max()) + 1
    present = torch.bincount(labels.flatten(), minlength=num) > 0
    if bool(present.all()):
        return labels
    # Drop unused label values: node i is the i-th smallest label that occurs.
    new_index = torch.cumsum(present, 0) - 1
    return new_index[labels]


def _resolve_backend(backend: object, device: torch.device) -> str:
    """``"torch"`` or ``"skimage"`` for ``backend`` on ``device`` (``"auto"``: see :func:`slic_segments`)."""
    check_choice("backend", backend, _BACKENDS)
    if backend != "auto":
        return backend
    return _CPU_BACKEND if device.type == "cpu" else "torch"


def slic_segments(
    image: torch.Tensor | np.ndarray,
    n_segments: int = 5500,
    *,
    compactness: float = 20.0,
    sigma: float = 1.0,
    max_num_iter: int = 5,
    convert2lab: bool = True,
    backend: SlicBackend = "auto",
) -> torch.Tensor:
    """SLIC superpixels of an RGB image (paper Sec. 3.2), labels ``0 .. S-1``.

    Two implementations of the same algorithm (every segment one 4-connected region;
    those below half the nominal size are merged into a neighbour, so ``S`` is usually a
    little below ``n_segments``):

    - ``backend="skimage"``: :func:`skimage.segmentation.slic` with ``start_label=0`` and
      ``enforce_connectivity=True``, labels renumbered consecutively with
      :func:`skimage.segmentation.relabel_sequential`; runs on the CPU (a GPU image makes a
      host round trip).
    - ``backend="torch"``: :func:`crfdepth.superpixels.slic.slic_torch`, on the image's device. Same
      grid, distance and iterations; the k-means labels agree with scikit-image's on
      99.96-99.99% of the pixels of the real frames (the candidate centres are the 3x3
      seed blocks around a pixel instead of every centre within two grid steps); small
      fragments join their largest neighbour instead of the neighbour met last by
      scikit-image's scan, so the labels differ, but on the real frames the segment
      count is within 1, boundary recall within 0.001 and undersegmentation error within
      0.0006 of scikit-image's (tests/superpixels/test_slic.py).
    - ``backend="auto"`` (default): ``"torch"`` for images on a GPU (or any non-CPU
      device); on the CPU also ``"torch"``, the faster one at 1216x352 (below).

    The defaults were chosen on the two real ``val_selection_cropped`` frames (1216x352,
    5500 segments), by the RMSE of the oracle piecewise-constant depth (each segment
    painted with its mean ground truth): ``compactness=20, sigma=1`` in Lab gives about
    5200 segments and 1.13 m; ``compactness=10`` follows colour more closely but
    gives fewer segments (4950) and 1.18 m; ``sigma=0`` produces ragged segments (1.20-
    1.53 m). Five k-means iterations match ten to within 1% on that measure at 60% of
    the time. Note that both backends rescale the image by its own min/max to [0, 1]
    before the Lab conversion, so ``compactness`` is in Lab units of that stretched image.

    Time at 1216x352, 5500 segments, on a 2-core CPU shared with other jobs (medians of
    9 interleaved runs, repeated 3 times): scikit-image 0.21-0.31 s (single-threaded;
    each k-means iteration about 35 ms, the Lab conversion about 40 ms, the Gaussian
    pre-smoothing and the connectivity pass about 10 ms each; ``max_num_iter=10`` about
    0.45 s); torch 0.10 s with 2 threads, 0.14-0.16 s with 1 thread (each further k-means
    iteration about 20 ms, Lab and smoothing 20 ms, connectivity 15 ms). Hence ``"auto"``
    picks torch on the CPU too. Caveat: while another process keeps a core busy, torch
    with 2 threads slowed down to 0.9-2.1 s per frame (its OpenMP threads wait for each
    other at every operation) where scikit-image stayed at 0.27-0.33 s; on a busy
    machine use ``torch.set_num_threads(1)`` or ``backend="skimage"``.

    Args:
        image: (3, H, W) float tensor or (H, W, 3) float array, RGB in [0, 1].
        n_segments: approximate number of superpixels, >= 1 (paper: 5500 at 1216x352).
        compactness: balance of colour against space (higher = more regular, grid-like).
        sigma: width (pixels) of the Gaussian pre-smoothing; 0 = none.
        max_num_iter: number of k-means iterations.
        convert2lab: cluster in CIELAB (True) or in the RGB values (False; then use a
            compactness of about 0.1-0.2 for RGB in [0, 1]).
        backend: ``"auto"``, ``"torch"`` or ``"skimage"`` (see above).

    Returns:
        (H, W) int64 tensor of labels ``0 .. S-1``, every value used, on the image's device.

    Raises:
        InputError: image not 3-channel RGB in [0, 1], ``n_segments < 1``, unknown
            ``backend`` (and, for the torch backend, ``compactness <= 0``, ``sigma < 0``
            or ``max_num_iter < 1``).
    """
    _resolve_backend(backend, torch.device("cpu"))  # a bad name is refused before the image is looked at
    tensor = image_tensor(image)
    n_segments = _check_n_segments(n_segments)
    device = tensor.device if isinstance(image, torch.Tensor) else torch.device("cpu")
    if _resolve_backend(backend, device) == "torch":
        return slic_torch(
            tensor,
            n_segments,
            compactness=compactness,
            sigma=sigma,
            max_num_iter=max_num_iter,
            convert2lab=convert2lab,
        )
    rgb = tensor.detach().to("cpu", torch.float32).permute(1, 2, 0).contiguous().numpy()
    from skimage.segmentation import relabel_sequential, slic  # at first use: SciPy's import is 0.2 s

    segments = slic(
        rgb,
        n_segments=n_segments,
        compactness=compactness,
        sigma=sigma,
        max_num_iter=max_num_iter,
        convert2lab=convert2lab,
        enforce_connectivity=True,
        start_label=0,
        channel_axis=-1,
    )
    # relabel_sequential keeps 0 as background, so shift to 1.. first and back after.
    consecutive, _, _ = relabel_sequential(segments.astype(np.int64) + 1)
    return torch.from_numpy(consecutive - 1).to(device)


def slic_batch(images: torch.Tensor, n_segments: int = 5500, *, compactness: float = 20.0, sigma: float = 1.0,
               max_num_iter: int = 5, convert2lab: bool = True, backend: SlicBackend = "auto") -> torch.Tensor:
    """:func:`slic_segments` of every frame of a (B, 3, H, W) batch (same arguments): (B, H, W) int64
    labels ``0 .. S_k-1`` per frame. The torch backend runs the whole batch at once on the images'
    device (:func:`crfdepth.superpixels.slic.slic_torch`); scikit-image one frame after another."""
    if not isinstance(images, torch.Tensor) or images.dim() != 4 or images.shape[1] != 3:
        raise InputError(f"image: expected a (B, 3, H, W) RGB tensor, got {describe(images)}")
    settings = dict(compactness=compactness, sigma=sigma, max_num_iter=max_num_iter, convert2lab=convert2lab)
    if _resolve_backend(backend, images.device) == "torch":
        return slic_torch(images.detach(), _check_n_segments(n_segments), **settings)
    return torch.stack([slic_segments(frame, n_segments, backend="skimage", **settings) for frame in images.detach()])


def batch_segments(labels: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Lay the segmentations of a batch out as one graph's nodes.

    Args:
        labels: (B, H, W) int64 segment index per pixel, >= 0 (need not be consecutive).

    Returns:
        ``node`` (B, H, W) int64 global node index (frame ``k``'s segments, renumbered
        consecutively in increasing label order, follow those of frames ``0 .. k-1``) and
        ``ptr`` (B + 1,) int64 node offsets.
    """
    nodes, sizes, offset = [], [], 0
    for k in range(labels.shape[0]):
        _, inv = torch.unique(labels[k], return_inverse=True)
        n_k = int(inv.max()) + 1
        nodes.append(inv + offset)
        sizes.append(n_k)
        offset += n_k
    ptr = torch.tensor([0] + sizes, device=labels.device).cumsum(0)
    return torch.stack(nodes), ptr


def paint(node_values: torch.Tensor, labels: torch.Tensor) -> torch.Tensor:
    """Node values to pixels, piecewise constant over each superpixel (paper, Fig. 2d).

    Differentiable with respect to ``node_values`` (an index gather).

    Args:
        node_values: (S,) values per node (e.g. depth in metres), or (S, C).
        labels: (H, W) int64 node index of each pixel, ``0 .. S-1``.

    Returns:
        (H, W), or (C, H, W) for (S, C) input: ``out[..., r, c] = node_values[labels[r, c]]``.
    """
    if not isinstance(node_values, torch.Tensor) or node_values.ndim not in (1, 2):
        raise InputError(f"node_values: expected an (S,) or (S, C) tensor, got {describe(node_values)}")
    if not isinstance(labels, torch.Tensor) or labels.ndim != 2 or labels.dtype != torch.int64:
        raise InputError(f"labels: expected an (H, W) int64 tensor, got {describe(labels)}")
    s = node_values.shape[0]
    if labels.numel() and (int(labels.min()) < 0 or int(labels.max()) >= s):
        raise InputError(
            f"labels: expected values in [0, {s - 1}] (node_values has {s} nodes), "
            f"got range [{int(labels.min())}, {int(labels.max())}]"
        )
    out = node_values[labels.to(node_values.device)]
    return out if node_values.ndim == 1 else out.permute(2, 0, 1)
