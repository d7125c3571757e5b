"""What :class:`crfdepth.model.CRFDepth` returns, and the per-stage timer it fills in."""

from __future__ import annotations

import time
from collections.abc import Callable
from contextlib import contextmanager
from dataclasses import dataclass, field

import torch

from crfdepth.linalg import SolveInfo
from crfdepth.potentials.energy import EnergyTerms
from crfdepth.superpixels.graph import SuperpixelGraph

__all__ = ["CRFOutput", "Stages"]


@dataclass
class CRFOutput:
    """What :meth:`CRFDepth.forward` returns.

    Attributes:
        depth: (B, 1, H, W) dense z-depth in metres, > 0.
        std: (B, 1, H, W) standard deviation in metres (None unless asked): the predictive
            std of :mod:`crfdepth.uncertainty.predictive`, or the posterior's with ``uncertainty="posterior"``.
        count_uncertainty: (B, 1, H, W) the paper's map from LiDAR counts per node: 1 where
            the node holds no LiDAR point, 0.5 for one point, 0 for several (pixel mode: 1
            without LiDAR, 0 with).
        node_depth: (N,) node depths of the (last) graph solve, all frames concatenated
            (superpixel mode: the super-resolved point cloud before painting).
        node_std: (N,) node standard deviations (None unless asked).
        ptr: (B + 1,) node offsets of the frames in ``node_depth``.
        graphs: per-frame :class:`~crfdepth.superpixels.graph.SuperpixelGraph` (superpixel mode) or None.
        terms: the :class:`~crfdepth.potentials.energy.EnergyTerms` of the last graph solve, for
            :func:`crfdepth.potentials.energy.energy`. Built at first access: in pixel mode their edge
            list (two int64 indices per edge) costs about 6 ms per 1216x352 frame, a tenth of a forward
            that seldom needs it; the model stores the pixel grid's maps and the property flattens them.
        info: diagnostics of every solve, in order.
        timings: wall-clock seconds per stage (``fill``, ``slic``, ``graph``, ``normals``,
            ``potentials``, ``solve``, ``painting``, ``refine``, ``uncertainty``; those that
            ran). On CUDA, stages are timed without synchronisation (queued work may be
            counted in a later stage).
        std_features: (B, 5, H, W) the signals of the predictive std
            (:func:`crfdepth.uncertainty.predictive.std_features`; None unless it was computed).
    """

    depth: torch.Tensor
    std: torch.Tensor | None
    count_uncertainty: torch.Tensor
    node_depth: torch.Tensor
    node_std: torch.Tensor | None
    ptr: torch.Tensor
    graphs: list[SuperpixelGraph] | None
    _terms: EnergyTerms | Callable[[], EnergyTerms] | None = field(repr=False)
    info: list[SolveInfo] = field(default_factory=list)
    timings: dict[str, float] = field(default_factory=dict)
    std_features: torch.Tensor | None = None

    @property
    def terms(self) -> EnergyTerms | None:
        if callable(self._terms):
            self._terms = self._terms()
        return self._terms


class Stages:
    """Wall-clock seconds per pipeline stage (accumulated over the frames of a batch).

    On a CUDA ``device`` each stage starts and ends with ``torch.cuda.synchronize()``, so
    that a stage's time is its own work and not that of kernels still queued before it.
    ``progress``, when given, is called with the stage's name as each stage starts
    (:attr:`crfdepth.model.CRFDepth.progress`).
    """

    def __init__(self, device: torch.device | None = None, progress: Callable[[str], None] | None = None) -> None:
        self.seconds: dict[str, float] = {}
        self.sync = device is not None and device.type == "cuda"
        self.progress = progress

    @contextmanager
    def __call__(self, name: str):
        if self.progress is not None:
            self.progress(name)
        if self.sync:
            torch.cuda.synchronize()
        start = time.perf_counter()
        try:
            yield
        finally:
            if self.sync:
                torch.cuda.synchronize()
            self.seconds[name] = self.seconds.get(name, 0.0) + time.perf_counter() - start
