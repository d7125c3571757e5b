"""The CRF depth model of the paper as a learnable ``nn.Module`` (docs/design.md sections 2-6).

:class:`CRFDepth` turns an RGB image, a sparse LiDAR depth map and the intrinsics into a
dense depth map, its standard deviation and the paper's count-based
uncertainty map. Two graphs are supported:

- ``mode="superpixel"`` (paper): SLIC superpixels, the paper's 4-neighbour edges,
  optionally followed by a pixel-level refinement started from the superpixel solution;
- ``mode="pixel"``: the 4-connected pixel grid with the same potentials per pixel.

Inference (docs/design.md section 3): a first solve with the data, colour and (where LiDAR
normals exist) normal terms; then 3D points and the missing normals are taken from that
solution and the full system (with the 3D-distance term) is solved; optionally more
rounds. Every solve is the differentiable implicit solve of :mod:`crfdepth.linalg`, so
gradients reach every parameter through all rounds.
"""

from __future__ import annotations

from typing import Callable, Literal, Mapping, Sequence

import torch
from kornia.geometry.camera import unproject_points

from crfdepth.checks import check_frames, check_number
from crfdepth.errors import InputError
from crfdepth.potentials.data_term import PRIORS, lidar_evidence, node_lidar
from crfdepth.superpixels.graph import build_superpixel_graphs
from crfdepth.potentials.head import PotentialHead
from crfdepth.linalg import SolveInfo, solve_system, solver_settings
from crfdepth.memory import check_frame_size, check_memory
from crfdepth.output import CRFOutput, Stages
from crfdepth.potentials.parameters import ConstrainedWeights
from crfdepth.geometry.normals import aggregate_normals, graph_normals, lidar_normals
from crfdepth.potentials.occlusion import DEFAULT_SOFTNESS, DEFAULT_THRESHOLD, DEFAULT_WINDOW
from crfdepth.uncertainty.predictive import PredictiveStd, check_std_terms, std_features
from crfdepth.potentials.energy import (VARIABLES, EnergyTerms, PotentialWeights, Variable, colour_affinity, data_confidence,
                                 distance_affinity, energy, graph_system, grid_potentials, grid_system,
                                 normal_affinity, std_in_metres, to_depth, to_unknown)
from crfdepth.potentials.robust import DEFAULT_IRLS_SCALE, reweight
from crfdepth.superpixels.segments import slic_batch
from crfdepth.uncertainty.posterior import posterior_std, system_conditional_variance
from crfdepth.weights import load_state, pretrained_state, weights_path

Mode = Literal["superpixel", "pixel"]
POTENTIALS = ("colour", "normal", "distance")
REFERENCE_AREA = 1216 * 352  # the KITTI benchmark crop, for which ``superpixels`` is given
UNCERTAINTIES = ("predictive", "posterior")  # the std of ``return_std`` (docs/design.md section 5)


