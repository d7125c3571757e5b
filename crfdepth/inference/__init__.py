"""Inference of the CRF, stage by stage (docs/design.md sections 3 and 6): the superpixel-graph
pipeline and the pixel-grid one. :class:`crfdepth.model.CRFDepth` holds the weights and settings
and calls these functions; they hold no state of their own."""

from crfdepth.inference.pixel import pixel_forward
from crfdepth.inference.superpixel import superpixel_forward

PIPELINES = {"pixel": pixel_forward, "superpixel": superpixel_forward}
"""The forward of each ``mode`` on checked inputs: ``PIPELINES[mode](model, image, sparse, K, return_std)``
with ``image`` (B, 3, H, W), ``sparse`` (B, 1, H, W) and ``K`` (B, 3, 3) in one dtype on one device; the pixel
grid's also takes ``lines=``, whether every frame's returns lie on scan lines where the caller has read it
(:func:`crfdepth.inference.regime.assign`)."""

__all__ = ["PIPELINES", "pixel_forward", "superpixel_forward"]
