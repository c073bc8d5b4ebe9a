"""Momentum contrast (MoCo, He et al. 2020) for correspondence mining (paper Sec. 3.3): streamed InfoNCE, the
key encoder / negative queue module, and the 3D correspondence miner (retrieval, patch matching, verification)."""

from threedq.contrastive.infonce import info_nce_plain, info_nce_streamed
from threedq.contrastive.miner import (
    calibrate_context_cosine,
    context_offsets,
    match_patch,
    mine_correspondences,
    patch_grid,
    retrieve_targets,
    rotate_patch_positions,
    salient_positions,
    verify_match,
)
from threedq.contrastive.moco import MomentumContrast

__all__ = [
    "MomentumContrast",
    "calibrate_context_cosine",
    "context_offsets",
    "info_nce_plain",
    "info_nce_streamed",
    "match_patch",
    "mine_correspondences",
    "patch_grid",
    "retrieve_targets",
    "rotate_patch_positions",
    "salient_positions",
    "verify_match",
]
