"""Rotation-max object retrieval: precision@K (the paper's Table 2 protocol).

Two object crops are compared at their best relative yaw: ``sim(q, g) = max_a cos(rotate(q, a), g)``
over ``num_angles`` yaw steps, computed by the rotation search
(:func:`threedq.quantization.rotation_search.all_pairs_rotation_max`, which owns both the ``"exact"`` and
the ``"fast"`` kernel; every table names the one it used). Precision@K counts, per query,
how many of its K most similar gallery objects share its category, then averages per category and
over categories (macro average), so frequent categories do not dominate.
"""

from __future__ import annotations

import torch
from torch import Tensor
from torchmetrics import Metric
from torchmetrics.utilities import dim_zero_cat

from threedq.quantization.rotation_search import SEARCH_METHODS, all_pairs_rotation_max

__all__ = ["retrieval_precision_at_k", "RetrievalPrecisionAtK"]


def retrieval_precision_at_k(
    sim: Tensor, query_labels: Tensor, gallery_labels: Tensor, k: int = 10, exclude_diagonal: bool = False
) -> Tensor:
    """Macro-averaged precision@K.

    Args:
        sim: ``[N, M]`` similarities (higher = more similar).
        query_labels: ``[N]`` category ids.
        gallery_labels: ``[M]`` category ids.
        k: neighbours per query (``k <= M``, or ``M - 1`` with ``exclude_diagonal``).
        exclude_diagonal: the gallery is the query set itself: item ``i`` does not retrieve itself.

    Returns:
        Scalar: the mean over categories of the mean over that category's queries of
        ``hits / k``.
    """
    n, m = sim.shape
    if query_labels.shape != (n,) or gallery_labels.shape != (m,):
        raise ValueError(f"labels must be [N]={n} and [M]={m}, got {tuple(query_labels.shape)}, {tuple(gallery_labels.shape)}")
    available = m - 1 if exclude_diagonal else m
    if not 1 <= k <= available:
        raise ValueError(f"k must be in [1, {available}] for a gallery of {m}, got {k}")
    sim = sim.clone().float()
    if exclude_diagonal:
        if n != m:
            raise ValueError("exclude_diagonal needs a square similarity matrix")
        sim.fill_diagonal_(float("-inf"))
    top = sim.topk(k, dim=1).indices  # [N, k]
    hits = (gallery_labels[top] == query_labels[:, None]).float().mean(dim=1)  # [N]
    classes = query_labels.unique()
    per_class = torch.stack([hits[query_labels == c].mean() for c in classes])
    return per_class.mean()


class RetrievalPrecisionAtK(Metric):
    """Leave-one-out rotation-max retrieval precision@K over all crops seen (DDP: crops are gathered).

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
