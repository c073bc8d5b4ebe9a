"""Unsupervised classification accuracy of a prototype assignment (the paper's LIN-MATCH, Fig. 3a / Table 5).

The ``K x C`` confusion matrix counts (prototype, true category) pairs; prototypes are matched to categories one-to-one
(Hungarian method) to maximise the correctly labelled objects, whose share is the accuracy. Objects of unmatched
prototypes (``K > C``) or categories (``K < C``) count as wrong.
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
        got = f"got {tuple(clusters.shape)} and {tuple(labels.shape)}"
        raise ValueError(f"clusters and labels must have the same length, {got}")


def _check_positive(**values: Any) -> None:
    for name, value in values.items():
        if not isinstance(value, int) or isinstance(value, bool) or value < 1:
            raise ValueError(f"{name} must be a positive int, got {value!r}")


def _check_confusion(confusion: Tensor) -> None:
    if not isinstance(confusion, Tensor) or confusion.ndim != 2:
        shape = tuple(confusion.shape) if isinstance(confusion, Tensor) else type(confusion).__name__
        raise ValueError(f"confusion must be a [K, C] matrix, got {shape}")
    if confusion.numel() and bool((confusion < 0).any()):
        raise ValueError("confusion must hold non-negative counts")


class _UnitMetric(Metric):
    """A metric in ``[0, 1]``, higher is better, not differentiable, whose ``update`` needs no full state."""

    is_differentiable = False
    higher_is_better = True
    full_state_update = False
    plot_lower_bound = 0.0
    plot_upper_bound = 1.0


def cluster_confusion(clusters: Tensor, labels: Tensor, num_clusters: int, num_classes: int) -> Tensor:
    """``[K, C]`` int64 counts of (assigned prototype, true category) pairs of ``clusters`` ``[N]`` in ``[0, K)`` and
    ``labels`` ``[N]`` in ``[0, C)`` (``K = num_clusters``, ``C = num_classes``).

    Raises:
        ValueError: if the inputs are not 1-D integer tensors of one length with ids in range.
    """
    _check_pair(clusters, labels, num_clusters, num_classes)
    flat = clusters.long() * num_classes + labels.long()
    return torch.bincount(flat, minlength=num_clusters * num_classes).view(num_clusters, num_classes)


def matching(confusion: Tensor) -> tuple[Tensor, Tensor]:
    """One-to-one prototype-to-category assignment of ``confusion`` ``[K, C]`` maximising the matched objects
    (``scipy.optimize.linear_sum_assignment``, ``maximize=True``): ``(cluster_ids, class_ids)``, two ``[min(K, C)]``
    int64 tensors sorted by prototype; prototype ``cluster_ids[i]`` is named category ``class_ids[i]``.

    Raises:
        ValueError: if ``confusion`` is not a 2-D matrix of non-negative counts.
    """
    _check_confusion(confusion)
    rows, cols = linear_sum_assignment(confusion.detach().cpu().double().numpy(), maximize=True)
    return torch.as_tensor(rows, dtype=torch.long), torch.as_tensor(cols, dtype=torch.long)


def hungarian_accuracy(confusion: Tensor) -> Tensor:
    """The paper's unsupervised classification accuracy (LIN-MATCH, scalar float32; ``nan`` without objects): the
    share of objects matched to their own category by :func:`matching` of ``confusion`` ``[K, C]`` (``K != C``
    allowed). ``ValueError`` if ``confusion`` is not a 2-D matrix of non-negative counts."""
    _check_confusion(confusion)
    total = float(confusion.sum())
    if total == 0:
        return torch.tensor(float("nan"), device=confusion.device)
    rows, cols = matching(confusion)
    matched = float(confusion.detach().cpu().double()[rows, cols].sum())
    return torch.tensor(matched / total, dtype=torch.float32, device=confusion.device)


class HungarianAccuracy(_UnitMetric):
    """Hungarian-matched unsupervised classification accuracy over all objects seen (the paper's LIN-MATCH): the state
    is the ``[num_clusters, num_classes]`` confusion matrix (:func:`cluster_confusion`), summed over batches and
    processes.

    Convention: ``update(clusters [N] long, labels [N] long)``; ``compute()`` returns :func:`hungarian_accuracy`
    (``nan`` before any object). Each object must be fed exactly once.
    """

    confusion: Tensor

    def __init__(self, num_clusters: int, num_classes: int, **kwargs: Any) -> None:
        super().__init__(**kwargs)
        _check_positive(num_clusters=num_clusters, num_classes=num_classes)
        self.num_clusters, self.num_classes = num_clusters, num_classes
        confusion = torch.zeros(num_clusters, num_classes, dtype=torch.long)
        self.add_state("confusion", default=confusion, dist_reduce_fx="sum")

    def update(self, clusters: Tensor, labels: Tensor) -> None:
        """Add a batch of objects: ``clusters`` ``[N]`` in ``[0, num_clusters)``, ``labels`` ``[N]`` in
        ``[0, num_classes)``."""
        dev = self.confusion.device
        self.confusion += cluster_confusion(clusters.detach().to(dev), labels.detach().to(dev), *self.confusion.shape)

    def compute(self) -> Tensor:
        """Hungarian-matched accuracy of all objects seen (scalar tensor)."""
        return hungarian_accuracy(self.confusion)
