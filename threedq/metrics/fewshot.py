"""Few-shot object category labelling accuracy through prototypes (the paper's Table 1 protocol), and the 2D
baselines' few-shot classifiers: ``shots`` objects per category get their true label, each prototype takes the
majority label of its labelled members, every object its prototype's; accuracy is over the objects not labelled.
"""

from __future__ import annotations

from typing import Any

import torch
from torch import Tensor
from torchmetrics.utilities import dim_zero_cat

from threedq.metrics.clustering import _check_ids, _check_pair, _check_positive, _UnitMetric

__all__ = [
    "FewShotAccuracy", "few_shot_accuracy", "linear_probe", "linear_probe_accuracy", "nearest_shot_accuracy",
    "select_labelled",
]  # fmt: skip


def select_labelled(labels: Tensor, shots: int, seed: int = 0, clusters: Tensor | None = None) -> Tensor:
    """``[M]`` int64 indices (ascending) of ``shots`` labelled examples per category of ``labels`` ``[N]``.

    Objects are ordered by ``(label, cluster)`` (``clusters`` ``[N]``, optional; stable), then, per category in
    increasing id, a ``torch.randperm`` from one generator seeded with ``seed`` picks ``min(shots, n_c)`` of its
    ``n_c`` objects, so the choice does not depend on the order the objects came in.

    Raises:
        ValueError: if ``shots < 1``.
    """
    _check_positive(shots=shots)
    labels = labels.long().cpu()
    if labels.numel() == 0:
        return torch.zeros(0, dtype=torch.long)
    key = labels
    if clusters is not None:
        clusters = clusters.long().cpu()
        key = labels * (int(clusters.max()) + 1) + clusters
    order = torch.sort(key, stable=True).indices
    _, counts = torch.unique_consecutive(labels[order], return_counts=True)
    gen = torch.Generator().manual_seed(seed)
    starts = (torch.cumsum(counts, 0) - counts).tolist()
    picked = [order[s + torch.randperm(n, generator=gen)[: min(shots, n)]] for s, n in zip(starts, counts.tolist())]
    return torch.sort(torch.cat(picked)).values


def few_shot_accuracy(clusters: Tensor, labels: Tensor, shots: int = 2, seed: int = 0, num_clusters: int | None = None,
                      labelled_indices: Tensor | None = None) -> dict[str, Tensor]:  # fmt: skip
    """Few-shot labelling accuracy: label ``shots`` objects per category, propagate through prototypes.

    Args:
        clusters: ``[N]`` integer prototype ids in ``[0, num_clusters)`` (default ``K = max(clusters) + 1``).
        labels: ``[N]`` integer true category ids (``>= 0``).
        shots, seed: the labelled examples, :func:`select_labelled`, unless ``labelled_indices`` ``[M]`` gives them.

    Returns:
        ``accuracy``: scalar float32, the share of the not-labelled objects whose prototype's label is their true
        label (``nan`` if every object was labelled); ``labelled_indices``: ``[M]`` int64 (ascending);
        ``cluster_labels``: ``[K]`` int64, each prototype's label, ``-1`` without a labelled member.

    Raises:
        ValueError: on malformed inputs (not 1-D integer tensors of one length, ids out of range, ``shots < 1``).

    Convention: a prototype takes the majority label of its labelled members (ties: the smallest label id).
    """
    _check_pair(clusters, labels, num_clusters, None)
    _check_positive(shots=shots)
    clusters, labels = clusters.detach().long().cpu(), labels.detach().long().cpu()
    k = num_clusters if num_clusters is not None else (int(clusters.max()) + 1 if clusters.numel() else 0)
    if labelled_indices is None:
        labelled = select_labelled(labels, shots, seed, clusters)
    else:
        _check_ids(labelled_indices, "labelled_indices", labels.numel())
        labelled = torch.unique(labelled_indices.detach().long().cpu())
    num_classes = int(labels.max()) + 1 if labels.numel() else 0
    # votes[k, c]: labelled members of prototype k with label c; argmax returns the first maximum (smallest c).
    votes = torch.bincount(clusters[labelled] * num_classes + labels[labelled], minlength=k * num_classes)
    votes = votes.view(k, num_classes)
    cluster_labels = torch.full((k,), -1, dtype=torch.long)
    if num_classes:
        has_label = votes.sum(dim=1) > 0
        cluster_labels[has_label] = votes[has_label].argmax(dim=1)
    accuracy = _accuracy(cluster_labels[clusters], labels, labelled)
    return {"accuracy": accuracy, "labelled_indices": labelled, "cluster_labels": cluster_labels}


