"""The Lightning trainer of crfdepth: learn the CRF's potential weights from data.

``python -m train fit --config configs/synthetic.yaml`` (see ``train/__main__.py`` and
``configs/``). The library, :mod:`crfdepth`, does not depend on this package or on
Lightning.
"""

from train.data import CRFDataModule
from train.metrics import DepthMetrics, PerImageMean
from train.module import CRFDepthModule

__all__ = ["CRFDataModule", "CRFDepthModule", "DepthMetrics", "PerImageMean"]
