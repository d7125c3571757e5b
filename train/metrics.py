"""Per-image metrics averaged over images, accumulated across batches and DDP processes.

The metrics themselves are pure functions (:func:`crfdepth.metrics.depth_metrics`: KITTI
RMSE/MAE in mm, iRMSE/iMAE in 1/km, REL, delta1, per image; docs/design.md section 7); this
module only holds the thin ``torchmetrics`` wrapper that sums per-image values and image
counts over an epoch, so that the epoch value is the **mean over images** (the devkit's
way), whatever the batch size and however the images were split between processes.
"""

from __future__ import annotations

from collections.abc import Sequence

import torch
from torchmetrics import Metric

from crfdepth.errors import InputError
from crfdepth.metrics import METRICS, depth_metrics


class PerImageMean(Metric):
    """Mean over images of named per-image values, synchronised across processes.

    States: ``sums`` (one float64 per name) and ``images`` (the image count), both summed
    over DDP processes by ``torchmetrics`` before :meth:`compute`.

    Args:
        names: the value names, e.g. ``("loss", "rmse", ...)``; every :meth:`update` must
            give all of them.

    Example::

        metric = PerImageMean(("loss",))
        metric.update(loss=torch.tensor([1.0, 3.0]))  # two images
        metric.update(loss=torch.tensor([5.0]))
        metric.compute()  # {"loss": tensor(3.0, dtype=torch.float64)}
    """

    full_state_update = False
    higher_is_better = None
    is_differentiable = False

    def __init__(self, names: Sequence[str], **kwargs) -> None:
        super().__init__(**kwargs)
        self.names = tuple(names)
        if not self.names or len(set(self.names)) != len(self.names):
            raise InputError(f"names: expected distinct value names, got {names!r}")
        self.add_state("sums", default=torch.zeros(len(self.names), dtype=torch.float64), dist_reduce_fx="sum")
        self.add_state("images", default=torch.zeros((), dtype=torch.float64), dist_reduce_fx="sum")

    def update(self, **values: torch.Tensor) -> None:
        """Add per-image values: each keyword is a (B,) tensor, one entry per image."""
        if set(values) != set(self.names):
            raise InputError(f"update: expected values for {sorted(self.names)}, got {sorted(values)}")
        rows = [torch.as_tensor(values[n]).detach().reshape(-1).to(self.sums.device, torch.float64)
                for n in self.names]
        count = rows[0].numel()
        if any(r.numel() != count for r in rows):
            raise InputError(f"update: expected one value per image for every name, got sizes "
                             f"{ {n: r.numel() for n, r in zip(self.names, rows)} }")
        self.sums += torch.stack([r.sum() for r in rows])
        self.images += count

    def compute(self) -> dict[str, torch.Tensor]:
        """``{name: mean over images}`` (float64 scalars); NaN when no image was seen."""
        means = self.sums / self.images
        return {n: means[i] for i, n in enumerate(self.names)}


class DepthMetrics(PerImageMean):
    """KITTI depth-completion metrics per image, averaged over images (docs/design.md section 7).

    :meth:`update` takes predictions and targets and calls
    :func:`crfdepth.metrics.depth_metrics`; images without any target pixel are skipped
    (they have nothing to evaluate). Extra per-image values (e.g. the loss) can be passed
    as keywords and are averaged over the same images.

    Args:
        extra: names of extra per-image values given to :meth:`update`.
    """

    def __init__(self, extra: Sequence[str] = (), **kwargs) -> None:
        super().__init__(tuple(extra) + METRICS, **kwargs)
        self.extra = tuple(extra)

    def update(self, pred: torch.Tensor, target: torch.Tensor, **extra: torch.Tensor) -> None:  # type: ignore[override]
        """Accumulate a batch.

        Args:
            pred: (B, 1, H, W) predicted depth in metres, > 0 on target pixels.
            target: (B, 1, H, W) ground truth in metres, 0 = none.
            extra: the ``extra`` per-image values, (B,) each.
        """
        has = (target.flatten(1) > 0).any(1)
        if not bool(has.any()):
            return
        values = depth_metrics(pred[has], target[has])
        values = {k: values[k] for k in METRICS}
        values.update({k: torch.as_tensor(v).reshape(-1)[has] for k, v in extra.items()})
        super().update(**values)
