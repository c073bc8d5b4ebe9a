"""Unsupervised classification accuracy of a prototype assignment (the paper's LIN-MATCH, Fig. 3a / Table 5).

Every object is assigned to one of ``K`` prototypes (clusters) and has one of ``C`` true categories. The
counts of (prototype, category) pairs form a ``K x C`` confusion matrix. The paper's accuracy matches
prototypes to categories one-to-one (a bipartite matching, Kuhn's Hungarian method) so as to maximise the
number of correctly labelled objects, and divides that number by the number of objects. With more
prototypes than categories (the paper uses ``K = 50``) only ``C`` prototypes are matched and the objects of
every other prototype count as wrong; with fewer prototypes than categories the objects of the ``C - K``
unmatched categories count as wrong.
"""

from __future__ import annotations

from typing import Any

import torch
from scipy.optimize import linear_sum_assignment
from torch import Tensor
from torchmetrics import Metric

__all__ = ["HungarianAccuracy", "cluster_confusion", "hungarian_accuracy", "matching"]


def _check_ids(values: Tensor, name: str, upper: int | None) -> None:
    if not isinstance(values, Tensor) or values.ndim != 1:
        shape = tuple(values.shape) if isinstance(values, Tensor) else type(values).__name__
        raise ValueError(f"{name} must be a 1-D tensor of ids [N], got {shape}")
    if values.is_floating_point() or values.is_complex() or values.dtype == torch.bool:
        raise ValueError(f"{name} must be an integer tensor, got {values.dtype}")
    if values.numel() == 0:
        return
    lo, hi = int(values.min()), int(values.max())
    if lo < 0 or (upper is not None and hi >= upper):
        bound = f"[0, {upper})" if upper is not None else "[0, inf)"
        raise ValueError(f"{name} must lie in {bound}, got values in [{lo}, {hi}]")


def _check_pair(clusters: Tensor, labels: Tensor, num_clusters: int | None, num_classes: int | None) -> None:
    _check_ids(clusters, "clusters", num_clusters)
    _check_ids(labels, "labels", num_classes)
    if clusters.shape != labels.shape:
        raise ValueError(
            f"clusters and labels must have the same length, got {tuple(clusters.shape)} and {tuple(labels.shape)}"
        )


def _check_confusion(confusion: Tensor) -> None:
    if not isinstance(confusion, Tensor) or confusion.ndim != 2:
        shape = tuple(confusion.shape) if isinstance(confusion, Tensor) else type(confusion).__name__
        raise ValueError(f"confusion must be a [K, C] matrix, got {shape}")
    if confusion.numel() and bool((confusion < 0).any()):
        raise ValueError("confusion must hold non-negative counts")


def cluster_confusion(clusters: Tensor, labels: Tensor, num_clusters: int, num_classes: int) -> Tensor:
    """Count (assigned prototype, true category) pairs.

    Args:
        clusters: ``[N]`` integer prototype ids in ``[0, num_clusters)``.
        labels: ``[N]`` integer category ids in ``[0, num_classes)``.
        num_clusters: ``K``, the number of prototypes.
        num_classes: ``C``, the number of categories.

    Returns:
        ``[K, C]`` int64 counts; entry ``[k, c]`` is how many objects of category ``c`` were assigned to
        prototype ``k``.

    Raises:
        ValueError: if the inputs are not 1-D integer tensors of one length with ids in range.

    Convention: rows are prototypes (clusters), columns are true categories.
    """
    _check_pair(clusters, labels, num_clusters, num_classes)
    flat = clusters.long() * num_classes + labels.long()
    return torch.bincount(flat, minlength=num_clusters * num_classes).view(num_clusters, num_classes)


