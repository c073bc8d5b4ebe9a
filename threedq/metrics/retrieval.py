"""Rotation-max object retrieval: precision@K under two protocols, its perfect-feature ceiling, same-object top-1.

Crops are compared at their best relative yaw (:func:`threedq.quantization.rotation_search.all_pairs_rotation_max`);
precision@K is macro-averaged over categories. Protocols (:data:`PROTOCOLS`): ``strict``, leave-one-out over one view
per scene; ``paper`` (Table 2), gallery row ``i`` is query ``i``'s object seen from a second view (its *twin*, a hit).
"""

from __future__ import annotations

from typing import Any

import torch
from torch import Tensor
from torchmetrics import Metric
from torchmetrics.utilities import dim_zero_cat

from threedq.quantization.rotation_search import SEARCH_METHODS, all_pairs_rotation_max

__all__ = [
    "PROTOCOLS", "PROTOCOL_LABELS", "RetrievalPrecisionAtK", "per_class_precision_at_k", "precision_ceiling",
    "retrieval_confusion", "retrieval_precision_at_k", "same_object_top1",
]  # fmt: skip

PROTOCOLS: tuple[str, ...] = ("strict", "paper")
#: How a table names each protocol.
PROTOCOL_LABELS = {"strict": "strict protocol (leave-one-out over one view per scene; a query never retrieves itself)",
                   "paper": "paper protocol (queries from one view, gallery = the same objects from a second view of "
                            "their scene; the query's own object, its twin, counts as a hit)"}  # fmt: skip


def _check(sim: Tensor, query_labels: Tensor, gallery_labels: Tensor, k: int, exclude_diagonal: bool) -> None:
    n, m = sim.shape
    if query_labels.shape != (n,) or gallery_labels.shape != (m,):
        got = f"got {tuple(query_labels.shape)}, {tuple(gallery_labels.shape)}"
        raise ValueError(f"labels must be [N]={n} and [M]={m}, {got}")
    if exclude_diagonal and n != m:
        raise ValueError("exclude_diagonal needs a square similarity matrix")
    _check_k(k, m, exclude_diagonal)


def _check_k(k: int, m: int, exclude_diagonal: bool) -> None:
    available = m - 1 if exclude_diagonal else m
    if not 1 <= k <= available:
        raise ValueError(f"k must be in [1, {available}] for a gallery of {m}, got {k}")


def _top_k(sim: Tensor, k: int, exclude_diagonal: bool) -> Tensor:
    """``[N, k]`` gallery indices of each query's k most similar items (the diagonal left out if asked)."""
    sim = sim.clone().float()
    if exclude_diagonal:
        sim.fill_diagonal_(float("-inf"))
    return sim.topk(k, dim=1).indices


def per_class_precision_at_k(sim: Tensor, query_labels: Tensor, gallery_labels: Tensor, k: int = 10,
                             exclude_diagonal: bool = False) -> tuple[Tensor, Tensor]:  # fmt: skip
    """Precision@K of each query category: ``classes`` ``[C]`` (sorted query categories) and ``precision`` ``[C]``, the
    mean of ``hits / k`` over the category's queries, of similarities ``sim`` ``[N, M]`` (higher = more similar) and
    category ids ``query_labels`` ``[N]``, ``gallery_labels`` ``[M]``; ``exclude_diagonal``: item ``i`` does not
    retrieve itself (strict; ``k <= M - 1``)."""
    _check(sim, query_labels, gallery_labels, k, exclude_diagonal)
    top = _top_k(sim, k, exclude_diagonal)
    hits = (gallery_labels[top] == query_labels[:, None]).float().mean(dim=1)  # [N]
    classes = query_labels.unique()
    return classes, torch.stack([hits[query_labels == c].mean() for c in classes])


def retrieval_precision_at_k(sim: Tensor, query_labels: Tensor, gallery_labels: Tensor, k: int = 10,
                             exclude_diagonal: bool = False) -> Tensor:  # fmt: skip
    """Macro-averaged precision@K: the mean over categories of :func:`per_class_precision_at_k`."""
    return per_class_precision_at_k(sim, query_labels, gallery_labels, k, exclude_diagonal)[1].mean()


