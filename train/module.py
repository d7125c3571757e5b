"""The Lightning module that learns the CRF's potential weights (docs/design.md sections 3, 5, 7).

:class:`CRFDepthModule` wraps one :class:`crfdepth.model.CRFDepth` as ``self.model`` and
fits its few parameters (alpha..delta, the sigmas, the data confidence, the refinement
prior and, with a negative log-likelihood term, the std scale) with Adam, by backpropagating a depth loss on
the target pixels through the CRF's implicit solves.

Checkpoint contract (read by :func:`crfdepth.load_model` and
``crfdepth evaluate``): state-dict keys are ``model.<parameter>``, and
``checkpoint["hyper_parameters"]["crf"]`` holds the model's whole configuration in its five
groups (``CRFDepth(crf)`` rebuilds the model; :mod:`crfdepth.config`; the defaults are written
out when the config gave none). All hyperparameters are plain Python values, so
``torch.load(path, weights_only=True)`` reads the checkpoint.

Logged (``self.log``; TensorBoard by default):

- ``train/loss`` (the objective), ``train/depth_loss`` (L2 in m^2 or L1 in m), with
  ``nll_weight > 0`` ``train/nll``, and with ``photometric_weight > 0``
  ``train/photometric`` (the unweighted photometric error); per step and per epoch.
- ``val/rmse`` ``val/mae`` (mm), ``val/irmse`` ``val/imae`` (1/km), ``val/rel``,
  ``val/delta1`` and ``val/loss`` (the training objective): computed per image, averaged
  over all validation images of the epoch (across DDP processes too).
- ``weights/<name>`` for every value of ``CRFDepth.weights()``, each epoch.
- When the sanity check before training covers the whole validation set
  (``trainer.num_sanity_val_steps: -1``), its metrics and the initial weights are logged
  at step 0: the validation curve then starts at the untrained model.
"""

from __future__ import annotations

import copy
import dataclasses
import difflib
import logging
import math
from collections.abc import Mapping
from typing import Any, Literal

import lightning.pytorch as pl
import torch
import torch.nn.functional as F

from crfdepth.config import FLAT, GROUPS, CRFConfig, is_group
from crfdepth.data.sample import Batch
from crfdepth.errors import InputError
from crfdepth.metrics import METRICS, format_metrics
from crfdepth.model import CRFDepth
from crfdepth.sequences.photometric import photometric_loss
from train.metrics import DepthMetrics

log = logging.getLogger(__name__)

#: Constrained weight name -> the free parameter of ``CRFDepth`` underneath it.
PARAMETERS = {
    "alpha": "raw_alpha", "beta": "raw_beta", "gamma": "raw_gamma", "delta": "raw_delta",
    "sigma_d": "log_sigma_d", "sigma_n": "log_sigma_n", "sigma_p": "log_sigma_p",
    "confidence": "log_confidence", "refine_prior": "log_refine_prior", "std_scale": "log_std_scale",
    "gate_threshold": "log_gate_threshold", "gate_softness": "log_gate_softness",
    "irls_scale": "log_irls_scale",
}


#: The default of ``CRFDepthModule(crf=...)``: all defaults (frozen, so one instance serves every module).
DEFAULT_CRF = CRFConfig()


def _finite(value: Any) -> bool:
    """A finite int or float (not a bool): nan and inf pass no range check below."""
    return isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)


def _did_you_mean(name: str, known) -> str:
    close = difflib.get_close_matches(name, list(known), n=1)
    return f" (did you mean {close[0]!r}?)" if close else ""


