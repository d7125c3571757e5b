"""The configuration of a :class:`~crfdepth.model.CRFDepth`, in five typed groups (docs/design.md section 8).

- :class:`Structure`: the graph (superpixels or the pixel grid), the unknown, the fill, the head.
- :class:`Potentials`: which pairwise terms are on and the initial weights of all terms.
- :class:`Gate`: the occlusion gate of the data term (section 3b).
- :class:`Solver`: the linear solves and the memory they may take.
- :class:`Uncertainty`: which standard deviation ``return_std`` gives, and its settings.

The weights file, the checkpoint and the trainer's YAML hold these groups
(``{"structure": {"mode": "pixel"}, "gate": {"enabled": true}}``); a group left out, or a field
left out of a group, keeps its default. Every field also has a flat name, the keyword argument of
``CRFDepth`` before the groups (``mode``, ``gate``, ``gate_window`` ...; :data:`FLAT`), which
files written before the groups use and which ``CRFDepth(mode="pixel")`` still takes.

Each group checks its fields as it is built, and :class:`CRFConfig` the rules across groups (the
gate needs the mean aggregate): a :class:`~crfdepth.errors.InputError` naming the field by its flat
name, the one users know (``Gate(window=4)``: ``gate_window: expected an odd int >= 3 (pixels), got 4``).
The solver's ``method`` / ``rtol`` / ``max_iter`` (:func:`check_solver`) and the std's ``terms``
(:func:`check_std_terms`) are checked here too, by the functions that :mod:`crfdepth.linalg` and
:mod:`crfdepth.uncertainty.predictive` (modules above this one) call on the same values.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field
from typing import Any, Literal, Mapping

from crfdepth.checks import check_choice, check_number
from crfdepth.errors import InputError

Mode = Literal["superpixel", "pixel"]
MODES = ("superpixel", "pixel")
Variable = Literal["depth", "inverse", "log"]
VARIABLES = ("depth", "inverse", "log")
"""The CRF's unknown (section 3b): ``"depth"`` solves for z (the paper), ``"inverse"`` for 1/z, on
which a membrane prior reproduces planes exactly, ``"log"`` for log z, between the two: a pixel
mixing a near and a far surface lands at their geometric mean."""
PRIORS = ("nearest", "ip_basic")
POTENTIALS = ("colour", "normal", "distance")
UNCERTAINTIES = ("predictive", "posterior")  # the std of ``return_std`` (section 5)

SOLVER_METHODS = ("cg", "cgs")  # the Krylov methods of crfdepth.linalg.adjoint
STD_TERMS = ("bias", "depth", "posterior", "distance", "edge", "gate")
"""Names of the predictive std's weights (:mod:`crfdepth.uncertainty.predictive`): ``bias`` (log metres), then
one exponent per signal."""
DEFAULT_STD_TERMS = {"bias": -1.35, "depth": 1.17, "posterior": 0.64, "distance": 1.09, "edge": 0.95, "gate": 0.19}
"""Hand-set weights: the shipped weights' fit on raw KITTI scans, rounded (crfdepth/weights/README.md)."""

MAX_COARSE = 64
"""Largest block side of the coarse solve, pixels (``Structure.coarse``)."""
MAX_NEAR_INVERSE = 1000.0
"""Largest ``Structure.near_inverse``, metres."""

DEFAULT_WINDOW = 5
"""Side of the occlusion gate's square neighbourhood, pixels (:mod:`crfdepth.potentials.occlusion`)."""
DEFAULT_THRESHOLD = 0.015
"""Inverse-depth lead r above which a return is see-through, 1/m."""
DEFAULT_SOFTNESS = 0.003
"""Width of the soft gate's transition in r, 1/m."""
DEFAULT_IRLS_SCALE = 0.015
"""``sigma`` of the robust reweighting's Geman-McClure factor, 1/m: the occlusion gate's threshold,
so that a return that far behind its prediction keeps a quarter of its weight."""


def _check_choice(name: str, value: Any, choices: tuple[str, ...]) -> None:
    if value not in choices:
        raise InputError(f"{name}: expected one of {choices}, got {value!r}")


def check_solver(method: object, rtol: object, max_iter: object) -> None:
    """A solve's ``method`` (one of :data:`SOLVER_METHODS`), ``rtol`` (in (0, 1)) and ``max_iter`` (an int >= 0
    or None), errors naming each."""
    check_choice("method", method, SOLVER_METHODS)
    if not (isinstance(rtol, (int, float)) and 0 < rtol < 1):
        raise InputError(f"rtol: expected a number in (0, 1), got {rtol!r}")
    if max_iter is not None and (isinstance(max_iter, bool) or not isinstance(max_iter, int) or max_iter < 0):
        raise InputError(f"max_iter: expected a non-negative int or None, got {max_iter!r}")