def _accuracy(predicted: Tensor, labels: Tensor, labelled: Tensor) -> Tensor:
    """Share of the objects not ``labelled`` predicted right (float32 scalar; NaN when every object is labelled)."""
    evaluated = torch.ones(labels.numel(), dtype=torch.bool)
    evaluated[labelled] = False
    if not bool(evaluated.any()):
        return torch.tensor(float("nan"))
    return (predicted[evaluated] == labels[evaluated]).float().mean()


class FewShotAccuracy(_UnitMetric):
    """Few-shot object category labelling accuracy over all objects seen (the paper's Table 1).

    List states (``"cat"``) of every object's prototype id and true label; ``compute()`` runs :func:`few_shot_accuracy`
    (``nan`` before any object). ``**kwargs``: passed to :class:`torchmetrics.Metric`.

    Convention: ``update(clusters [N] long, labels [N] long)``, ids in ``[0, num_clusters)`` and ``[0, num_classes)``;
    each object must be fed exactly once.
    """

    clusters: list[Tensor]
    labels: list[Tensor]

    def __init__(self, num_clusters: int, num_classes: int, shots: int = 2, seed: int = 0, **kwargs: Any) -> None:
        super().__init__(**kwargs)
        _check_positive(num_clusters=num_clusters, num_classes=num_classes, shots=shots)
        self.num_clusters, self.num_classes, self.shots, self.seed = num_clusters, num_classes, shots, seed
        self.add_state("clusters", default=[], dist_reduce_fx="cat")
        self.add_state("labels", default=[], dist_reduce_fx="cat")

    def update(self, clusters: Tensor, labels: Tensor) -> None:
        """Add a batch of objects: ``clusters`` ``[N]`` in ``[0, num_clusters)``, ``labels`` ``[N]`` in
        ``[0, num_classes)``."""
        _check_pair(clusters, labels, self.num_clusters, self.num_classes)
        self.clusters.append(clusters.detach().long())
        self.labels.append(labels.detach().long())

    def compute(self) -> Tensor:
        """Few-shot accuracy on the not-labelled objects (scalar tensor)."""
        if isinstance(self.clusters, list) and not self.clusters:
            return torch.tensor(float("nan"))
        clusters, labels = dim_zero_cat(self.clusters), dim_zero_cat(self.labels)
        return few_shot_accuracy(clusters, labels, self.shots, self.seed, self.num_clusters)["accuracy"]


def _check_features(features: Tensor, labels: Tensor) -> None:
    if not isinstance(features, Tensor) or features.ndim != 2 or not features.is_floating_point():
        raise ValueError(f"features must be a float tensor [N, D], got {getattr(features, 'shape', type(features))}")
    _check_ids(labels, "labels", None)
    if labels.numel() != features.shape[0]:
        raise ValueError(f"labels must have {features.shape[0]} entries (one per feature row), got {labels.numel()}")


def _shot_split(features: Tensor, labels: Tensor, shots: int, seed: int) -> tuple[Tensor, Tensor, Tensor]:
    """Checked L2-normalised float64 features, int64 labels and the :func:`select_labelled` indices."""
    _check_features(features, labels)
    _check_positive(shots=shots)
    feats, labels = features.detach().double().cpu(), labels.detach().long().cpu()
    return torch.nn.functional.normalize(feats, dim=1), labels, select_labelled(labels, shots, seed)