def build_model(crf: CRFConfig | Mapping[str, Any] | None) -> CRFDepth:
    """``CRFDepth(crf)`` with every fault of ``crf`` one :class:`~crfdepth.errors.InputError` naming the key
    as the config gives it: ``crf.gate: expected fields among enabled, window, ..., got 'windw' (did you
    mean 'window'?)``, ``crf.structure.mode: expected one of ...`` (``crf.mode`` when given flat). ``crf``: a
    :class:`~crfdepth.config.CRFConfig`, a mapping of groups or flat names, or None (the defaults)."""
    if crf is not None and not isinstance(crf, (CRFConfig, Mapping)):
        raise InputError(f"crf: expected a mapping of CRFDepth options (groups such as {{structure: {{mode: pixel}}}} "
                         f"or flat names such as {{mode: pixel}}), got {type(crf).__name__} {crf!r}")
    given = crf if isinstance(crf, Mapping) else {}
    for key, value in given.items():
        if key in GROUPS and isinstance(value, Mapping):
            fields = [f.name for f in dataclasses.fields(GROUPS[key])]
            unknown = [str(k) for k in value if k not in fields]
            if unknown:
                raise InputError(f"crf.{key}: expected fields among {', '.join(fields)}, got {unknown[0]!r}"
                                 f"{_did_you_mean(unknown[0], fields)}")
        elif key not in FLAT and not (key in GROUPS and is_group(value)):
            raise InputError(f"crf: expected the groups {', '.join(GROUPS)} or flat CRFDepth options, got {key!r}"
                             f"{_did_you_mean(str(key), [*GROUPS, *FLAT])}")
    try:
        return CRFDepth(crf)
    except InputError as exc:  # "<flat name>: expected ...": name it where the config sets it
        name, _, rest = str(exc).partition(": ")
        if name in FLAT and rest:
            group, field = FLAT[name]
            where = f"crf.{name}" if name in given and not is_group(given[name]) else f"crf.{group}.{field}"
            raise InputError(f"{where}: {rest}") from None
        raise InputError(f"crf: {exc}") from None
    except (TypeError, ValueError) as exc:  # a value of the wrong kind deep inside
        raise InputError(f"crf: expected CRFDepth options of the right types, got {crf!r} ({exc})") from None


def depth_loss(depth: torch.Tensor, target: torch.Tensor, kind: Literal["l2", "l1", "huber"] = "l2",
               huber_delta: float = 1.0) -> torch.Tensor:
    """Per-image depth loss over the target pixels.

    Args:
        depth: (B, 1, H, W) predicted depth in metres.
        target: (B, 1, H, W) ground truth in metres, 0 = none.
        kind: "l2" (mean squared error, m^2), "l1" (mean absolute error, m) or "huber": the
            squared error up to ``huber_delta`` metres of error and linear beyond, with the
            same slope there (``2 delta |e| - delta^2``; twice torch's ``huber_loss``, so that
            it equals "l2" on small errors). A target wrong by more than ``delta`` (a
            see-through return or a mover's smear the cleaning kept) then pulls with a bounded
            force, where "l2" lets it dominate (docs/design.md section 15).
        huber_delta: metres; used by "huber" only.

    Returns:
        (B,) mean over each image's target pixels; 0 for an image without any (and no
        gradient from it).
    """
    valid = target > 0
    err = torch.where(valid, depth - target, torch.zeros_like(depth))
    if kind == "l2":
        err = err.square()
    elif kind == "l1":
        err = err.abs()
    elif kind == "huber":
        err = 2 * F.huber_loss(err, torch.zeros_like(err), reduction="none", delta=huber_delta)
    else:
        raise InputError(f"loss: expected 'l2', 'l1' or 'huber', got {kind!r}")
    return err.flatten(1).sum(1) / valid.flatten(1).sum(1).clamp_min(1)