MAX_STD_SAMPLES = 4096
"""Most samples of the posterior-variance estimate: its error falls as 1 / sqrt(samples), so 4096 is already
1.6% of one sample's, and each sample is a solve (a 20-digit count would run for ever)."""


def check_std_samples(samples: object, name: str = "std_samples") -> int:
    """``samples`` of the variance estimate, an integer in [1, :data:`MAX_STD_SAMPLES`], told under ``name`` (the
    keyword the caller gave it by: ``std_samples`` for the model and the layer, ``samples`` for the std
    functions)."""
    return check_number(name, samples, low=1, high=MAX_STD_SAMPLES, low_open=False, high_open=False, integer=True)


def check_std_terms(terms: Mapping[str, float] | None, name: str = "std_terms") -> dict[str, float]:
    """``terms`` as floats in the order of :data:`STD_TERMS` (None: :data:`DEFAULT_STD_TERMS`); errors name
    ``name``."""
    if terms is None:
        return dict(DEFAULT_STD_TERMS)
    if not isinstance(terms, Mapping) or set(terms) != set(STD_TERMS):
        got = sorted(terms) if isinstance(terms, Mapping) else type(terms).__name__
        raise InputError(f"{name}: expected a mapping with the keys {STD_TERMS}, got {got}")
    bad = {k: v for k, v in terms.items() if isinstance(v, bool) or not isinstance(v, (int, float))
           or not math.isfinite(v)}
    if bad:
        raise InputError(f"{name}: expected finite numbers, got {bad}")
    return {k: float(terms[k]) for k in STD_TERMS}


def _check_positive(group: Any, names: dict[str, str]) -> None:
    """Each field of ``group`` named by the keys of ``names`` a finite number > 0, errors naming the value."""
    for flat, name in names.items():
        check_number(flat, getattr(group, name), low=0.0)


@dataclass(frozen=True)
class Structure:
    """The graph and what it solves for (section 2, 3b, 6)."""

    mode: Mode = "superpixel"
    superpixels: int = 5500  # SLIC segments for a 1216x352 image
    scale_superpixels: bool = True
    aggregate: Literal["mean", "median"] = "mean"
    refine: bool = True
    rounds: int = 1
    variable: Variable = "depth"
    prior: Literal["nearest", "ip_basic"] = "nearest"
    head: bool = False
    coarse: int = 1
    """Pixel mode: side in pixels of the square blocks of a coarse first solve whose depth is the pixel
    solve's prior (section 17); 1: no coarse solve."""
    near_inverse: float = 0.0
    """With the depth unknown and a coarse solve: metres below which the coarse depth comes from a second
    coarse solve in inverse depth, blended into the first linearly up to three times this depth (section 17);
    0: one coarse solve."""
    coarse_shifts: int = 1
    """With a coarse solve: 2 solves it a second time on a grid that starts half a block up and left of the frame,
    and averages the two painted depths (cycle spinning, section 17); 1: one grid."""

    def __post_init__(self) -> None:
        for name, choices in (("mode", MODES), ("variable", VARIABLES), ("prior", PRIORS)):
            _check_choice(name, getattr(self, name), choices)
        check_number("superpixels", self.superpixels, low=1, low_open=False, integer=True)
        check_number("coarse", self.coarse, low=1, high=MAX_COARSE, low_open=False, high_open=False, integer=True)
        check_number("rounds", self.rounds, low=1, low_open=False, integer=True)
        check_number("near_inverse", self.near_inverse, low=0.0, high=MAX_NEAR_INVERSE, low_open=False,
                     high_open=False)
        check_number("coarse_shifts", self.coarse_shifts, low=1, high=2, low_open=False, high_open=False,
                     integer=True)
        if self.coarse_shifts > 1 and (self.coarse == 1 or self.mode != "pixel"):
            raise InputError(f"coarse_shifts: expected 1 unless the pixel grid has a coarse solve (mode 'pixel', "
                             f"coarse > 1), got {self.coarse_shifts} with mode {self.mode!r}, coarse {self.coarse}")
        if self.near_inverse > 0 and (self.coarse == 1 or self.variable != "depth" or self.mode != "pixel"):
            raise InputError(f"near_inverse: expected 0 unless the pixel grid solves for depth with a coarse solve "
                             f"(mode 'pixel', variable 'depth', coarse > 1), got {self.near_inverse} with mode "
                             f"{self.mode!r}, variable {self.variable!r}, coarse {self.coarse}")


