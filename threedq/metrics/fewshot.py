"""Few-shot object category labelling accuracy through prototypes (the paper's Table 1 protocol).

``shots`` objects per category (two in the paper: 52 labelled crops for CARLA's 26 categories) are given
their true label. Each prototype (cluster) takes the label that most of its labelled members carry, and
every object inherits the label of its prototype. Accuracy is measured on the objects that were not
labelled. The labelled examples are not used to train features or prototypes: this metric only reads the
final assignments.
"""

from __future__ import annotations

from typing import Any

import torch
from torch import Tensor
from torchmetrics import Metric
from torchmetrics.utilities import dim_zero_cat

from threedq.metrics.clustering import _check_ids, _check_pair

__all__ = [
    "FewShotAccuracy",
    "few_shot_accuracy",
    "linear_probe",
    "linear_probe_accuracy",
    "nearest_shot_accuracy",
    "select_labelled",
]


def _check_shots(shots: int) -> None:
    if not isinstance(shots, int) or isinstance(shots, bool) or shots < 1:
        raise ValueError(f"shots must be a positive int, got {shots!r}")


def select_labelled(labels: Tensor, shots: int, seed: int = 0, clusters: Tensor | None = None) -> Tensor:
    """Pick ``shots`` labelled examples per category, deterministically from ``seed``.

    Objects are first ordered by ``(label, cluster)`` (stable), then, for each category in increasing id, a
    ``torch.randperm`` drawn from one ``torch.Generator`` seeded with ``seed`` picks ``min(shots, n_c)`` of
    its ``n_c`` objects. Because objects with the same label and cluster are interchangeable for the metric,
    the resulting accuracy does not depend on the order in which objects were fed (e.g. the rank order of a
    DDP gather).

    Args:
        labels: ``[N]`` integer category ids.
        shots: labelled examples per category (``>= 1``); a category with fewer objects uses all of them.
        seed: seed of the selection.
        clusters: ``[N]`` integer prototype ids used for the order-independent ordering (optional).

    Returns:
        ``[M]`` int64 indices into ``labels``, sorted ascending, ``M = sum_c min(shots, n_c)``.

    Raises:
        ValueError: if ``shots < 1``.

    Convention: categories are visited in increasing id; a category absent from ``labels`` gets no example.
    """
    _check_shots(shots)
    labels = labels.long().cpu()
    if labels.numel() == 0:
        return torch.zeros(0, dtype=torch.long)
    if clusters is not None:
        clusters = clusters.long().cpu()
        key = labels * (int(clusters.max()) + 1) + clusters
    else:
        key = labels
    order = torch.sort(key, stable=True).indices
    sorted_labels = labels[order]
    _, counts = torch.unique_consecutive(sorted_labels, return_counts=True)
    gen = torch.Generator().manual_seed(seed)
    picked: list[Tensor] = []
    start = 0
    for n in counts.tolist():
        take = torch.randperm(n, generator=gen)[: min(shots, n)]
        picked.append(order[start + take])
        start += n
    return torch.sort(torch.cat(picked)).values


def few_shot_accuracy(
    clusters: Tensor,
    labels: Tensor,
    shots: int = 2,
    seed: int = 0,
    num_clusters: int | None = None,
    labelled_indices: Tensor | None = None,
) -> dict[str, Tensor]:
    """Few-shot labelling accuracy: label ``shots`` objects per category, propagate through prototypes.

    Args:
        clusters: ``[N]`` integer prototype ids in ``[0, num_clusters)`` (the prototype each object is
            assigned to by the rotation-aware matching).
        labels: ``[N]`` integer true category ids (``>= 0``).
        shots: labelled examples per category (2 in the paper); categories with fewer objects use all.
        seed: seed of the choice of labelled examples (see :func:`select_labelled`).
        num_clusters: ``K``; default ``max(clusters) + 1``.
        labelled_indices: ``[M]`` indices of the labelled examples, overriding the seeded choice (e.g. to
            reuse a fixed labelled set); default :func:`select_labelled` ``(labels, shots, seed, clusters)``.

    Returns:
        A dict with

        * ``accuracy``: scalar float32, the fraction of the NOT-labelled objects whose prototype's label
          equals their true label (``nan`` if every object was labelled);
        * ``labelled_indices``: ``[M]`` int64 indices of the labelled examples (ascending);
        * ``cluster_labels``: ``[K]`` int64, the label each prototype took, ``-1`` for a prototype without
          a labelled member (its objects count as wrong).

    Raises:
        ValueError: on malformed inputs (not 1-D integer tensors of one length, ids out of range,
            ``shots < 1``, ``labelled_indices`` out of range).

    Convention: a prototype takes the majority label of its labelled members, ties going to the smallest
    label id; accuracy is micro-averaged over objects (not per category).
    """
    _check_pair(clusters, labels, num_clusters, None)
    _check_shots(shots)
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

    evaluated = torch.ones(labels.numel(), dtype=torch.bool)
    evaluated[labelled] = False
    if bool(evaluated.any()):
        correct = cluster_labels[clusters[evaluated]] == labels[evaluated]
        accuracy = correct.float().mean()
    else:
        accuracy = torch.tensor(float("nan"))
    return {"accuracy": accuracy, "labelled_indices": labelled, "cluster_labels": cluster_labels}


