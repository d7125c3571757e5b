"""Inference of the CRF, stage by stage (docs/design.md sections 3 and 6): the superpixel-graph
pipeline and the pixel-grid one. :class:`crfdepth.model.CRFDepth` holds the weights and settings
and calls these functions; they hold no state of their own."""