@dataclass(frozen=True)
class Potentials:
    """The pairwise terms that are on and the initial weights of every term (section 3)."""

    on: tuple[str, ...] = POTENTIALS
    alpha: float = 0.5
    beta: float = 0.5
    gamma: float = 0.05
    delta: float = 0.25
    sigma_d: float = 0.1
    sigma_n: float = 0.3
    sigma_p: float = 1.0
    confidence: float = 100.0
    eps: float = 0.1
    refine_prior: float = 0.05
    irls: int = 0
    irls_scale: float = DEFAULT_IRLS_SCALE

    def __post_init__(self) -> None:
        if isinstance(self.on, list):  # as YAML and JSON give it; stored as a tuple
            object.__setattr__(self, "on", tuple(self.on))
        if set(self.on) - set(POTENTIALS) or "colour" not in self.on:
            raise InputError(f"potentials: expected a subset of {POTENTIALS} containing 'colour', "
                             f"got {tuple(self.on)!r}")
        check_number("irls", self.irls, low=0, low_open=False, integer=True)
        for name in ("alpha", "beta", "gamma", "delta"):
            check_number(name, getattr(self, name), low=0.0, high=1.0)
        _check_positive(self, {name: name for name in ("sigma_d", "sigma_n", "sigma_p", "confidence", "eps",
                                                       "refine_prior", "irls_scale")})


@dataclass(frozen=True)
class Gate:
    """The soft occlusion gate on each return's data weight (section 3b)."""

    enabled: bool = False
    window: int = DEFAULT_WINDOW
    threshold: float = DEFAULT_THRESHOLD
    softness: float = DEFAULT_SOFTNESS

    def __post_init__(self) -> None:
        window = self.window
        if isinstance(window, bool) or not isinstance(window, int) or window < 3 or window % 2 == 0:
            raise InputError(f"gate_window: expected an odd int >= 3 (pixels), got {window!r}")
        _check_positive(self, {"gate_threshold": "threshold", "gate_softness": "softness"})


@dataclass(frozen=True)
class Solver:
    """Settings of every linear solve (section 4) and the memory a forward may take (section 10)."""

    method: Literal["cg", "cgs"] = "cg"
    rtol: float = 1e-5
    max_iter: int | None = None
    memory_limit_gb: float | None = None

    def __post_init__(self) -> None:
        check_solver(self.method, self.rtol, self.max_iter)
        if self.memory_limit_gb is not None:
            check_number("memory_limit_gb", self.memory_limit_gb, low=0.0)


@dataclass(frozen=True)
class Uncertainty:
    """The std of ``return_std`` (section 5)."""

    kind: Literal["predictive", "posterior"] = "predictive"
    scale: float = 1.0
    samples: int = 32
    terms: Mapping[str, float] | None = None

    def __post_init__(self) -> None:
        check_std_terms(self.terms)  # kept as given (None: the hand-set ones), so files store what was given
        _check_choice("uncertainty", self.kind, UNCERTAINTIES)
        _check_positive(self, {"std_scale": "scale"})
        # named by CRFDepth's keyword (std_samples), not the field, and refused when built, not at the first std
        check_std_samples(self.samples)


GROUPS: dict[str, type] = {"structure": Structure, "potentials": Potentials, "gate": Gate, "solver": Solver,
                           "uncertainty": Uncertainty}

FLAT: dict[str, tuple[str, str]] = {
    **{name: ("structure", name) for name in ("mode", "superpixels", "scale_superpixels", "aggregate", "refine",
                                              "rounds", "variable", "prior", "head", "coarse",
                                              "near_inverse", "coarse_shifts")},
    "potentials": ("potentials", "on"),
    **{name: ("potentials", name) for name in ("alpha", "beta", "gamma", "delta", "sigma_d", "sigma_n", "sigma_p",
                                               "confidence", "eps", "refine_prior", "irls", "irls_scale")},
    "gate": ("gate", "enabled"), "gate_window": ("gate", "window"), "gate_threshold": ("gate", "threshold"),
    "gate_softness": ("gate", "softness"),
    **{name: ("solver", name) for name in ("method", "rtol", "max_iter", "memory_limit_gb")},
    "uncertainty": ("uncertainty", "kind"), "std_scale": ("uncertainty", "scale"),
    "std_samples": ("uncertainty", "samples"), "std_terms": ("uncertainty", "terms"),
}
"""Flat name (``CRFDepth``'s keyword argument, and the key in files written before the groups) ->
(group, field)."""


