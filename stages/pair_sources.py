"""Where a mining refresh's candidate pairs come from: :class:`PairSource` and its two strategies,
:class:`InputPairs` (``candidates_from: input`` or ``occupancy``: mutual nearest neighbours by the unprojected input
crops' agreement over every yaw) and :class:`FeaturePairs` (``features``: the paper's miner on the learned features).
Either hands its pairs best first, optionally spread over the queries (:func:`spread_candidates`).

Convention: crops ``[N, C, Z, Y, X]``; yaw about the crop's vertical axis through its centre, counter-clockwise seen
from above, step ``b`` meaning ``2 pi b / num_angles``; a pair's yaw rotates the TARGET crop onto the query.
"""

from __future__ import annotations

import math
from abc import ABC, abstractmethod
from typing import Any

import torch
import torch.nn.functional as F
from torch import Tensor

from threedq.contrastive import mine_correspondences
from threedq.geometry import rotate_yaw
from threedq.stages.positives import shape_agreement, take_pairs

__all__ = ["FeaturePairs", "InputPairs", "PairSource", "input_occupancy", "input_pairs", "mutual_pool_neighbours",
           "pool_shape_agreement", "spread_candidates"]


def input_occupancy(raw: Tensor, colour: bool = False) -> Tensor:
    """The pool crops' input occupancy, the surface and the cells next to it (a 3^3 max): ``[N, 1, s, s, s]`` from
    ``raw`` ``[N, 4, s, s, s]`` (``cat[occ, occ * rgb]``); ``colour``: the whole input crop dilated alike, ``[N, 4, s,
    s, s]``."""
    return F.max_pool3d((raw if colour else raw[:, :1]).float(), kernel_size=3, stride=1, padding=1)


def pool_shape_agreement(occ: Tensor, num_angles: int, chunk: int = 128) -> Tensor:
    """:func:`~threedq.stages.positives.shape_agreement` of every box of a pool with every other: ``S[n, m]``, the
    cosine of crop ``n`` with crop ``m`` turned onto it, at the yaw where it is highest.

    Args:
        occ: ``[N, C, s, s, s]`` non-negative crops (one cosine over all channels). num_angles: yaw steps.
        chunk: target crops rotated at once (memory ``chunk * num_angles * C * s^3`` floats).

    Returns:
        ``[N, N]`` cosines (0 where a crop is empty); row: the query, column: the target.
    """
    N, A = occ.shape[0], num_angles
    q = F.normalize(occ.flatten(1), dim=1)  # [N, C s^3]
    out = occ.new_zeros(N, N)
    angles = torch.arange(A, device=occ.device, dtype=occ.dtype) * (2 * math.pi / A)
    for s in range(0, N, chunk):
        t = rotate_yaw(occ[s:s + chunk], angles.expand(min(chunk, N - s), A))  # [n, A, C, s, s, s]
        t = F.normalize(t.flatten(2), dim=2)  # [n, A, C s^3]
        out[:, s:s + chunk] = torch.einsum("nv,mav->nma", q, t).amax(dim=2)
    return out


def mutual_pool_neighbours(similarity: Tensor, exclude: Tensor, k: int) -> Tensor:
    """``[N, N]`` bool: ``n`` and ``m`` are each among the other's ``k`` most similar by their own row (excluded pairs
    never count; ties go to the lower index).

    Args:
        similarity: ``[N, N]``; exclude: ``[N, N]`` bool (e.g. the same scene, the box itself); k: >= 1.
    """
    sim = similarity.masked_fill(exclude, float("-inf"))
    k = min(k, sim.shape[1])
    near = torch.zeros_like(exclude)
    near.scatter_(1, sim.topk(k, dim=1).indices, True)
    return near & near.T & ~exclude


def input_pairs(crops: Tensor, scene: Tensor, n_q: int, k: int, num_angles: int) -> dict[str, Tensor]:
    """Every pair of mutual ``k`` nearest neighbours by :func:`pool_shape_agreement` (other scenes only) whose query is
    one of the first ``n_q`` boxes, best agreement first.

    Args:
        crops: ``[N, C, s, s, s]`` input crops (non-negative); scene: ``[N]`` long scene of each box; n_q: queries;
            k: >= 1; num_angles: yaw steps in a full turn.

    Returns:
        :func:`~threedq.contrastive.mine_correspondences`' keys: ``query_index``, ``target_index``, ``yaw`` ``[P]``
        long, ``score`` ``[P]`` (the agreement), ``query_pos``, ``target_pos``, ``target_pos_aligned`` ``[P, 3]``
        (zeros).
    """
    sim = pool_shape_agreement(crops, num_angles)
    mutual = mutual_pool_neighbours(sim, scene[:, None] == scene[None, :], k)[:n_q]
    qi, ti = mutual.nonzero(as_tuple=True)
    order = torch.sort(sim[qi, ti], descending=True, stable=True).indices
    qi, ti = qi[order], ti[order]
    _, yaw = shape_agreement(crops[qi], crops[ti], num_angles)
    zeros = qi.new_zeros(qi.numel(), 3)
    return {"query_index": qi, "target_index": ti, "yaw": yaw, "score": sim[qi, ti],
            "query_pos": zeros, "target_pos": zeros.clone(), "target_pos_aligned": zeros.clone()}