def matching(confusion: Tensor) -> tuple[Tensor, Tensor]:
    """One-to-one prototype-to-category assignment maximising the number of matched objects.

    Solves the rectangular linear assignment problem (``scipy.optimize.linear_sum_assignment`` with
    ``maximize=True``) on the ``K x C`` counts, so exactly ``min(K, C)`` pairs are returned.

    Args:
        confusion: ``[K, C]`` non-negative counts (rows prototypes, columns categories).

    Returns:
        ``(cluster_ids, class_ids)``, two ``[min(K, C)]`` int64 tensors: prototype ``cluster_ids[i]`` is
        named category ``class_ids[i]``. Sorted by prototype id. Prototypes (``K > C``) or categories
        (``K < C``) left out are unmatched.

    Raises:
        ValueError: if ``confusion`` is not a 2-D matrix of non-negative counts.

    Convention: rows are prototypes, columns are categories; ties between equally good assignments are
    broken by scipy's solver (deterministic).
    """
    _check_confusion(confusion)
    rows, cols = linear_sum_assignment(confusion.detach().cpu().double().numpy(), maximize=True)
    return torch.as_tensor(rows, dtype=torch.long), torch.as_tensor(cols, dtype=torch.long)


def hungarian_accuracy(confusion: Tensor) -> Tensor:
    """The paper's unsupervised classification accuracy (LIN-MATCH): Hungarian-matched count / N.

    Args:
        confusion: ``[K, C]`` non-negative counts (rows prototypes, columns categories), ``K != C``
            allowed.

    Returns:
        Scalar float32 tensor in ``[0, 1]``: the number of objects whose prototype is matched to their own
        category under :func:`matching`, divided by the total count ``N``; ``nan`` when ``N == 0``.

    Raises:
        ValueError: if ``confusion`` is not a 2-D matrix of non-negative counts.

    Convention: one-to-one matching; with ``K > C`` the objects of the ``K - C`` unmatched prototypes count
    as wrong, with ``K < C`` the objects of the ``C - K`` unmatched categories count as wrong.
    """
    _check_confusion(confusion)
    total = float(confusion.sum())
    if total == 0:
        return torch.tensor(float("nan"), device=confusion.device)
    rows, cols = matching(confusion)
    matched = float(confusion.detach().cpu().double()[rows, cols].sum())
    return torch.tensor(matched / total, dtype=torch.float32, device=confusion.device)


class HungarianAccuracy(Metric):
    """Hungarian-matched unsupervised classification accuracy over all objects seen (the paper's LIN-MATCH).

    The state is the ``[K, C]`` confusion matrix of (assigned prototype, true category) counts, summed over
    batches and, under DDP, over processes (``dist_reduce_fx="sum"``: cheap to sync).

    Args:
        num_clusters: ``K``, the number of prototypes.
        num_classes: ``C``, the number of true categories.
        **kwargs: passed to :class:`torchmetrics.Metric`.

    Convention: ``update(clusters [N] long, labels [N] long)`` with prototype ids in ``[0, K)`` and category
    ids in ``[0, C)``; ``compute()`` returns :func:`hungarian_accuracy` of the summed confusion matrix
    (``nan`` before any object). Each object must be fed exactly once over all processes: a
    ``DistributedSampler`` that pads with repeated samples counts those twice.
    """

    is_differentiable = False
    higher_is_better = True
    full_state_update = False
    plot_lower_bound = 0.0
    plot_upper_bound = 1.0

    confusion: Tensor

    def __init__(self, num_clusters: int, num_classes: int, **kwargs: Any) -> None:
        super().__init__(**kwargs)
        for name, value in (("num_clusters", num_clusters), ("num_classes", num_classes)):
            if not isinstance(value, int) or isinstance(value, bool) or value < 1:
                raise ValueError(f"{name} must be a positive int, got {value!r}")
        self.num_clusters = num_clusters
        self.num_classes = num_classes
        self.add_state(
            "confusion", default=torch.zeros(num_clusters, num_classes, dtype=torch.long), dist_reduce_fx="sum"
        )

    def update(self, clusters: Tensor, labels: Tensor) -> None:
        """Add a batch of objects.

        Args:
            clusters: ``[N]`` integer prototype ids in ``[0, num_clusters)``.
            labels: ``[N]`` integer category ids in ``[0, num_classes)``.
        """
        self.confusion += cluster_confusion(
            clusters.detach().to(self.confusion.device), labels.detach().to(self.confusion.device),
            self.num_clusters, self.num_classes,
        )

    def compute(self) -> Tensor:
        """Hungarian-matched accuracy of all objects seen (scalar tensor)."""
        return hungarian_accuracy(self.confusion)