def precision_ceiling(query_labels: Tensor, gallery_labels: Tensor, k: int = 10,
                      exclude_diagonal: bool = False) -> Tensor:  # fmt: skip
    """Macro precision@K (scalar) of perfect features on labels ``[N]``, ``[M]``: a query of a category with ``n``
    gallery items (``n - 1`` with ``exclude_diagonal``) scores ``min(k, n) / k``."""
    n, m = query_labels.shape[0], gallery_labels.shape[0]
    if exclude_diagonal and n != m:
        raise ValueError("exclude_diagonal needs queries and gallery of one length")
    _check_k(k, m, exclude_diagonal)
    classes = query_labels.unique()
    same = torch.stack([(gallery_labels == c).sum() for c in classes]).double() - (1 if exclude_diagonal else 0)
    return (same.clamp(0, k) / k).mean()


def same_object_top1(sim: Tensor) -> Tensor:
    """Share (scalar) of queries whose most similar gallery item is their twin, of ``sim`` ``[N, N]`` (gallery row
    ``i`` = query ``i``'s twin); ties go to the lowest gallery index."""
    if sim.ndim != 2 or sim.shape[0] != sim.shape[1]:
        raise ValueError(f"sim must be square [N, N] (gallery row i = query i's twin), got {tuple(sim.shape)}")
    return (sim.float().argmax(dim=1) == torch.arange(sim.shape[0], device=sim.device)).double().mean()


def retrieval_confusion(sim: Tensor, query_labels: Tensor, gallery_labels: Tensor, num_classes: int, k: int = 10,
                        exclude_diagonal: bool = False) -> Tensor:  # fmt: skip
    """``[num_classes, num_classes]`` counts: entry ``(a, b)`` is how many of the top-k slots of category ``a``'s
    queries hold an item of category ``b`` (row sums = queries of ``a`` times k)."""
    _check(sim, query_labels, gallery_labels, k, exclude_diagonal)
    top = _top_k(sim, k, exclude_diagonal)
    q = query_labels[:, None].expand_as(top).flatten()
    g = gallery_labels[top].flatten()
    conf = torch.zeros(num_classes * num_classes, dtype=torch.long, device=sim.device)
    conf.index_add_(0, q * num_classes + g, torch.ones_like(q))
    return conf.view(num_classes, num_classes)


class RetrievalPrecisionAtK(Metric):
    """Leave-one-out (strict protocol) rotation-max retrieval precision@K over all crops seen (gathered under DDP).

    ``update(crops [N, C, S, S, S], labels [N])``; ``compute()`` compares every crop with every other with
    ``all_pairs_rotation_max(..., method=method)``.
    """

    is_differentiable = False
    higher_is_better = True
    full_state_update = False

    def __init__(self, k: int = 10, num_angles: int = 36, method: str = "fast", **kwargs: Any) -> None:
        super().__init__(**kwargs)
        if method not in SEARCH_METHODS:
            raise ValueError(f"method must be one of {SEARCH_METHODS}, got {method!r}")
        self.k, self.num_angles, self.method = k, num_angles, method
        self.add_state("crops", default=[], dist_reduce_fx="cat")
        self.add_state("labels", default=[], dist_reduce_fx="cat")

    def update(self, crops: Tensor, labels: Tensor) -> None:
        if crops.shape[0] != labels.shape[0]:
            raise ValueError(f"crops and labels disagree in length: {crops.shape[0]} vs {labels.shape[0]}")
        self.crops.append(crops.detach().float())
        self.labels.append(labels.detach().long())

    def compute(self) -> Tensor:
        crops, labels = dim_zero_cat(self.crops), dim_zero_cat(self.labels)
        sim, _ = all_pairs_rotation_max(crops, crops, self.num_angles, method=self.method)
        return retrieval_precision_at_k(sim, labels, labels, min(self.k, crops.shape[0] - 1), exclude_diagonal=True)