class CRFDepth(ConstrainedWeights):
    """Gaussian CRF depth completion with learnable potential weights (paper eq. 2).

    ``CRFDepth()`` starts from hand-set weights (the ``"paper"`` set), the starting point
    for training; ``CRFDepth.from_pretrained()`` has the weights learned on KITTI that
    :func:`~crfdepth.api.complete_depth` and the CLI use by default.

    Energy (docs/design.md section 3) on nodes ``i`` and edges ``(i, j)``::

        E(x) = alpha sum w_i (x_i - z_i)^2 + beta sum e_ij (x_i - x_j)^2
             + gamma sum nr_ij (x_i - x_j)^2 + delta sum dp_ij (x_i - x_j)^2
             + eps' sum (x_i - x0_i)^2

    with ``w_i = c n_i / (n_i + 1)`` (``c`` the data confidence, ``n_i`` LiDAR pixels in
    the node), the affinities of :mod:`crfdepth.potentials.energy`, and ``x0`` the nearest-LiDAR
    fill. ``eps' = eps * mean(alpha, beta, gamma, delta)`` over the potentials that are
    on: the prior scales with the weights, so multiplying alpha..delta by one factor
    leaves the depth exactly unchanged; only their ratios matter, and the sigmoid
    parametrisation keeps each in (0, 1) as in the paper.

    Learnable parameters (``nn.Parameter``, unconstrained underneath): ``alpha, beta,
    gamma, delta`` through a sigmoid; ``sigma_d, sigma_n, sigma_p``, the data confidence
    ``c``, the refinement prior weight and the posterior std's scale ``s`` through ``exp``
    (:mod:`crfdepth.potentials.parameters`); the predictive std's weights (``std_head``). The std's
    parameters get gradients through ``std`` only.

    Args:
        mode: "superpixel" (paper) or "pixel".
        superpixels: SLIC segments for a 1216x352 image (paper: 1200, 2400, 5500).
        scale_superpixels: scale the segment count with the image area (any image size
            gets superpixels of the same pixel size); False uses ``superpixels`` as is.
        potentials: pairwise potentials that are on, a subset of ("colour", "normal",
            "distance"); the paper's ablation is ("colour",), ("colour", "normal"), all.
        aggregate: "mean" or "median" of the LiDAR depths in a superpixel.
        refine: superpixel mode only: follow the superpixel solve with a pixel-level solve
            whose prior is the painted superpixel solution (docs/design.md section 6); False
            keeps the paper's piecewise-constant painting.
        rounds: solves with the 3D-distance term after the first pass (>= 1).
        alpha, beta, gamma, delta: initial weights in (0, 1). ``gamma`` defaults low: the
            normal potential joins *parallel* surfaces across a depth step as readily as
            one surface (a car's back and the wall behind it), so it is a tie-breaker
            where colour edges are not depth edges, not a main smoothness term.
        sigma_d: initial colour scale (RGB in [0, 1]); sigma_n: normal scale; sigma_p:
            3D-distance scale in metres.
        confidence: initial data confidence ``c`` > 0.
        eps: prior weight relative to the mean potential weight (keeps A positive
            definite; where nothing else informs a node, its depth falls back to x0).
        refine_prior: initial weight of the superpixel solution as the refinement's prior,
            relative to the mean potential weight (learnable: smaller lets the pixel solve
            depart further from the piecewise-constant superpixel depth).
        std_scale: initial ``s`` > 0.
        std_samples: samples of the posterior-variance estimate on large graphs
            (:mod:`crfdepth.uncertainty.posterior`); graphs up to 1,000 nodes are exact.
        rtol, max_iter, method: settings of every solve (:func:`crfdepth.linalg.solve_laplacian`).
        variable: the CRF's unknown (docs/design.md section 3b): ``"depth"`` (the paper),
            ``"inverse"`` (1/z: the smoothness terms then reproduce planes exactly) or
            ``"log"`` (log z: between the two where a pixel mixes a near and a far surface).
            Data, prior and warm start are mapped to it, depth and std are mapped back
            (``std_z = z^2 std_(1/z)``, ``z std_(log z)``); ``CRFOutput.terms`` hold the system in it.
        gate: multiply each return's data weight by the soft occlusion gate of
            :mod:`crfdepth.potentials.occlusion` (see-through returns lose weight); ``gate_window``
            (odd pixels), ``gate_threshold`` and ``gate_softness`` (1/m, learnable) set it.
        prior: the fill that is ``x0`` and the warm start, "nearest" or "ip_basic".
        irls: robust reweighting rounds of the pixel-grid data term after the last solve
            (:mod:`crfdepth.potentials.robust`; 0 = none): each scales a return's data weight by a
            Geman-McClure factor of how far *behind* its leave-one-out prediction it lies.
        irls_scale: initial ``sigma`` of that factor, inverse depth in 1/m (learnable).
        head: add the small learned :class:`~crfdepth.potentials.head.PotentialHead` (per-pixel data
            and edge-weight factors of the pixel-grid solves; docs/design.md section 3b).
        uncertainty: the std of ``return_std`` (docs/design.md section 5): "predictive" (the
            posterior's local part with depth, edge, data-distance and gate signals,
            :mod:`crfdepth.uncertainty.predictive`; about 0.15 x the forward's time) or "posterior"
            (``s sqrt(diag(A^-1))`` alone, sampled: about 40 solves).
        std_terms: initial weights of the predictive std by name
            (:data:`crfdepth.uncertainty.predictive.STD_TERMS`; None: the hand-set ones), learnable.
        memory_limit_gb: refuse a forward whose estimated peak memory
            (:mod:`crfdepth.memory`, an upper bound) exceeds this many GB, before
            allocating; None: the memory the device has available at each forward.
    """

    def __init__(
        self,
        mode: Mode = "superpixel",
        superpixels: int = 5500,
        scale_superpixels: bool = True,
        potentials: Sequence[str] = POTENTIALS,
        aggregate: Literal["mean", "median"] = "mean",
        refine: bool = True,
        rounds: int = 1,
        alpha: float = 0.5,
        beta: float = 0.5,
        gamma: float = 0.05,
        delta: float = 0.25,
        sigma_d: float = 0.1,
        sigma_n: float = 0.3,
        sigma_p: float = 1.0,
        confidence: float = 100.0,
        eps: float = 0.1,
        refine_prior: float = 0.05,
        std_scale: float = 1.0,
        std_samples: int = 32,
        rtol: float = 1e-5,
        max_iter: int | None = None,
        method: Literal["cg", "cgs"] = "cg",
        variable: Variable = "depth",
        head: bool = False,
        gate: bool = False,
        gate_window: int = DEFAULT_WINDOW,
        gate_threshold: float = DEFAULT_THRESHOLD,
        gate_softness: float = DEFAULT_SOFTNESS,
        prior: Literal["nearest", "ip_basic"] = "nearest",
        irls: int = 0,
        irls_scale: float = DEFAULT_IRLS_SCALE,
        uncertainty: Literal["predictive", "posterior"] = "predictive",
        std_terms: Mapping[str, float] | None = None,
        memory_limit_gb: float | None = None,
    ) -> None:
        super().__init__()
        # The constructor arguments, JSON-friendly: checkpoints store them to rebuild the model.
        self.config = {k: v for k, v in locals().items() if k not in ("self", "__class__")}
        self.config["potentials"] = list(potentials)
        for name, value, choices in (("mode", mode, ("superpixel", "pixel")), ("variable", variable, VARIABLES),
                                     ("prior", prior, PRIORS), ("uncertainty", uncertainty, UNCERTAINTIES)):
            if value not in choices:
                raise InputError(f"{name}: expected one of {choices}, got {value!r}")
        check_number("superpixels", superpixels, low=1, low_open=False, integer=True)
        unknown = set(potentials) - set(POTENTIALS)
        if unknown or "colour" not in potentials:
            raise InputError(f"potentials: expected a subset of {POTENTIALS} containing 'colour', "
                             f"got {tuple(potentials)!r}")
        if gate and aggregate != "mean":
            raise InputError(f"aggregate: the occlusion gate weights a mean, expected 'mean' with gate=True, "
                             f"got {aggregate!r}")
        if isinstance(gate_window, bool) or not isinstance(gate_window, int) or gate_window < 3 or gate_window % 2 == 0:
            raise InputError(f"gate_window: expected an odd int >= 3 (pixels), got {gate_window!r}")
        check_number("rounds", rounds, low=1, low_open=False, integer=True)
        if memory_limit_gb is not None:
            check_number("memory_limit_gb", memory_limit_gb, low=0.0)
        check_number("irls", irls, low=0, low_open=False, integer=True)
        for name, value in (("alpha", alpha), ("beta", beta), ("gamma", gamma), ("delta", delta)):
            check_number(name, value, low=0.0, high=1.0)
        for name, value in (("sigma_d", sigma_d), ("sigma_n", sigma_n), ("sigma_p", sigma_p),
                            ("confidence", confidence), ("eps", eps), ("refine_prior", refine_prior),
                            ("std_scale", std_scale), ("gate_threshold", gate_threshold),
                            ("gate_softness", gate_softness), ("irls_scale", irls_scale)):
            check_number(name, value, low=0.0)
        self.mode, self.superpixels, self.scale_superpixels = mode, superpixels, scale_superpixels
        self.potentials = tuple(p for p in POTENTIALS if p in potentials)
        self.aggregate, self.refine, self.rounds, self.std_samples = aggregate, refine, rounds, std_samples
        self.variable, self.gate, self.gate_window, self.prior = variable, gate, gate_window, prior
        self.irls, self.uncertainty, self.memory_limit_gb = irls, uncertainty, memory_limit_gb
        std_terms = check_std_terms(std_terms)
        self.std_head = None if uncertainty == "posterior" else PredictiveStd(std_terms)
        self.head = PotentialHead() if head else None
        self.solver = solver_settings(method=method, rtol=rtol, max_iter=max_iter)
        self._register_weights(dict(alpha=alpha, beta=beta, gamma=gamma, delta=delta, sigma_d=sigma_d, sigma_n=sigma_n,
                                    sigma_p=sigma_p, confidence=confidence, std_scale=std_scale,
                                    refine_prior=refine_prior, gate_threshold=gate_threshold,
                                    gate_softness=gate_softness, irls_scale=irls_scale))
        self.register_buffer("eps", torch.tensor(float(eps)))

    @classmethod
    def from_pretrained(cls, name: str = "kitti", **overrides) -> "CRFDepth":
        """The model with a shipped weight set, in eval mode (:func:`crfdepth.checkpoints.load_pretrained`).

        ``"kitti"``: weights learned on real KITTI frames (``crfdepth/weights/README.md``
        says how); ``"paper"``: the hand-set initial values of ``CRFDepth()``.
        ``overrides`` replace stored arguments, e.g. ``mode="superpixel"``; without them
        the model has the structure the weights were made for (kitti: pixel grid, log
        depth, occlusion gate). Stored tensors are loaded with every key checked (a
        missing or unexpected one is an error naming the file).
        """
        config, state = pretrained_state(name)
        return cls.from_stored({**config, **overrides}, state, file=weights_path(name)).eval()

    @classmethod
    def from_stored(cls, config: Mapping, state: dict[str, torch.Tensor], *, file=None,
                    kind: str | None = None) -> "CRFDepth":
        """The model built from a stored configuration and state dict: the one step every loader
        (shipped sets, weights files, checkpoints) ends in, with its checks.

        ``kind`` names the file's kind ("Lightning checkpoint" ...) when the configuration
        comes from that file, and errors in it name the file; without it the configuration's
        faults are the caller's ``overrides``.

        Raises:
            InputError: a configuration ``CRFDepth`` rejects, or tensors that do not fit it
                (:func:`crfdepth.weights.state.load_state`), naming ``file``.
        """
        try:
            model = cls(**config)
        except TypeError as exc:  # unknown or missing keyword arguments
            if kind is None:
                raise InputError(f"overrides: not CRFDepth arguments ({exc})") from None
            raise InputError(f"{file}: the {kind}'s model configuration does not fit CRFDepth ({exc})") from None
        except InputError as exc:
            if kind is None:
                raise
            raise InputError(f"{file}: invalid model configuration in the {kind} ({exc})") from None
        return load_state(file, model, state) if state else model

    def _scales(self) -> tuple[torch.Tensor, ...]:
        """alpha, beta, gamma, delta (0 for potentials that are off) and the scaled eps."""
        alpha = self.alpha
        beta = self.beta
        gamma = self.gamma if "normal" in self.potentials else None
        delta = self.delta if "distance" in self.potentials else None
        active = [t for t in (alpha, beta, gamma, delta) if t is not None]
        mean = torch.stack(active).mean()
        return alpha, beta, gamma, delta, self.eps * mean, mean

    def _weights_for_grid(self) -> PotentialWeights:
        """The weights :func:`crfdepth.potentials.energy.grid_potentials` needs (None: potential off)."""
        alpha, beta, gamma, delta, _, _ = self._scales()
        return PotentialWeights(alpha=alpha, beta=beta, gamma=gamma, delta=delta, confidence=self.confidence,
                                sigma_d=self.sigma_d, sigma_n=self.sigma_n, sigma_p=self.sigma_p)

    def segments_for(self, height: int, width: int) -> int:
        """SLIC segments used for an image of this size."""
        if not self.scale_superpixels:
            return self.superpixels
        return max(16, round(self.superpixels * height * width / REFERENCE_AREA))

    # -- forward -------------------------------------------------------------------------
    progress: Callable[[str], None] | None = None
    """Called with each stage's name (those of ``CRFOutput.timings``) as the stage starts; None: no calls.
    Set on an instance, e.g. by the CLI for its progress line (:mod:`crfdepth.cli.progress`)."""

    def forward(self, image: torch.Tensor, sparse: torch.Tensor, K: torch.Tensor, *,
                return_std: bool = False) -> CRFOutput:
        """Complete ``sparse`` into dense depth.

        Args:
            image: (B, 3, H, W) RGB in [0, 1].
            sparse: (B, 1, H, W) LiDAR z-depth in metres, 0 = no return; every frame needs
                at least one LiDAR pixel.
            K: (B, 3, 3) or (3, 3) intrinsics of the image, pixels.
            return_std: also compute the posterior standard deviation (extra solves).

        Returns:
            :class:`CRFOutput`; tensors in the dtype of ``sparse`` on its device.

        Raises:
            InputError: bad inputs (:func:`crfdepth.checks.check_frames`), a frame smaller
                than 2x2 pixels, or (:class:`crfdepth.memory.MemoryRefusal`) an estimated
                peak memory above ``memory_limit_gb`` or, without it, above the memory the
                device has available; size and memory are checked from the shape alone,
                before anything is allocated.
        """
        if isinstance(sparse, torch.Tensor) and sparse.dim() == 4 and sparse.is_floating_point():
            # Size and memory first, from the shape alone: the checks below allocate per pixel.
            check_frame_size("image", *sparse.shape[2:])
            check_memory(self.mode, *sparse.shape[:1], *sparse.shape[2:], return_std, self.uncertainty, sparse.dtype,
                         sparse.device, self.memory_limit_gb)
        image, sparse, K = check_frames(image, sparse, K)
        image = image.to(sparse.dtype)
        K = K.to(sparse.dtype)
        if self.mode == "pixel":
            return self._forward_pixel(image, sparse, K, return_std)
        return self._forward_superpixel(image, sparse, K, return_std)

    def _evidence(self, sparse: torch.Tensor) -> tuple[torch.Tensor | None, torch.Tensor, torch.Tensor]:
        """``(gate, kept, fill)`` of :func:`crfdepth.potentials.data_term.lidar_evidence` (docs/design.md section 3b)."""
        gate = (self.gate_threshold, self.gate_softness) if self.gate else None
        return lidar_evidence(sparse, gate, self.gate_window, self.prior)

    # -- superpixel mode -----------------------------------------------------------------
    def _forward_superpixel(self, image, sparse, K, return_std) -> CRFOutput:
        bsz, _, h, w = sparse.shape
        dtype, device = sparse.dtype, sparse.device
        stage = Stages(sparse.device, self.progress)
        with stage("fill"):
            gate, kept, fill = self._evidence(sparse)
        n_seg = self.segments_for(h, w)
        offsets = [0]
        z, count, colour, centroid, prior, nrm, nrm_ok, frame, edges = [], [], [], [], [], [], [], [], []
        with stage("slic"):
            all_labels = slic_batch(image.detach(), n_seg)  # (B, H, W), the whole batch at once
        with stage("graph"):
            graphs = build_superpixel_graphs(image.detach(), kept.detach(), aggregate=self.aggregate, labels=all_labels)
        if "normal" in self.potentials:
            with stage("normals"):  # (B, 3, H, W), (B, 1, H, W): all frames' returns at once
                lidar_n, lidar_ok = lidar_normals(kept.detach(), K.detach())
        for b, g in enumerate(graphs):
            with stage("graph"):
                col = g.node_mean(image[b])  # colour kept differentiable in the image
                x0 = g.node_mean(fill[b])[:, 0]
                if gate is None:
                    z.append(to_unknown(g.lidar_depth.to(dtype), self.variable))
                    count.append(g.lidar_count)
                else:  # gate-weighted mean and count, differentiable in the gate's parameters
                    zn, n = node_lidar(sparse[b, 0], gate[b, 0], g.labels, g.num_nodes, self.variable)
                    z.append(zn)
                    count.append(n)
                colour.append(col)
                centroid.append(g.centroid.to(dtype))
                prior.append(x0)
                frame.append(torch.full((g.num_nodes,), b, dtype=torch.long, device=device))
                edges.append(g.edge_index + offsets[-1])
                offsets.append(offsets[-1] + g.num_nodes)
            if "normal" in self.potentials:
                with stage("normals"):
                    nn_, nv = aggregate_normals(lidar_n[b], lidar_ok[b, 0], g.labels, g.num_nodes)
                    nrm.append(nn_.to(dtype))
                    nrm_ok.append(nv)
        with stage("potentials"):
            ptr = torch.tensor(offsets, device=device)
            z, count, colour = torch.cat(z), torch.cat(count), torch.cat(colour)
            centroid, prior, frame = torch.cat(centroid), torch.cat(prior), torch.cat(frame)
            prior = to_unknown(prior, self.variable)
            edge_index = torch.cat(edges, 1)
            src, dst = edge_index
            alpha, beta, gamma, delta, eps, mean_weight = self._scales()
            wdata = data_confidence(count, self.confidence)
            e = colour_affinity(colour[src], colour[dst], self.sigma_d)
            node_normal = normal_ok = None
            nr = None
            if "normal" in self.potentials:
                node_normal, normal_ok = torch.cat(nrm), torch.cat(nrm_ok)
                both = (normal_ok[src] & normal_ok[dst]).to(dtype)
                nr = normal_affinity(node_normal[src], node_normal[dst], self.sigma_n) * both
            terms = EnergyTerms(z, wdata, prior, edge_index, e, nr, None, alpha, beta,
                                gamma if gamma is not None else torch.zeros_like(alpha),
                                torch.zeros_like(alpha), eps)
        infos: list[SolveInfo] = []
        with stage("solve"):
            x = self._graph_solve(terms, ptr, prior, infos)
        K_node = K[frame]
        if "normal" in self.potentials or "distance" in self.potentials:
            for _ in range(self.rounds):
                with stage("potentials"):
                    points = unproject_points(centroid, to_depth(x, self.variable)[:, None], K_node)
                    if "normal" in self.potentials:
                        fitted = graph_normals(points, edge_index, x.shape[0])
                        normals = torch.where(normal_ok[:, None], node_normal, fitted)
                        terms.normal = normal_affinity(normals[src], normals[dst], self.sigma_n)
                    if "distance" in self.potentials:
                        terms.distance = distance_affinity(points[src], points[dst], self.sigma_p)
                        terms.delta = delta
                with stage("solve"):
                    x = self._graph_solve(terms, ptr, x, infos)
        with stage("painting"):
            x = to_depth(x, self.variable)  # node depths in metres from here on
            labels = torch.stack([g.labels for g in graphs]) + ptr[:-1, None, None]
            depth = x[labels][:, None]
            lidar = torch.cat([g.lidar_count for g in graphs])
            node_count = torch.where(lidar == 0, 1.0, torch.where(lidar == 1, 0.5, 0.0)).to(dtype)
            count_map = node_count[labels][:, None]
        if self.refine:
            with stage("refine"):
                depth, t = self._pixel_solve(image, sparse, K, depth, self.refine_prior * mean_weight, infos,
                                             geometry=depth, gate=gate, kept=kept)
        node_std = std = features = None
        if return_std:
            with stage("uncertainty"):
                system = graph_system(terms, ptr)
                if self.uncertainty == "posterior":
                    node_std = posterior_std(system, self.std_scale, samples=self.std_samples)
                    node_std = std_in_metres(node_std, x, self.variable)
                    std = node_std[labels][:, None]
                else:
                    if self.refine:  # the last solve is the refinement's pixel grid
                        var = system_conditional_variance(grid_system(t))[:, None]
                    else:
                        var = system_conditional_variance(system)[labels][:, None]
                    std, features = self._predictive(depth, sparse, kept, gate, var)
                    node_std = torch.cat([g.node_mean(std[b])[:, 0] for b, g in enumerate(graphs)])
        return CRFOutput(depth, std, count_map, x, node_std, ptr, graphs, terms, infos, stage.seconds, features)

    def _predictive(self, depth, sparse, kept, gate, variance) -> tuple[torch.Tensor, torch.Tensor]:
        """The predictive std (:mod:`crfdepth.uncertainty.predictive`) and its signals, from the conditional
        variance of the last solve in the unknown's units."""
        variance = (std_in_metres(variance.sqrt(), depth, self.variable) / depth.detach()) ** 2  # in (log z)^2
        features = std_features(depth, sparse, kept, gate, variance)
        return self.std_head(features), features

    def _graph_solve(self, terms: EnergyTerms, ptr, x0, infos) -> torch.Tensor:
        x, info = solve_system(graph_system(terms, ptr), x0, self.solver)
        infos.append(info)
        return x

    # -- pixel grid (pixel mode and the refinement) --------------------------------------
    def _pixel_solve(self, image, sparse, K, prior, eps, infos, geometry=None, gate=None, kept=None):
        """Pixel-level solve(s) of the grid CRF; without ``geometry`` a first pass provides it.

        Returns the (B, 1, H, W) depth and the last round's potentials.
        """
        rounds, v = 1, self.variable
        kept = sparse if kept is None else kept
        extra = dict(variable=v, gate=gate, factors=None if self.head is None else self.head(image, kept, prior))
        if geometry is None:
            t = grid_potentials(image, sparse, K, prior, eps, None, self._weights_for_grid(), **extra)
            x, info = solve_system(grid_system(t), t.prior, self.solver)
            infos.append(info)
            if "normal" not in self.potentials and "distance" not in self.potentials:
                return to_depth(x, v)[:, None], t
            geometry, rounds = to_depth(x, v)[:, None], self.rounds
        for _ in range(rounds):
            t = grid_potentials(image, sparse, K, prior, eps, geometry, self._weights_for_grid(), **extra)
            x, info = solve_system(grid_system(t), to_unknown(geometry[:, 0], v), self.solver)
            infos.append(info)
            geometry = to_depth(x, v)[:, None]
        if self.irls:
            geometry, t = reweight(t, x, sparse, self.irls, self.irls_scale, v, self.solver, infos)
        return geometry, t

    def _forward_pixel(self, image, sparse, K, return_std) -> CRFOutput:
        bsz, _, h, w = sparse.shape
        stage = Stages(sparse.device, self.progress)
        with stage("fill"):
            gate, kept, fill = self._evidence(sparse)
        eps = self._scales()[4]
        infos: list[SolveInfo] = []
        with stage("solve"):  # potentials, normals and solves of all rounds
            depth, t = self._pixel_solve(image, sparse, K, fill, eps, infos, gate=gate, kept=kept)
        std = node_std = features = None
        if return_std:
            with stage("uncertainty"):
                system = grid_system(t)
                if self.uncertainty == "posterior":
                    std = posterior_std(system, self.std_scale, samples=self.std_samples)[:, None]
                    std = std_in_metres(std, depth, self.variable)
                else:
                    std, features = self._predictive(depth, sparse, kept, gate,
                                                     system_conditional_variance(system)[:, None])
                node_std = std.reshape(-1)
        count_map = (sparse <= 0).to(sparse.dtype)
        terms = t.energy_terms()
        return CRFOutput(depth, std, count_map, depth.reshape(-1), node_std,
                         torch.arange(bsz + 1, device=sparse.device) * (h * w), None, terms, infos, stage.seconds,
                         features)


__all__ = ["CRFDepth", "CRFOutput", "POTENTIALS", "energy"]
