"""A six-number hand-made object descriptor: what colour and box size alone tell (a reference row of Table 2).

``[mean R, mean G, mean B, longer horizontal extent, shorter horizontal extent, height]``: the occupancy-weighted mean
colour of the object's raw input crop and its box's extents (horizontal ones sorted: invariant to yaw). Retrieval
compares standardised descriptors by Euclidean distance.
"""

from __future__ import annotations

import torch
from torch import Tensor

__all__ = ["colour_size_descriptor", "descriptor_similarity"]


def colour_size_descriptor(raw: Tensor, aabb: Tensor, eps: float = 1e-6) -> Tensor:
    """The descriptor ``[N, 6]`` float64 of each object from its raw input crop ``raw`` ``[N, 4, s, s, s]``
    (``cat[occ, occ * rgb]``, occupancy in ``[0, 1]``) and its box ``aabb`` ``[N, 6]`` (metres, frame R, z up); an empty
    crop gets colour 0."""
    if raw.ndim != 5 or raw.shape[1] != 4:
        raise ValueError(f"raw: expected [N, 4, s, s, s] crops cat[occ, occ * rgb], got {tuple(raw.shape)}")
    if aabb.shape != (raw.shape[0], 6):
        raise ValueError(f"aabb: expected [{raw.shape[0]}, 6], got {tuple(aabb.shape)}")
    r = raw.detach().double().flatten(2)
    occ = r[:, 0].sum(1, keepdim=True)
    colour = r[:, 1:].sum(2) / occ.clamp_min(eps)
    ext = (aabb[:, 3:] - aabb[:, :3]).detach().double()
    horizontal = ext[:, :2].sort(dim=1, descending=True).values
    return torch.cat([colour, horizontal, ext[:, 2:]], dim=1)


def descriptor_similarity(query: Tensor, gallery: Tensor) -> Tensor:
    """``[N, M]`` minus the Euclidean distance between descriptors ``[N, D]``, ``[M, D]``, each dimension divided by
    its standard deviation over both (a constant dimension by 1)."""
    if query.ndim != 2 or gallery.ndim != 2 or query.shape[1] != gallery.shape[1]:
        raise ValueError(f"query [N, D] and gallery [M, D] expected, got {tuple(query.shape)}, {tuple(gallery.shape)}")
    std = torch.cat([query, gallery]).double().std(0, unbiased=False)
    std = torch.where(std > 0, std, torch.ones_like(std))
    return -torch.cdist(query.double() / std, gallery.double() / std)