class FewShotAccuracy(Metric):
    """Few-shot object category labelling accuracy over all objects seen (the paper's Table 1).

    Stores every object's prototype id and true label (list states, ``dist_reduce_fx="cat"``) and runs
    :func:`few_shot_accuracy` on all of them in ``compute()``: the labelled examples are picked from the
    whole evaluation set, so they cannot be chosen batch by batch.

    Args:
        num_clusters: ``K``, the number of prototypes.
        num_classes: ``C``, the number of true categories.
        shots: labelled examples per category (2 in the paper).
        seed: seed of the choice of labelled examples.
        **kwargs: passed to :class:`torchmetrics.Metric`.

    Convention: ``update(clusters [N] long, labels [N] long)``, ids in ``[0, K)`` and ``[0, C)``; ``compute()``
    returns the accuracy on the not-labelled objects (scalar; ``nan`` before any object). The result does
    not depend on the order of objects (nor on DDP rank order), but each object must be fed exactly once.
    """

    is_differentiable = False
    higher_is_better = True
    full_state_update = False
    plot_lower_bound = 0.0
    plot_upper_bound = 1.0

    clusters: list[Tensor]
    labels: list[Tensor]

    def __init__(self, num_clusters: int, num_classes: int, shots: int = 2, seed: int = 0, **kwargs: Any) -> None:
        super().__init__(**kwargs)
        for name, value in (("num_clusters", num_clusters), ("num_classes", num_classes), ("shots", shots)):
            if not isinstance(value, int) or isinstance(value, bool) or value < 1:
                raise ValueError(f"{name} must be a positive int, got {value!r}")
        self.num_clusters = num_clusters
        self.num_classes = num_classes
        self.shots = shots
        self.seed = seed
        self.add_state("clusters", default=[], dist_reduce_fx="cat")
        self.add_state("labels", default=[], dist_reduce_fx="cat")

    def update(self, clusters: Tensor, labels: Tensor) -> None:
        """Add a batch of objects.

        Args:
            clusters: ``[N]`` integer prototype ids in ``[0, num_clusters)``.
            labels: ``[N]`` integer category ids in ``[0, num_classes)``.
        """
        _check_pair(clusters, labels, self.num_clusters, self.num_classes)
        self.clusters.append(clusters.detach().long())
        self.labels.append(labels.detach().long())

    def compute(self) -> Tensor:
        """Few-shot accuracy on the not-labelled objects (scalar tensor)."""
        if isinstance(self.clusters, list) and not self.clusters:
            return torch.tensor(float("nan"))
        clusters, labels = dim_zero_cat(self.clusters), dim_zero_cat(self.labels)
        return few_shot_accuracy(clusters, labels, self.shots, self.seed, self.num_clusters)["accuracy"]


def _shot_split(labels: Tensor, shots: int, seed: int) -> tuple[Tensor, Tensor]:
    labelled = select_labelled(labels, shots, seed)
    evaluated = torch.ones(labels.numel(), dtype=torch.bool)
    evaluated[labelled] = False
    return labelled, evaluated


def _check_features(features: Tensor, labels: Tensor) -> None:
    if not isinstance(features, Tensor) or features.ndim != 2 or not features.is_floating_point():
        raise ValueError(f"features must be a float tensor [N, D], got {getattr(features, 'shape', type(features))}")
    _check_ids(labels, "labels", None)
    if labels.numel() != features.shape[0]:
        raise ValueError(f"labels must have {features.shape[0]} entries (one per feature row), got {labels.numel()}")


def nearest_shot_accuracy(features: Tensor, labels: Tensor, shots: int = 2, seed: int = 0) -> dict[str, Tensor]:
    """Few-shot accuracy by retrieval (the paper's "ResNetRet"): copy the label of the nearest labelled example.

    The labelled examples are :func:`select_labelled` ``(labels, shots, seed)``; every other object takes the
    label of the labelled example of highest cosine similarity (ties: the lowest index).

    Args:
        features: ``[N, D]`` object features.
        labels: ``[N]`` category ids.
        shots, seed: as :func:`few_shot_accuracy`.

    Returns:
        ``accuracy`` (scalar, NaN when every object is labelled), ``labelled_indices`` ``[M]``, ``predicted``
        ``[N]`` (labelled objects keep their own label).

    Convention: cosine similarity of the raw feature vectors; accuracy micro-averaged over the unlabelled objects.
    """
    _check_features(features, labels)
    _check_shots(shots)
    feats, labels = features.detach().double().cpu(), labels.detach().long().cpu()
    labelled, evaluated = _shot_split(labels, shots, seed)
    f = torch.nn.functional.normalize(feats, dim=1)
    nearest = (f @ f[labelled].T).argmax(dim=1)  # [N]
    predicted = labels[labelled][nearest]
    predicted[labelled] = labels[labelled]
    acc = (predicted[evaluated] == labels[evaluated]).float().mean() if evaluated.any() else torch.tensor(float("nan"))
    return {"accuracy": acc, "labelled_indices": labelled, "predicted": predicted}


