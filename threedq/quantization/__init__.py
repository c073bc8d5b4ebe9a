"""Rotation-aware quantization (paper Sec. 3.2): the yaw search (exact and fast kernels) and the prototype bank.

2D crops (2.5DQ-Nets) go through the same search as one-slice volumes ``[N, C, 1, H, W]``, whose yaw is an in-plane
rotation."""

from threedq.quantization.prototypes import (
    PrototypeBank,
    fill_free_slots,
    fit_prototype_bank,
    prototype_crops,
    quantization_loss,
    run_prototype_em,
)
from threedq.quantization.rotation_search import (
    RotationSearchResult,
    all_pairs_rotation_max,
    best_prototype_and_yaw,
    rotation_max_similarity,
    yaw_confidence,
    yaw_margin,
)

__all__ = ["PrototypeBank", "RotationSearchResult", "all_pairs_rotation_max", "best_prototype_and_yaw",
           "fill_free_slots", "fit_prototype_bank", "prototype_crops", "quantization_loss", "rotation_max_similarity",
           "run_prototype_em", "yaw_confidence", "yaw_margin"]