def spread_candidates(query_index: Tensor, per_query: int, count: int) -> Tensor:
    """Indices of the candidate pairs spread over the queries: each query's first ``per_query`` pairs, every query's
    best before any query's second (ties in rank order), cut at ``count``.

    Args:
        query_index: ``[P]`` pool index of each pair's query, best pair first. per_query, count: >= 1.

    Returns:
        ``[P']`` long indices into the pairs, ``P' <= min(count, P)``, in the new order.
    """
    P = query_index.numel()
    if P == 0:
        return torch.zeros(0, dtype=torch.long, device=query_index.device)
    order = torch.sort(query_index, stable=True).indices  # pairs grouped by query, rank order within a query
    q = query_index[order]
    start = torch.ones_like(q, dtype=torch.bool)
    start[1:] = q[1:] != q[:-1]
    group_start = torch.cummax(torch.where(start, torch.arange(P, device=q.device), 0), dim=0).values
    rank = torch.empty_like(order)
    rank[order] = torch.arange(P, device=q.device) - group_start  # each pair's rank among its query's pairs
    pos = torch.arange(P, device=q.device)
    keep = (rank < per_query).nonzero().flatten()
    return keep[torch.sort(rank[keep] * P + pos[keep], stable=True).indices][:count]


class PairSource(ABC):
    """A refresh's candidate pairs of a pool, best first.

    Args:
        per_query: each query's best ``per_query`` pairs, spread over the queries (:func:`spread_candidates`);
            ``None``: the ``count`` best pairs.
        num_angles: yaw steps in a full turn.
    """

    #: the ``candidates_from`` value that names the source
    name: str

    def __init__(self, per_query: int | None, num_angles: int) -> None:
        self.per_query, self.num_angles = per_query, num_angles

    @abstractmethod
    def pairs(self, pool: dict[str, Tensor], n_q: int, count: int, min_cosine: float) -> dict[str, Tensor]:
        """Every candidate of the source, best first (the spread and the cut at ``count`` are :meth:`candidates`')."""

    def candidates(self, pool: dict[str, Tensor], n_q: int, count: int, min_cosine: float) -> dict[str, Any]:
        """At most ``count`` candidate pairs of ``pool`` whose queries are its first ``n_q`` boxes, best first.

        Args:
            pool: ``features`` ``[N, C, s, s, s]``, ``raw`` ``[N, 4, s, s, s]`` input crops, ``scene`` ``[N]`` long.
            n_q: queries; count: pairs at most; min_cosine: the context threshold of the miner's verification.

        Returns:
            :func:`~threedq.contrastive.mine_correspondences`' keys (``query_index``, ``target_index``, ``yaw``,
            ``score``, ``query_pos``, ``target_pos``, ``target_pos_aligned``).
        """
        mined = self.pairs(pool, n_q, count, min_cosine)
        if self.per_query is not None:
            return take_pairs(mined, spread_candidates(mined["query_index"], self.per_query, count))
        return take_pairs(mined, torch.arange(min(count, mined["query_index"].numel()),
                                              device=mined["query_index"].device))

    def describe(self) -> dict[str, Any]:
        """What a refresh's diagnostics record of the source."""
        return {}


class InputPairs(PairSource):
    """The input crops' mutual ``mutual_k`` nearest neighbours by agreement over every yaw (:func:`input_pairs`):
    occupancy and colour (``colour``, ``candidates_from: input``) or the occupancy alone (``occupancy``)."""

    def __init__(self, mutual_k: int, colour: bool, per_query: int | None, num_angles: int) -> None:
        super().__init__(per_query, num_angles)
        self.mutual_k, self.colour = mutual_k, colour
        self.name = "input" if colour else "occupancy"

    def pairs(self, pool: dict[str, Tensor], n_q: int, count: int, min_cosine: float) -> dict[str, Tensor]:
        crops = input_occupancy(pool["raw"], colour=self.colour)
        return input_pairs(crops, pool["scene"], n_q, self.mutual_k, self.num_angles)

    def describe(self) -> dict[str, Any]:
        return {"occupancy_mutual_k": self.mutual_k, "candidates_from": self.name}


class FeaturePairs(PairSource):
    """The paper's miner on the learned features (:func:`~threedq.contrastive.mine_correspondences`; ``miner``: its
    other keywords)."""

    name = "features"

    def __init__(self, top_k: int, per_query: int | None, num_angles: int, **miner: Any) -> None:
        super().__init__(per_query, num_angles)
        self.top_k, self.miner = top_k, miner

    def pairs(self, pool: dict[str, Tensor], n_q: int, count: int, min_cosine: float) -> dict[str, Tensor]:
        feats, scene = pool["features"], pool["scene"]
        top_k = min(self.top_k, feats.shape[0])
        return mine_correspondences(
            feats[:n_q], feats, top_k=top_k, keep=n_q * top_k if self.per_query is not None else count,
            exclude=scene[:n_q, None] == scene[None, :], min_cosine=min_cosine, num_angles=self.num_angles,
            **self.miner)
