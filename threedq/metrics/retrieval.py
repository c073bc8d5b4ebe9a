"""Rotation-max object retrieval: precision@K under two protocols, its perfect-feature ceiling, same-object top-1.

Two object crops are compared at their best relative yaw: ``sim(q, g) = max_a cos(rotate(q, a), g)``
over ``num_angles`` yaw steps, computed by the rotation search
(:func:`threedq.quantization.rotation_search.all_pairs_rotation_max`, which owns both the ``"exact"`` and
the ``"fast"`` kernel; every table names the one it used). Precision@K counts, per query,
how many of its K most similar gallery objects share its category, then averages per category and
over categories (macro average), so frequent categories do not dominate.

Protocols (:data:`PROTOCOLS`; every table names the one it used, its pool and its ceiling):

* ``strict`` — leave-one-out: the queries are the gallery (one view per scene) and a query never retrieves
  itself. A category of ``n`` objects can fill at most ``n - 1`` of the K slots.
* ``paper`` — the paper's Table 2 protocol (its supplement's retrieval figure, where a retrieved crop of "the same
  object instance as the query, but in a different viewpoint" is drawn as a hit): queries are the objects seen
  from one view of their scene, the gallery is the same objects seen from a second view, row ``i`` of the gallery
  being query ``i``'s own object (its *twin*), which counts as a hit. A category of ``n`` objects fills at most
  ``n`` slots. :func:`same_object_top1` measures view invariance directly: how often the twin is the nearest.

:func:`precision_ceiling` is precision@K of perfect features (every same-category item ranked first) for given
labels: what a protocol on a pool allows.
"""

from __future__ import annotations

import torch
from torch import Tensor
from torchmetrics import Metric
from torchmetrics.utilities import dim_zero_cat

from threedq.quantization.rotation_search import SEARCH_METHODS, all_pairs_rotation_max

__all__ = [
    "PROTOCOLS",
    "PROTOCOL_LABELS",
    "RetrievalPrecisionAtK",
    "precision_ceiling",
    "retrieval_confusion",
    "retrieval_precision_at_k",
    "per_class_precision_at_k",
    "same_object_top1",
]

#: The retrieval protocols (see the module docstring).
PROTOCOLS: tuple[str, ...] = ("strict", "paper")
#: How a table names each protocol.
PROTOCOL_LABELS = {
    "strict": "strict protocol (leave-one-out over one view per scene; a query never retrieves itself)",
    "paper": "paper protocol (queries from one view, gallery = the same objects from a second view of their scene; "
             "the query's own object, its twin, counts as a hit)",
}


def _check(sim: Tensor, query_labels: Tensor, gallery_labels: Tensor, k: int, exclude_diagonal: bool) -> None:
    n, m = sim.shape
    if query_labels.shape != (n,) or gallery_labels.shape != (m,):
        raise ValueError(f"labels must be [N]={n} and [M]={m}, got {tuple(query_labels.shape)}, {tuple(gallery_labels.shape)}")
    if exclude_diagonal and n != m:
        raise ValueError("exclude_diagonal needs a square similarity matrix")
    available = m - 1 if exclude_diagonal else m
    if not 1 <= k <= available:
        raise ValueError(f"k must be in [1, {available}] for a gallery of {m}, got {k}")


def _top_k(sim: Tensor, k: int, exclude_diagonal: bool) -> Tensor:
    """``[N, k]`` gallery indices of each query's k most similar items (the diagonal left out if asked)."""
    sim = sim.clone().float()
    if exclude_diagonal:
        sim.fill_diagonal_(float("-inf"))
    return sim.topk(k, dim=1).indices