def is_group(value: Any) -> bool:
    """A group's value: a mapping of its fields or the group's dataclass (a flat option such as
    ``gate=True`` or ``potentials=("colour",)`` is not)."""
    return isinstance(value, Mapping) or (dataclasses.is_dataclass(value) and not isinstance(value, type))


def is_grouped(config: Mapping[str, Any]) -> bool:
    """Does ``config`` hold groups (the current files) rather than flat names (older ones)?"""
    return any(key in GROUPS and is_group(value) for key, value in config.items())


@dataclass(frozen=True)
class CRFConfig:
    """The whole configuration: five groups."""

    structure: Structure = field(default_factory=Structure)
    potentials: Potentials = field(default_factory=Potentials)
    gate: Gate = field(default_factory=Gate)
    solver: Solver = field(default_factory=Solver)
    uncertainty: Uncertainty = field(default_factory=Uncertainty)

    def __post_init__(self) -> None:
        """The checks across groups (each group checks its own fields as it is built)."""
        if self.gate.enabled and self.structure.aggregate != "mean":
            raise InputError(f"aggregate: the occlusion gate weights a mean, expected 'mean' with gate=True, "
                             f"got {self.structure.aggregate!r}")

    @classmethod
    def build(cls, config: CRFConfig | Mapping[str, Any] | None = None, **options: Any) -> CRFConfig:
        """The configuration from a base (a :class:`CRFConfig`, a mapping of groups or of flat names,
        or None for the defaults) and ``options``: groups (``gate={"enabled": True}``) or flat names
        (``mode="pixel"``, ``gate=True``), applied in that order.

        Raises:
            TypeError: a name that is neither a group nor a flat name, or a field a group does not
                have (as for any unknown keyword argument).
            InputError: a value a group refuses (its ``__post_init__``), named by its flat name
                (``gate_window: expected an odd int >= 3 (pixels), got 4``).
        """
        result = config if isinstance(config, CRFConfig) else cls()._with(config or {})
        return result._with(options)

    def _with(self, values: Mapping[str, Any]) -> CRFConfig:
        """This configuration with ``values`` (groups, then flat names over them) applied: each group's
        updates in one ``dataclasses.replace``, so that a group is only ever checked whole."""
        updates: dict[str, dict[str, Any]] = {name: {} for name in GROUPS}
        flat = {}
        for key, value in values.items():
            if key in GROUPS and is_group(value):
                update = dataclasses.asdict(value) if dataclasses.is_dataclass(value) else dict(value)
                unknown = sorted(set(update) - {f.name for f in dataclasses.fields(GROUPS[key])})
                if unknown:
                    raise TypeError(f"CRFDepth() got unexpected {key} field(s) {', '.join(map(repr, unknown))}")
                updates[key].update(update)
            elif key in FLAT:
                flat[key] = value
            else:
                raise TypeError(f"CRFDepth() got an unexpected keyword argument {key!r}")
        for key, value in flat.items():
            group, name = FLAT[key]
            updates[group][name] = value
        return CRFConfig(**{name: dataclasses.replace(getattr(self, name), **update) if update else getattr(self, name)
                            for name, update in updates.items()})

    def flat(self) -> dict[str, Any]:
        """The configuration by flat names (every one of :data:`FLAT`)."""
        return {key: getattr(getattr(self, group), name) for key, (group, name) in FLAT.items()}

    def groups(self) -> dict[str, dict[str, Any]]:
        """The configuration as plain data, group by group (what files and checkpoints store)."""
        return {name: {f.name: plain_data(getattr(getattr(self, name), f.name)) for f in dataclasses.fields(kind)}
                for name, kind in GROUPS.items()}


def flat_view(config: Mapping[str, Any]) -> dict[str, Any]:
    """The flat names a stored configuration sets (grouped or flat), without filling defaults."""
    if not is_grouped(config):
        return dict(config)
    by_field = {value: key for key, value in FLAT.items()}
    return {by_field[(group, name)]: value for group, fields in config.items() if group in GROUPS
            for name, value in dict(fields).items() if (group, name) in by_field}


def plain_data(value: Any) -> Any:
    """Tuples as lists and mappings as dicts, recursively: what JSON and ``torch.load(weights_only=True)``
    read back as they were written."""
    if isinstance(value, Mapping):
        return {k: plain_data(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [plain_data(v) for v in value]
    return value