def nearest_shot_accuracy(features: Tensor, labels: Tensor, shots: int = 2, seed: int = 0) -> dict[str, Tensor]:
    """Few-shot accuracy by retrieval (the paper's "ResNetRet"): every object of ``features`` ``[N, D]`` not among
    :func:`select_labelled` ``(labels [N], shots, seed)`` takes the label of the labelled example of highest cosine
    similarity (ties: the lowest index).

    Returns:
        ``accuracy`` (scalar, NaN when every object is labelled), ``labelled_indices`` ``[M]``, ``predicted`` ``[N]``.
    """
    f, labels, labelled = _shot_split(features, labels, shots, seed)
    nearest = (f @ f[labelled].T).argmax(dim=1)  # [N]
    predicted = labels[labelled][nearest]
    predicted[labelled] = labels[labelled]
    return {"accuracy": _accuracy(predicted, labels, labelled), "labelled_indices": labelled, "predicted": predicted}


def linear_probe_accuracy(features: Tensor, labels: Tensor, shots: int = 2, seed: int = 0, weight_decay: float = 1e-3,
                          iterations: int = 100) -> dict[str, Tensor]:  # fmt: skip
    """Few-shot accuracy of a linear classifier (the paper's "ResNetClass"): :func:`_fit_logistic` on the
    L2-normalised ``features`` ``[N, D]`` of :func:`select_labelled` ``(labels [N], shots, seed)`` predicts the others.

    Returns:
        ``accuracy`` (scalar, NaN when every object is labelled), ``labelled_indices`` ``[M]``, ``predicted`` ``[N]``
        (classes ``0 .. max(labels)``).
    """
    x, labels, labelled = _shot_split(features, labels, shots, seed)
    w, b = _fit_logistic(x[labelled], labels[labelled], int(labels.max()) + 1, weight_decay, iterations)
    with torch.no_grad():
        predicted = (x @ w + b).argmax(dim=1)
    return {"accuracy": _accuracy(predicted, labels, labelled), "labelled_indices": labelled, "predicted": predicted}


def _fit_logistic(x: Tensor, y: Tensor, classes: int, weight_decay: float, iterations: int) -> tuple[Tensor, Tensor]:
    """Multinomial logistic regression ``x @ w + b`` (float64, full batch, L-BFGS from zero weights, L2 penalty
    ``weight_decay * ||w||^2`` on the weights only; deterministic). Returns ``(w [D, classes], b [classes])``."""
    w = torch.zeros(x.shape[1], classes, dtype=torch.float64, requires_grad=True)
    b = torch.zeros(classes, dtype=torch.float64, requires_grad=True)
    opt = torch.optim.LBFGS([w, b], lr=1.0, max_iter=iterations, line_search_fn="strong_wolfe")

    def closure() -> Tensor:
        opt.zero_grad()
        loss = torch.nn.functional.cross_entropy(x @ w + b, y) + weight_decay * w.pow(2).sum()
        loss.backward()
        return loss

    with torch.enable_grad():
        opt.step(closure)
    return w.detach(), b.detach()


def linear_probe(train_features: Tensor, train_labels: Tensor, test_features: Tensor, test_labels: Tensor,
                 weight_decay: float = 1e-4, iterations: int = 200) -> dict[str, Tensor]:  # fmt: skip
    """Test accuracy (scalar) and ``predicted`` ``[M]`` of :func:`_fit_logistic` (``weight_decay``, ``iterations``)
    trained on every training object: ``train_features`` ``[N, D]``, ``train_labels`` ``[N]``, ``test_features``
    ``[M, D]``, ``test_labels`` ``[M]``. Each dimension is standardised by the training objects' mean and standard
    deviation; classes are ``0 .. max(train, test labels)``."""
    _check_features(train_features, train_labels)
    _check_features(test_features, test_labels)
    d_train, d_test = train_features.shape[1], test_features.shape[1]
    if d_train != d_test:
        raise ValueError(f"train and test features differ in width: {d_train} vs {d_test}")
    xtr, xte = train_features.detach().double().cpu(), test_features.detach().double().cpu()
    ytr, yte = train_labels.detach().long().cpu(), test_labels.detach().long().cpu()
    mean, std = xtr.mean(0), xtr.std(0, unbiased=False).clamp_min(1e-12)
    num_classes = int(max(ytr.max(), yte.max())) + 1
    w, b = _fit_logistic((xtr - mean) / std, ytr, num_classes, weight_decay, iterations)
    predicted = (((xte - mean) / std) @ w + b).argmax(dim=1)
    return {"accuracy": (predicted == yte).double().mean(), "predicted": predicted}