def gaussian_nll(depth: torch.Tensor, std: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """Per-image Gaussian negative log-likelihood of the targets (docs/design.md section 5).

    ``log std + (x - t)^2 / (2 std^2)`` (the constant ``log sqrt(2 pi)`` left out),
    averaged over each image's target pixels. ``depth`` is used as given: detach it to
    fit only the std.

    Args:
        depth: (B, 1, H, W) predicted depth ``x`` in metres.
        std: (B, 1, H, W) predicted standard deviation in metres, > 0.
        target: (B, 1, H, W) ground truth ``t`` in metres, 0 = none.

    Returns:
        (B,) per-image NLL; 0 for an image without target pixels.
    """
    valid = target > 0
    std = torch.where(valid, std, torch.ones_like(std)).clamp_min(1e-6)
    nll = std.log() + torch.where(valid, depth - target, torch.zeros_like(depth)).square() / (2.0 * std.square())
    nll = torch.where(valid, nll, torch.zeros_like(nll))
    return nll.flatten(1).sum(1) / valid.flatten(1).sum(1).clamp_min(1)


class CRFDepthModule(pl.LightningModule):
    """Learn the weights of a :class:`~crfdepth.model.CRFDepth` from depth targets.

    Objective per batch (mean over the images that have target pixels)::

        loss = depth_loss(x, t) + nll_weight * NLL(t | x.detach(), std)
               + photometric_weight * photometric_loss(I_t, I_s, x, K, T_s<-t)

    ``depth_loss`` is the per-image mean over target pixels (``t > 0``) of
    ``(x - t)^2`` (``"l2"``, m^2), ``|x - t|`` (``"l1"``, m) or the squared error up to
    ``huber_delta`` and linear beyond (``"huber"``, m^2). The NLL term sees the
    depth detached, so it fits the std's weights only (the predictive std's ``std_head``, or
    the posterior std's scale ``s`` with ``uncertainty="posterior"``; docs/design.md
    section 5) and the depth loss alone decides the potential weights. With
    ``nll_weight = 0`` the std is not computed and its weights stay frozen (the shipped
    recipe fits them after training: ``python -m train.export --calibrate-std``).

    Args:
        crf: the model's configuration, a :class:`~crfdepth.config.CRFConfig` (its five groups; the
            default: all defaults). Typed so that LightningCLI reads it by groups and checks each field
            (``model: {crf: {structure: {mode: pixel}, gate: {enabled: true}}}``, ``--model.crf.gate.window 7``;
            :mod:`train.options`). From Python a mapping of groups or of flat ``CRFDepth`` arguments
            (``{"mode": "pixel"}``) or None is taken too. Stored complete, in groups, in the hyperparameters.
        loss: "l2", "l1" or "huber" (:func:`depth_loss`).
        huber_delta: metres of error where "huber" turns from squared to linear (> 0).
        exclude_inputs: leave out of the depth loss and the NLL the target pixels where the
            input has a return, so that only completion is scored. A camera-view target holds
            the frame's own scan where it is consistent (docs/design.md section 14, rule c), so
            at those pixels it is the input itself (98% within 0.5% on drive 0060), where KITTI's
            annotation differs from the input by more at a quarter of them. On drive 0060 it moved
            no protocol by more than 0.001 (run E17s, docs/design.md section 15); off by default.
        nll_weight: weight of the Gaussian NLL term (>= 0).
        lr: Adam learning rate on the free (unconstrained) parameters: logits of
            alpha..delta, logs of the sigmas, confidence and std scale.
        freeze: names of weights to keep at their initial value (any of alpha, beta,
            gamma, delta, sigma_d, sigma_n, sigma_p, confidence, refine_prior, std_scale,
            gate_threshold, gate_softness, irls_scale).
        head_lr: Adam learning rate of the small learned head (``crf: {structure: {head: true}}``), whose
            weights are ordinary network weights rather than logs of scalars.
        photometric_weight: weight of the photometric self-supervision (>= 0; 0 = off):
            :func:`crfdepth.sequences.photometric.photometric_loss` of the predicted depth, per image
            (``reduction="frame"``, ``allow_empty=True``: a fully masked frame adds 0), with
            the batch's ``neighbours`` and ``poses``, which only the ``sequence`` layout
            gives (:class:`crfdepth.data.sequences.SequenceFrames`; docs/design.md section 13).
            With a weight > 0, data without neighbours is refused at setup (a data module
            of another layout) or at the first such batch.

    Batches are :class:`~crfdepth.data.sample.Batch` objects; Lightning moves them to the
    device through ``Batch.to`` (its default ``transfer_batch_to_device``).

    Parameters the model does not use (the weights of potentials that are off; the
    refinement prior without a painted solution to weigh (no superpixel refinement, no coarse solve); the std scale without NLL) are frozen too, so every trainable parameter gets a gradient each
    step (as DDP requires).
    """

    def __init__(
        self,
        crf: CRFConfig = DEFAULT_CRF,
        loss: Literal["l2", "l1", "huber"] = "l2",
        nll_weight: float = 0.0,
        lr: float = 0.05,
        freeze: list[str] | None = None,
        head_lr: float = 2e-3,
        photometric_weight: float = 0.0,
        huber_delta: float = 1.0,
        exclude_inputs: bool = False,
    ) -> None:
        super().__init__()
        if not isinstance(exclude_inputs, bool):
            raise InputError(f"exclude_inputs: expected true or false, got {exclude_inputs!r}")
        if loss not in ("l2", "l1", "huber"):
            raise InputError(f"loss: expected 'l2', 'l1' or 'huber', got {loss!r}")
        if not _finite(huber_delta) or not huber_delta > 0:
            raise InputError(f"huber_delta: expected a number of metres > 0, got {huber_delta!r}")
        if not _finite(nll_weight) or nll_weight < 0:
            raise InputError(f"nll_weight: expected a number >= 0, got {nll_weight!r}")
        if not _finite(photometric_weight) or photometric_weight < 0:
            raise InputError(f"photometric_weight: expected a number >= 0, got {photometric_weight!r}")
        for name, value in (("lr", lr), ("head_lr", head_lr)):
            if not _finite(value) or value <= 0:
                raise InputError(f"{name}: expected a learning rate > 0, got {value!r}")
        unknown = set(freeze or ()) - set(PARAMETERS)
        if unknown:
            raise InputError(f"freeze: expected names among {', '.join(PARAMETERS)}, got {sorted(unknown)}")
        self.model = build_model(crf)
        self.save_hyperparameters()
        # Self-describing checkpoints: the complete constructor arguments, plain values.
        self.hparams["crf"] = copy.deepcopy(self.model.config)
        self.loss_kind = loss
        self.huber_delta = float(huber_delta)
        self.exclude_inputs = exclude_inputs
        self.nll_weight = float(nll_weight)
        self.photometric_weight = float(photometric_weight)
        self.lr = float(lr)
        self.head_lr = float(head_lr)
        frozen, settings = set(freeze or ()), self.model.settings
        if self.nll_weight == 0 or settings.uncertainty.kind == "predictive":
            frozen.add("std_scale")  # the posterior std's scale: trained by the NLL term of a posterior model
        if self.model.std_head is not None and self.nll_weight == 0:
            self.model.std_head.requires_grad_(False)  # the predictive std's weights: by the NLL term, or after
        if "normal" not in settings.potentials.on:
            frozen.update(("gamma", "sigma_n"))
        if "distance" not in settings.potentials.on:
            frozen.update(("delta", "sigma_p"))
        structure = settings.structure
        if (not structure.refine) if structure.mode == "superpixel" else structure.coarse <= 1:
            frozen.add("refine_prior")  # weighs a painted solution: the superpixels' or the coarse blocks'
        for name in frozen:
            if hasattr(self.model, PARAMETERS[name]):  # the gate's exist only with gate=True
                getattr(self.model, PARAMETERS[name]).requires_grad_(False)
        self.frozen = tuple(n for n in PARAMETERS if n in frozen)
        self.val_metrics = DepthMetrics(extra=("loss",))

    # -- steps ----------------------------------------------------------------------------
    def _data_layout(self) -> str | None:
        """The layout of the attached data module (``CRFDataModule.layout``), if any."""
        trainer = self._trainer
        datamodule = getattr(trainer, "datamodule", None) if trainer is not None else None
        return getattr(datamodule, "layout", None)

    def _no_neighbours(self, layout: str | None) -> InputError:
        got = f"layout {layout!r}" if layout is not None else "batches without neighbouring frames"
        return InputError(f"photometric_weight: expected data with neighbouring frames and poses (data.layout "
                          f"'sequence') for photometric_weight={self.photometric_weight:g}, got {got}; use the "
                          f"sequence layout or set photometric_weight: 0")

    def setup(self, stage: str) -> None:
        if self.photometric_weight > 0:
            layout = self._data_layout()
            if layout is not None and layout != "sequence":
                raise self._no_neighbours(layout)

    def forward(self, batch: Batch, return_std: bool = False):
        """The CRF on a :class:`~crfdepth.data.sample.Batch`: a ``CRFOutput``."""
        return self.model(batch.image, batch.sparse, batch.K, return_std=return_std)

    def _objective(self, batch: Batch) -> tuple[torch.Tensor, dict[str, torch.Tensor], Any]:
        """Per-image losses of a batch: ``(loss (B,), parts, output)``."""
        want_std = self.nll_weight > 0
        out = self(batch, return_std=want_std)
        target = batch.target
        if self.exclude_inputs:
            target = torch.where(batch.sparse > 0, torch.zeros_like(target), target)
        parts = {"depth_loss": depth_loss(out.depth, target, self.loss_kind, self.huber_delta)}
        loss = parts["depth_loss"]
        if want_std:
            parts["nll"] = gaussian_nll(out.depth.detach(), out.std, target)
            loss = loss + self.nll_weight * parts["nll"]
        if self.photometric_weight > 0:
            if batch.neighbours is None or batch.poses is None:
                # an extra_train source without neighbours (e.g. synthetic scenes) beside a sequence
                # layout: no photometric term for that batch; any other layout is a configuration error
                if self._data_layout() != "sequence":
                    raise self._no_neighbours(self._data_layout())
                parts["photometric"] = torch.zeros_like(loss)
            else:
                parts["photometric"] = photometric_loss(batch.image, batch.neighbours, out.depth, batch.K,
                                                        batch.poses, allow_empty=True, reduction="frame")
            loss = loss + self.photometric_weight * parts["photometric"]
        return loss, parts, out

    def training_step(self, batch: Batch, batch_idx: int) -> torch.Tensor:
        loss, parts, out = self._objective(batch)
        has = (batch.target.flatten(1) > 0).any(1)
        if not bool(has.any()):  # nothing to learn from; keep the graph for DDP
            return out.depth.sum() * 0.0
        n = int(has.sum())
        log_args = dict(on_step=True, on_epoch=True, batch_size=n, sync_dist=True)  # mean over processes
        self.log("train/loss", loss[has].mean(), prog_bar=True, **log_args)
        for name, value in parts.items():
            self.log(f"train/{name}", value[has].mean(), **log_args)
        return loss[has].mean()

    def validation_step(self, batch: Batch, batch_idx: int) -> None:
        loss, _, out = self._objective(batch)
        self.val_metrics.update(out.depth, batch.target, loss=loss)

    def on_validation_epoch_end(self) -> None:
        values = {f"val/{k}": v.float() for k, v in self.val_metrics.compute().items()}
        self.val_metrics.reset()
        if self.trainer.sanity_checking:
            # Lightning drops what is logged during the sanity check. When it covered the
            # whole validation set it is the validation of the untrained model: log it at
            # step 0 ourselves.
            if sum(self.trainer.num_sanity_val_batches) >= sum(self.trainer.num_val_batches):
                metrics = {k: float(v) for k, v in values.items()}
                metrics.update({f"weights/{k}": v for k, v in self._weights().items()})
                for logger in self.loggers:
                    logger.log_metrics(metrics, step=0)
                log.info("validation before training: %s", _describe(metrics))
            return
        rmse = values.pop("val/rmse")
        self.log("val/rmse", rmse, prog_bar=True, sync_dist=True)  # identical on every process
        self.log_dict(values, sync_dist=True)
        values["val/rmse"] = rmse
        log.info("validation: %s", _describe({k: float(v) for k, v in values.items()}))

    def on_train_epoch_end(self) -> None:
        self.log_dict({f"weights/{k}": v for k, v in self._weights().items()}, sync_dist=True)

    def _weights(self) -> dict[str, float]:
        with torch.no_grad():
            return self.model.weights()

    def configure_optimizers(self) -> torch.optim.Optimizer:
        scalars = [p for n, p in self.model.named_parameters() if p.requires_grad and not n.startswith("head.")]
        head = [p for n, p in self.model.named_parameters() if p.requires_grad and n.startswith("head.")]
        groups = [dict(params=scalars, lr=self.lr)] + ([dict(params=head, lr=self.head_lr)] if head else [])
        return torch.optim.Adam(groups)


def _describe(metrics: dict[str, float]) -> str:
    text = format_metrics({k[len("val/"):]: v for k, v in metrics.items() if k[len("val/"):] in METRICS})
    return f"{text} | loss {metrics['val/loss']:.4g}"


__all__ = ["CRFDepthModule", "PARAMETERS", "build_model", "depth_loss", "gaussian_nll"]
