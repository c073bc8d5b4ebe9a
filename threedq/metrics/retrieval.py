"""Rotation-max object retrieval: similarity over yaw and precision@K (the paper's Table 2 protocol).

Two object crops are compared at their best relative yaw: ``sim(q, g) = max_a cos(rotate(q, a), g)``
over ``num_angles`` yaw steps, with each crop flattened to one vector. Precision@K counts, per query,
how many of its K most similar gallery objects share its category, then averages per category and
over categories (macro average), so frequent categories do not dominate.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor
from torchmetrics import Metric
from torchmetrics.utilities import dim_zero_cat

from threedq.geometry.rotate import rotate_yaw, yaw_angles

__all__ = ["rotation_max_similarity", "retrieval_precision_at_k", "RetrievalPrecisionAtK"]


def rotation_max_similarity(
    query: Tensor, gallery: Tensor, num_angles: int = 36, chunk: int = 64, method: str = "exact"
) -> tuple[Tensor, Tensor]:
    """Cosine similarity of every query to every gallery crop at the best yaw of the query.

    ``method="exact"`` (the reference): each query is rotated by every candidate yaw (trilinear, about its
    vertical centre line), flattened and L2-normalised, then compared with every flattened, L2-normalised
    gallery crop. ``method="fast"``: ``threedq.rotation_search.all_pairs_rotation_max`` (cylindrical
    resampling + rFFT correlation over the angle; the cosine is taken over the inscribed cylinder of the
    crops, so it differs slightly from the exact one when content lies in the corners; ~30x faster on CPU).

    Args:
        query: ``[N, C, S, S, S]`` crops.
        gallery: ``[M, C, S, S, S]`` crops.
        num_angles: yaw candidates ``2 pi a / num_angles``.
        chunk: queries rotated at once (bounds memory: ``chunk * num_angles`` crops); ``"exact"`` only, the
            fast path sizes its own chunks.
        method: ``"exact"`` or ``"fast"``.

    Returns:
        ``sim`` ``[N, M]`` the maximum cosine over yaw, and ``angle`` ``[N, M]`` long, the index ``a``
        of the best yaw (rotating the query by ``2 pi a / num_angles`` aligns it with the gallery crop).

    Convention: crops in frame R order ``[C, Z, Y, X]``, z up; yaw counter-clockwise seen from above.
    """
    if query.ndim != 5 or gallery.ndim != 5 or query.shape[1:] != gallery.shape[1:]:
        raise ValueError(
            f"query and gallery must be [N, C, Z, Y, X] crops of one shape, got {tuple(query.shape)} and "
            f"{tuple(gallery.shape)}"
        )
    if method == "fast":
        from threedq.rotation_search import all_pairs_rotation_max

        return all_pairs_rotation_max(query, gallery, num_angles, method="fast")
    if method != "exact":
        raise ValueError(f"method must be 'exact' or 'fast', got {method!r}")
    g = F.normalize(gallery.flatten(1), dim=1)  # [M, D]
    angles = yaw_angles(num_angles, device=query.device, dtype=query.dtype)
    sims, idxs = [], []
    for start in range(0, query.shape[0], chunk):
        q = query[start : start + chunk]
        rotated = rotate_yaw(q, angles.expand(q.shape[0], num_angles))  # [n, A, C, Z, Y, X]
        r = F.normalize(rotated.flatten(2), dim=2)  # [n, A, D]
        s = torch.einsum("nad,md->nma", r, g)  # [n, M, A]
        best, arg = s.max(dim=2)
        sims.append(best)
        idxs.append(arg)
    return torch.cat(sims), torch.cat(idxs)


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
    ``rotation_max_similarity(..., method=method)`` (default ``"fast"``: cylindrical resampling + rFFT over the
    angle; ``"exact"`` rotates every crop by every yaw).
    """

    is_differentiable = False
    higher_is_better = True
    full_state_update = False

    def __init__(self, k: int = 10, num_angles: int = 36, method: str = "fast", **kwargs) -> None:  # noqa: ANN003
        super().__init__(**kwargs)
        if method not in ("exact", "fast"):
            raise ValueError(f"method must be 'exact' or 'fast', got {method!r}")
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
        sim, _ = rotation_max_similarity(crops, crops, self.num_angles, method=self.method)
        return retrieval_precision_at_k(sim, labels, labels, min(self.k, crops.shape[0] - 1), exclude_diagonal=True)
