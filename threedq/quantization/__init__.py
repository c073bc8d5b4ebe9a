"""Rotation-aware quantization (paper Sec. 3.2): the yaw search (exact and fast kernels), its in-plane form for 2D
crops (2.5DQ-Nets) and the prototype bank."""

from threedq.quantization.inplane import all_pairs_inplane_max, best_prototype_and_angle, rotate_inplane
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
)

__all__ = [
    "PrototypeBank",
    "RotationSearchResult",
    "all_pairs_inplane_max",
    "all_pairs_rotation_max",
    "best_prototype_and_angle",
    "best_prototype_and_yaw",
    "fill_free_slots",
    "fit_prototype_bank",
    "prototype_crops",
    "quantization_loss",
    "rotate_inplane",
    "rotation_max_similarity",
    "run_prototype_em",
]