def per_class_precision_at_k(
    sim: Tensor, query_labels: Tensor, gallery_labels: Tensor, k: int = 10, exclude_diagonal: bool = False
) -> tuple[Tensor, Tensor]:
    """Precision@K of each query category.

    Args:
        sim: ``[N, M]`` similarities (higher = more similar).
        query_labels: ``[N]`` category ids.
        gallery_labels: ``[M]`` category ids.
        k: neighbours per query (``k <= M``, or ``M - 1`` with ``exclude_diagonal``).
        exclude_diagonal: the gallery is the query set itself: item ``i`` does not retrieve itself (strict).

    Returns:
        ``classes`` ``[C]`` (sorted query categories) and ``precision`` ``[C]``: the mean over that category's
        queries of ``hits / k``.
    """
    _check(sim, query_labels, gallery_labels, k, exclude_diagonal)
    top = _top_k(sim, k, exclude_diagonal)
    hits = (gallery_labels[top] == query_labels[:, None]).float().mean(dim=1)  # [N]
    classes = query_labels.unique()
    return classes, torch.stack([hits[query_labels == c].mean() for c in classes])


def retrieval_precision_at_k(
    sim: Tensor, query_labels: Tensor, gallery_labels: Tensor, k: int = 10, exclude_diagonal: bool = False
) -> Tensor:
    """Macro-averaged precision@K: the mean over categories of :func:`per_class_precision_at_k`.

    ``exclude_diagonal=True`` with the query set as gallery is the strict protocol; ``False`` with a gallery
    whose row ``i`` is query ``i``'s twin is the paper's.
    """
    return per_class_precision_at_k(sim, query_labels, gallery_labels, k, exclude_diagonal)[1].mean()


def precision_ceiling(query_labels: Tensor, gallery_labels: Tensor, k: int = 10, exclude_diagonal: bool = False) -> Tensor:
    """Macro precision@K of perfect features on these labels: a query of a category with ``n`` gallery items
    (``n - 1`` with ``exclude_diagonal``, itself left out) scores ``min(k, n) / k``.

    Args:
        query_labels: ``[N]``; gallery_labels: ``[M]``; k, exclude_diagonal: as :func:`retrieval_precision_at_k`.

    Returns:
        Scalar in ``[0, 1]``.
    """
    n, m = query_labels.shape[0], gallery_labels.shape[0]
    available = m - 1 if exclude_diagonal else m
    if exclude_diagonal and n != m:
        raise ValueError("exclude_diagonal needs queries and gallery of one length")
    if not 1 <= k <= available:
        raise ValueError(f"k must be in [1, {available}] for a gallery of {m}, got {k}")
    classes = query_labels.unique()
    same = torch.stack([(gallery_labels == c).sum() for c in classes]).double() - (1 if exclude_diagonal else 0)
    return (same.clamp(0, k) / k).mean()


def same_object_top1(sim: Tensor) -> Tensor:
    """Share of queries whose most similar gallery item is their own object seen from the other view.

    Args:
        sim: ``[N, N]`` query x gallery similarities, gallery row ``i`` = query ``i``'s twin (the paper protocol).

    Returns:
        Scalar in ``[0, 1]``. Ties go to the lowest gallery index (``argmax``).
    """
    if sim.ndim != 2 or sim.shape[0] != sim.shape[1]:
        raise ValueError(f"sim must be square [N, N] (gallery row i = query i's twin), got {tuple(sim.shape)}")
    return (sim.float().argmax(dim=1) == torch.arange(sim.shape[0], device=sim.device)).double().mean()


def retrieval_confusion(
    sim: Tensor, query_labels: Tensor, gallery_labels: Tensor, num_classes: int, k: int = 10,
    exclude_diagonal: bool = False,
) -> Tensor:
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
    """Leave-one-out (strict protocol) rotation-max retrieval precision@K over all crops seen (DDP: crops are
    gathered).

    ``update(crops [N, C, S, S, S], labels [N])``; ``compute()`` compares every crop with every other, with
    ``all_pairs_rotation_max(..., method=method)`` (default ``"fast"``: cylindrical resampling + rFFT over the
    angle; ``"exact"`` rotates every crop by every yaw).
    """

    is_differentiable = False
    higher_is_better = True
    full_state_update = False

    def __init__(self, k: int = 10, num_angles: int = 36, method: str = "fast", **kwargs) -> None:  # noqa: ANN003
        super().__init__(**kwargs)
        if method not in SEARCH_METHODS:
            raise ValueError(f"method must be one of {SEARCH_METHODS}, got {method!r}")
        self.k = k
        self.num_angles = num_angles
        self.method = method
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
