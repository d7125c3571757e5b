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

from typing import Any, Callable, Mapping

import torch

from crfdepth.checks import check_flag, check_frames
from crfdepth.config import FLAT, POTENTIALS, CRFConfig
from crfdepth.errors import InputError
from crfdepth.inference import PIPELINES
from crfdepth.inference.regime import REGIMES, assign, merge_outputs
from crfdepth.intrinsics import check_batch_intrinsics
from crfdepth.linalg import SolverSettings, solver_settings
from crfdepth.memory import check_frame_size, check_memory
from crfdepth.output import CRFOutput
from crfdepth.potentials.energy import PotentialWeights, energy
from crfdepth.potentials.head import PotentialHead
from crfdepth.potentials.parameters import ConstrainedWeights
from crfdepth.precision import autocast_off, widen
from crfdepth.uncertainty.predictive import PredictiveStd
from crfdepth.weights import SPARSE_REGIMES, load_state, pretrained_state, weights_path

REFERENCE_AREA = 1216 * 352  # the KITTI benchmark crop, for which ``superpixels`` is given


def asks_one_model(overrides: Mapping[str, Any]) -> bool:
    """Whether ``overrides`` (groups or flat names) set the structure or the potentials: they ask for that one
    model on every frame, no regime beside it (:meth:`CRFDepth.from_pretrained`, :func:`crfdepth.load_model`)."""
    return bool({FLAT[key][0] if key in FLAT else key for key in overrides} & {"structure", "potentials"})


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
        config: a :class:`~crfdepth.config.CRFConfig`, or a mapping of its groups
            (``{"structure": {"mode": "pixel"}, "gate": {"enabled": True}}``, what
            ``model.config``, weights files and checkpoints hold) or of flat names; None: the
            defaults below.
        **options: groups (``gate={"enabled": True}``) or flat names that replace what
            ``config`` sets; the flat names are listed below.

    The configuration is kept once, as ``model.settings`` (a checked :class:`~crfdepth.config.CRFConfig`:
    ``model.settings.structure.mode``, ``model.settings.gate.window`` ...); ``model.config`` is it as
    plain data, and ``model.solve_settings`` the solver's part as :mod:`crfdepth.linalg` takes it.

    The flat names, each a field of one group (:data:`crfdepth.config.FLAT`):

    - ``mode``: "superpixel" (paper) or "pixel".
    - ``superpixels``: SLIC segments for a 1216x352 image (paper: 1200, 2400, 5500).
    - ``scale_superpixels``: scale the segment count with the image area (any image size
      gets superpixels of the same pixel size); False uses ``superpixels`` as is.
    - ``potentials``: pairwise potentials that are on, a subset of ("colour", "normal",
      "distance"); the paper's ablation is ("colour",), ("colour", "normal"), all.
    - ``aggregate``: "mean" or "median" of the LiDAR depths in a superpixel.
    - ``refine``: superpixel mode only: follow the superpixel solve with a pixel-level solve
      whose prior is the painted superpixel solution (docs/design.md section 6); False
      keeps the paper's piecewise-constant painting.
    - ``rounds``: solves with the 3D-distance term after the first pass (>= 1).
    - ``alpha``, ``beta``, ``gamma``, ``delta``: initial weights in (0, 1). ``gamma`` defaults
      low: the normal potential joins *parallel* surfaces across a depth step as readily as
      one surface (a car's back and the wall behind it), so it is a tie-breaker
      where colour edges are not depth edges, not a main smoothness term.
    - ``sigma_d``: initial colour scale (RGB in [0, 1]); ``sigma_n``: normal scale; ``sigma_p``:
      3D-distance scale in metres.
    - ``confidence``: initial data confidence ``c`` > 0.
    - ``eps``: prior weight relative to the mean potential weight (keeps A positive
      definite; where nothing else informs a node, its depth falls back to x0).
    - ``refine_prior``: initial weight of the superpixel solution as the refinement's prior,
      relative to the mean potential weight (learnable: smaller lets the pixel solve
      depart further from the piecewise-constant superpixel depth).
    - ``std_scale``: initial ``s`` > 0.
    - ``std_samples``: samples of the posterior-variance estimate on large graphs
      (:mod:`crfdepth.uncertainty.posterior`); graphs up to 1,000 nodes are exact.
    - ``rtol``, ``max_iter``, ``method``: settings of every solve (:func:`crfdepth.linalg.solve_laplacian`).
    - ``variable``: the CRF's unknown (docs/design.md section 3b): ``"depth"`` (the paper),
      ``"inverse"`` (1/z: the smoothness terms then reproduce planes exactly) or
      ``"log"`` (log z: between the two where a pixel mixes a near and a far surface).
      Data, prior and warm start are mapped to it, depth and std are mapped back
      (``std_z = z^2 std_(1/z)``, ``z std_(log z)``); ``CRFOutput.terms`` hold the system in it.
    - ``gate``: multiply each return's data weight by the soft occlusion gate of
      :mod:`crfdepth.potentials.occlusion` (see-through returns lose weight); ``gate_window``
      (odd pixels), ``gate_threshold`` and ``gate_softness`` (1/m, learnable) set it.
    - ``prior``: the fill that is ``x0`` and the warm start, "nearest" or "ip_basic".
    - ``coarse``: pixel mode: side in pixels of the blocks of a coarse first solve whose painted depth is the
      pixel solve's prior (docs/design.md section 17); 1: none.
    - ``near_inverse``: with ``coarse`` > 1 and the depth unknown, metres: nearer than this the coarse depth
      comes from a second coarse solve in inverse depth, beyond three times it from the first, blended
      between (section 17); 0: one coarse solve.
    - ``coarse_shifts``: with ``coarse`` > 1, 2: a second coarse grid shifted by half a block, the two painted
      depths averaged (section 17); 1: one grid.
    - ``irls``: robust reweighting rounds of the pixel-grid data term after the last solve
      (:mod:`crfdepth.potentials.robust`; 0 = none): each scales a return's data weight by a
      Geman-McClure factor of how far *behind* its leave-one-out prediction it lies.
    - ``irls_scale``: initial ``sigma`` of that factor, inverse depth in 1/m (learnable).
    - ``head``: add the small learned :class:`~crfdepth.potentials.head.PotentialHead` (per-pixel data
      and edge-weight factors of the pixel-grid solves; docs/design.md section 3b).
    - ``uncertainty``: the std of ``return_std`` (docs/design.md section 5): "predictive" (the
      posterior's local part with depth, edge, data-distance and gate signals,
      :mod:`crfdepth.uncertainty.predictive`; about 0.15 x the forward's time) or "posterior"
      (``s sqrt(diag(A^-1))`` alone, sampled: about 40 solves).
    - ``std_terms``: initial weights of the predictive std by name
      (:data:`crfdepth.uncertainty.predictive.STD_TERMS`; None: the hand-set ones), learnable.
    - ``memory_limit_gb``: refuse a forward whose estimated peak memory
      (:mod:`crfdepth.memory`, an upper bound) exceeds this many GB, before
      allocating; None: the memory the device has available at each forward.

    ``torch.compile(model)`` works, under ``torch.no_grad()``, ``torch.inference_mode()`` or with
    autograd, and gives the eager depth, but compiles nothing of the CRF: its input checks and its
    pipeline always run eagerly (``torch.compiler.disable``). Their numpy steps and data-dependent
    solver loops made dynamo fail with an internal "Guard failed ... This is a bug" error (torch 2.13);
    compile the network around the CRF instead.
    """

    def __init__(self, config: CRFConfig | Mapping[str, Any] | None = None, **options: Any) -> None:
        super().__init__()
        self.settings = CRFConfig.build(config, **options)  # checked group by group as it is built
        """The configuration, the one copy (:class:`~crfdepth.config.CRFConfig`); :attr:`config` is it as plain data."""
        structure, terms, gate, std = (self.settings.structure, self.settings.potentials, self.settings.gate,
                                       self.settings.uncertainty)
        self.std_head = None if std.kind == "posterior" else PredictiveStd(std.terms)
        self.head = PotentialHead() if structure.head else None
        weights = dict(alpha=terms.alpha, beta=terms.beta, gamma=terms.gamma, delta=terms.delta, sigma_d=terms.sigma_d,
                       sigma_n=terms.sigma_n, sigma_p=terms.sigma_p, confidence=terms.confidence, std_scale=std.scale,
                       refine_prior=terms.refine_prior, gate_threshold=gate.threshold, gate_softness=gate.softness,
                       irls_scale=terms.irls_scale)
        off = set() if gate.enabled else {"gate_threshold", "gate_softness"}  # the weights of parts that are off
        if not terms.irls:
            off.add("irls_scale")
        self._register_weights({name: value for name, value in weights.items() if name not in off})
        self.register_buffer("eps", torch.tensor(float(terms.eps)))

    @property
    def config(self) -> dict[str, dict[str, Any]]:
        """What checkpoints and weights files store to rebuild the model: :attr:`settings`' five groups as
        plain data (:meth:`crfdepth.config.CRFConfig.groups`), read-only."""
        return self.settings.groups()

    @property
    def solve_settings(self) -> SolverSettings:
        """The checked settings of every linear solve (:func:`crfdepth.linalg.solver_settings`), from
        ``settings.solver``."""
        solver = self.settings.solver
        return solver_settings(method=solver.method, rtol=solver.rtol, max_iter=solver.max_iter)

    @classmethod
    def from_pretrained(cls, name: str = "kitti", *, adaptive: bool = True, **overrides) -> "CRFDepth":
        """The model with a shipped weight set, in eval mode (:func:`crfdepth.checkpoints.load_pretrained`).

        ``"kitti"``: weights learned on real KITTI frames (``crfdepth/weights/README.md``
        says how); ``"paper"``: the hand-set initial values of ``CRFDepth()``.
        ``overrides`` replace stored arguments, e.g. ``mode="superpixel"``; without them
        the model has the structure the weights were made for (kitti: pixel grid, log
        depth, occlusion gate). Stored tensors are loaded with every key checked (a
        missing or unexpected one is an error naming the file).

        ``adaptive`` (kitti on the pixel grid): frames with few returns (a median distance to the nearest
        return above 4.5 pixels: 500 samples, 16 beams) go to the hand-set weights on the pixel grid with a
        coarse first solve of 6-pixel blocks on two grids (:mod:`crfdepth.inference.regime`, docs/design.md section 17):
        :attr:`sparse_regime` (the depth unknown, near blocks in inverse depth) for scattered returns, :attr:`line_regime` (the log unknown,
        blocks twice as tall) for returns on scan lines, :attr:`indoor_regime` (the ``"nyu"`` weights) for
        scattered returns whose depths are a room's (90% within 10 m). ``overrides`` of the gate, the solver or the std apply to the shipped weights
        only; one of the structure or the potentials (``mode``, ``variable``, ``alpha`` ...) asks for that one
        model on every frame, as ``adaptive=False`` does.
        """
        check_flag("adaptive", adaptive)
        config, state = pretrained_state(name)
        model = cls.from_stored(config, state, overrides=overrides, file=weights_path(name)).eval()
        if adaptive and name in SPARSE_REGIMES and not asks_one_model(overrides):
            regimes = SPARSE_REGIMES[name]
            model.sparse_regime = cls(regimes["scattered"]).eval()
            model.line_regime = cls(regimes["lines"]).eval()
            model.indoor_regime = cls.from_pretrained(regimes["indoor"], adaptive=False)
        return model

    @classmethod
    def from_stored(cls, config: Mapping, state: dict[str, torch.Tensor], *, overrides: Mapping | None = None,
                    file=None, kind: str | None = None) -> "CRFDepth":
        """The model built from a stored configuration and state dict: the one step every loader
        (shipped sets, weights files, checkpoints) ends in, with its checks.

        ``config`` holds groups or flat names (files written before the groups);
        ``overrides`` (groups or flat names) replace what it sets. ``kind`` names the file's kind
        ("Lightning checkpoint" ...) when the configuration comes from that file, and errors in
        it name the file; without it the configuration's faults are the caller's ``overrides``.

        Raises:
            InputError: a configuration ``CRFDepth`` rejects, or tensors that do not fit it
                (:func:`crfdepth.weights.state.load_state`), naming ``file``.
        """
        try:
            model = cls(config, **dict(overrides or {}))
        except TypeError as exc:  # unknown or missing keyword arguments
            if kind is None:
                raise InputError(f"overrides: not CRFDepth arguments ({exc})") from None
            raise InputError(f"{file}: the {kind}'s model configuration does not fit CRFDepth ({exc})") from None
        except InputError as exc:
            if kind is None:
                raise
            raise InputError(f"{file}: invalid model configuration in the {kind} ({exc})") from None
        return load_state(file, model, state) if state else model

    def scales(self) -> tuple[torch.Tensor, ...]:
        """``(alpha, beta, gamma, delta, eps', mean)``: ``gamma`` / ``delta`` None for potentials that are
        off, ``eps' = eps * mean`` the prior's weight and ``mean`` that of the potentials that are on."""
        alpha = self.alpha
        beta = self.beta
        on = self.settings.potentials.on
        gamma = self.gamma if "normal" in on else None
        delta = self.delta if "distance" in on else None
        active = [t for t in (alpha, beta, gamma, delta) if t is not None]
        mean = torch.stack(active).mean()
        return alpha, beta, gamma, delta, self.eps * mean, mean

    def potential_weights(self) -> PotentialWeights:
        """The weights :func:`crfdepth.potentials.energy.grid_potentials` needs (None: potential off)."""
        alpha, beta, gamma, delta, _, _ = self.scales()
        return PotentialWeights(alpha=alpha, beta=beta, gamma=gamma, delta=delta, confidence=self.confidence,
                                sigma_d=self.sigma_d, sigma_n=self.sigma_n, sigma_p=self.sigma_p)

    def segments_for(self, height: int, width: int) -> int:
        """SLIC segments used for an image of this size."""
        structure = self.settings.structure
        if not structure.scale_superpixels:
            return structure.superpixels
        return max(16, round(structure.superpixels * height * width / REFERENCE_AREA))

    sparse_regime: "CRFDepth | None" = None
    """The model that completes frames with few, scattered returns instead of this one (:meth:`from_pretrained`'s
    ``adaptive``; :mod:`crfdepth.inference.regime`); None: this model does. Not a sub-module: its weights are
    hand-set, outside this model's ``state_dict`` and ``parameters()``; :meth:`_apply` moves and casts it with
    this model, and :func:`crfdepth.save_model` / :func:`crfdepth.save_weights` write it into the model's file
    (:mod:`crfdepth.weights.regimes`)."""
    line_regime: "CRFDepth | None" = None
    """The same for frames whose few returns lie on scan lines (16 beams)."""
    indoor_regime: "CRFDepth | None" = None
    """The same for frames whose few scattered returns are near, a room's (the indoor weights)."""

    def regimes(self) -> dict[str, "CRFDepth"]:
        """The regimes this model has (attribute name -> model), in the order of
        :data:`~crfdepth.inference.regime.REGIMES`."""
        return {name: getattr(self, name) for name in REGIMES if getattr(self, name) is not None}

    def __setattr__(self, name: str, value: Any) -> None:
        if name in REGIMES:  # kept out of the module tree (state_dict, parameters, train())
            object.__setattr__(self, name, value)
        else:
            super().__setattr__(name, value)

    def _apply(self, fn, recurse: bool = True):
        for regime in (getattr(self, name) for name in REGIMES):
            if regime is not None:
                regime._apply(fn, recurse)
        return super()._apply(fn, recurse)

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
            :class:`CRFOutput`; tensors in the dtype of ``sparse`` (float32 for float16 /
            bfloat16) on its device. Under ``torch.autocast`` the whole CRF runs with autocast
            off, so its depth is the one computed without autocast (:mod:`crfdepth.precision`).

        Raises:
            InputError: bad inputs (:func:`crfdepth.checks.check_frames`), a ``K`` that is not a
                plausible pinhole matrix of the image (:func:`crfdepth.intrinsics.check_intrinsics`,
                each frame's as ``K[b]`` when K is (B, 3, 3) with B > 1), a frame smaller
                than 2x2 pixels, or (:class:`crfdepth.memory.MemoryRefusal`) an estimated
                peak memory above ``memory_limit_gb`` or, without it, above the memory the
                device has available; size and memory are checked from the shape alone,
                before anything is allocated.
        """
        if torch.compiler.is_compiling():  # inside torch.compile: the CRF runs eagerly (_eager_forward)
            return _eager_forward(self, image, sparse, K, return_std)
        return self._forward(image, sparse, K, return_std)

    def _forward(self, image, sparse, K, return_std: bool) -> CRFOutput:
        """:meth:`forward`: the inputs checked, then the model's pipeline (``crfdepth.inference.PIPELINES``) with
        autocast off (the CRF in full precision, :mod:`crfdepth.precision`)."""
        image, sparse, K = self._checked_inputs(image, sparse, K, return_std)
        with autocast_off(sparse):
            return self.pipeline(image, sparse, K, return_std)

    def pipeline(self, image: torch.Tensor, sparse: torch.Tensor, K: torch.Tensor, return_std: bool) -> CRFOutput:
        """The model's pipeline (``crfdepth.inference.PIPELINES``) on checked inputs of one dtype and device
        (``K`` (B, 3, 3)): what :meth:`forward` and :func:`crfdepth.api.complete_checked` run. With a
        regime (:attr:`sparse_regime`, :attr:`line_regime`, :attr:`indoor_regime`), frames with few returns go to them
        (:mod:`crfdepth.inference.regime`)."""
        if all(getattr(self, name) is None for name in REGIMES):
            return PIPELINES[self.settings.structure.mode](self, image, sparse, K, return_std)
        K = K.expand(sparse.shape[0], 3, 3) if K.dim() == 2 else K
        parts = assign(self, sparse)
        if len(parts) == 1:
            return PIPELINES["pixel"](parts[0][1], image, sparse, K, return_std, lines=parts[0][2])
        return merge_outputs([(rows, PIPELINES["pixel"](model, image[rows], sparse[rows], K[rows], return_std,
                                                        lines=lines)) for rows, model, lines in parts],
                             sparse.shape[0])

    def _checked_inputs(self, image, sparse, K, return_std: bool) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """The inputs of :meth:`forward` checked (docs/design.md section 8) and in the dtype of ``sparse``."""
        check_flag("return_std", return_std)
        image, sparse, K = widen(image), widen(sparse), widen(K)
        if isinstance(sparse, torch.Tensor) and sparse.dim() == 4 and sparse.is_floating_point():
            # Size and memory first, from the shape alone: the checks below allocate per pixel.
            check_frame_size("image", *sparse.shape[2:])
            settings = self.settings
            check_memory(settings.structure.mode, *sparse.shape[:1], *sparse.shape[2:], return_std,
                         settings.uncertainty.kind, sparse.dtype, sparse.device, settings.solver.memory_limit_gb)
        batched = isinstance(K, torch.Tensor) and K.dim() == 3 and K.shape[0] > 1
        image, sparse, K = check_frames(image, sparse, K)
        check_batch_intrinsics(K, tuple(sparse.shape[2:]), batched)
        return image.to(sparse.dtype), sparse, K.to(sparse.dtype)


# CRFDepth._forward kept out of torch.compile's graphs: the checks read values on the host (numpy, float) and the
# pipeline holds numpy steps (superpixels, the nearest fill, the solver's bookkeeping) and data-dependent loops,
# which made dynamo fail with an internal "Guard failed ... This is a bug" error under torch.no_grad() and
# torch.inference_mode() (torch 2.13). torch._disable_dynamo is torch.compiler.disable that imports dynamo (about
# 1 s) at its first call, which only a compiled forward makes, instead of when this module is imported.
_eager_forward = getattr(torch, "_disable_dynamo", torch.compiler.disable)(CRFDepth._forward)

__all__ = ["CRFDepth", "CRFOutput", "POTENTIALS", "energy"]
