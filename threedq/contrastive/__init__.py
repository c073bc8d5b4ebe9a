"""Momentum contrast (MoCo, He et al. 2020) for correspondence mining (paper Sec. 3.3): streamed InfoNCE and the
key encoder / negative queue module."""

from threedq.contrastive.infonce import info_nce_plain, info_nce_streamed
from threedq.contrastive.moco import MomentumContrast

__all__ = ["MomentumContrast", "info_nce_plain", "info_nce_streamed"]