def linear_probe_accuracy(
    features: Tensor, labels: Tensor, shots: int = 2, seed: int = 0, weight_decay: float = 1e-3, iterations: int = 100
) -> dict[str, Tensor]:
    """Few-shot accuracy of a linear classifier trained on the labelled examples (the paper's "ResNetClass").

    A multinomial logistic regression (the top layer, features frozen) on the L2-normalised features of the
    :func:`select_labelled` examples, full batch, L-BFGS from zero weights in float64 with an L2 penalty
    ``weight_decay * ||W||^2`` (deterministic); it predicts every other object.

    Args:
        features: ``[N, D]`` object features.
        labels: ``[N]`` category ids.
        shots, seed: as :func:`few_shot_accuracy`.
        weight_decay: L2 penalty on the weights (not the bias).
        iterations: L-BFGS iterations.

    Returns:
        ``accuracy`` (scalar, NaN when every object is labelled), ``labelled_indices`` ``[M]``, ``predicted`` ``[N]``.

    Convention: classes are the category ids ``0 .. max(labels)``; a category without labelled examples is never
    predicted (its logit has no positive example and is driven down).
    """
    _check_features(features, labels)
    _check_shots(shots)
    feats, labels = features.detach().double().cpu(), labels.detach().long().cpu()
    labelled, evaluated = _shot_split(labels, shots, seed)
    x = torch.nn.functional.normalize(feats, dim=1)
    w, b = _fit_logistic(x[labelled], labels[labelled], int(labels.max()) + 1, weight_decay, iterations)
    with torch.no_grad():
        predicted = (x @ w + b).argmax(dim=1)
    acc = (predicted[evaluated] == labels[evaluated]).float().mean() if evaluated.any() else torch.tensor(float("nan"))
    return {"accuracy": acc, "labelled_indices": labelled, "predicted": predicted}


def _fit_logistic(x: Tensor, y: Tensor, num_classes: int, weight_decay: float, iterations: int) -> tuple[Tensor, Tensor]:
    """Multinomial logistic regression ``x @ w + b`` (float64, full batch, L-BFGS from zero weights, L2 penalty
    ``weight_decay * ||w||^2`` on the weights only; deterministic). Returns ``(w [D, num_classes], b [num_classes])``."""
    w = torch.zeros(x.shape[1], num_classes, dtype=torch.float64, requires_grad=True)
    b = torch.zeros(num_classes, dtype=torch.float64, requires_grad=True)
    opt = torch.optim.LBFGS([w, b], lr=1.0, max_iter=iterations, line_search_fn="strong_wolfe")

    def closure() -> Tensor:
        opt.zero_grad()
        loss = torch.nn.functional.cross_entropy(x @ w + b, y) + weight_decay * w.pow(2).sum()
        loss.backward()
        return loss

    with torch.enable_grad():
        opt.step(closure)
    return w.detach(), b.detach()


def linear_probe(
    train_features: Tensor, train_labels: Tensor, test_features: Tensor, test_labels: Tensor,
    weight_decay: float = 1e-4, iterations: int = 200,
) -> dict[str, Tensor]:
    """Accuracy of a linear classifier trained on every labelled training object, on the test objects.

    The features stay frozen (labels train the probe only): each dimension is standardised by the training
    objects' mean and standard deviation, then a multinomial logistic regression is fitted as in
    :func:`linear_probe_accuracy` (float64, L-BFGS, deterministic).

    Args:
        train_features: ``[N, D]``; train_labels: ``[N]`` category ids.
        test_features: ``[M, D]``; test_labels: ``[M]``.
        weight_decay, iterations: L2 penalty on the weights and L-BFGS iterations.

    Returns:
        ``accuracy`` (scalar: share of test objects predicted right) and ``predicted`` ``[M]``.

    Convention: classes are ``0 .. max(train, test labels)``; a class absent from training is never predicted.
    """
    _check_features(train_features, train_labels)
    _check_features(test_features, test_labels)
    if train_features.shape[1] != test_features.shape[1]:
        raise ValueError(f"train and test features differ in width: {train_features.shape[1]} vs {test_features.shape[1]}")
    xtr, xte = train_features.detach().double().cpu(), test_features.detach().double().cpu()
    ytr, yte = train_labels.detach().long().cpu(), test_labels.detach().long().cpu()
    mean, std = xtr.mean(0), xtr.std(0, unbiased=False).clamp_min(1e-12)
    num_classes = int(max(ytr.max(), yte.max())) + 1
    w, b = _fit_logistic((xtr - mean) / std, ytr, num_classes, weight_decay, iterations)
    predicted = (((xte - mean) / std) @ w + b).argmax(dim=1)
    return {"accuracy": (predicted == yte).double().mean(), "predicted": predicted}
