"""Relative yaw error of objects assigned to the same prototype.

Matching an object to a prototype also yields a yaw (Eq. 1 of the paper: the rotation ``R`` that best aligns
the object's crop with the prototype). A prototype's canonical pose is arbitrary, so an absolute yaw cannot
be scored; what can is whether two objects of one category put into the same prototype get the right
*relative* yaw. For every such pair the error is the circular difference between the estimated and the true
relative yaw, in ``[0, pi]``.

Sign convention (as produced by ``rotation_max_similarity`` and the argmin of Eq. 1): ``y_o`` is the yaw that,
applied to object ``o``'s crop with :func:`threedq.geometry.rotate_yaw` (counter-clockwise about +z seen from
above), aligns it with its prototype. If the object is the prototype turned by ``theta_o`` then
``y_o = -theta_o``, so the estimated orientation of ``o`` relative to ``p`` is ``-(y_o - y_p)``, which must equal
the true ``g_o - g_p``::

    error(o, p) = | wrap( -(y_o - y_p) - (g_o - g_p) ) | = | wrap( (y_p + g_p) - (y_o + g_o) ) |

i.e. perfect estimates are exactly those with ``y_o = const - g_o``. Only asymmetric categories (symmetry order
1) give pairs.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any

import torch
from torch import Tensor
from torchmetrics import Metric
from torchmetrics.utilities import dim_zero_cat

__all__ = ["RelativeYawError", "relative_yaw_error", "relative_yaw_errors"]

#: accuracy thresholds of the summary, degrees (inclusive)
THRESHOLDS_DEG = (10.0, 20.0)


def _check_options(symmetry_order: Sequence[int], max_pairs_per_group: int) -> None:
    if isinstance(symmetry_order, (str, bytes)) or not isinstance(symmetry_order, Sequence):
        raise TypeError(f"symmetry_order must be a sequence of ints, one per category, got {symmetry_order!r}")
    for o in symmetry_order:
        if not isinstance(o, int) or isinstance(o, bool) or o < 0:
            raise ValueError(f"symmetry_order entries must be ints >= 0 (0 = continuous), got {list(symmetry_order)}")
    if not isinstance(max_pairs_per_group, int) or isinstance(max_pairs_per_group, bool) or max_pairs_per_group < 1:
        raise ValueError(f"max_pairs_per_group must be a positive int, got {max_pairs_per_group!r}")


def _check_inputs(est_yaw: Tensor, gt_yaw: Tensor, categories: Tensor, clusters: Tensor, num_categories: int) -> None:
    tensors = {"est_yaw": est_yaw, "gt_yaw": gt_yaw, "categories": categories, "clusters": clusters}
    for name, t in tensors.items():
        if not isinstance(t, Tensor) or t.ndim != 1:
            shape = tuple(t.shape) if isinstance(t, Tensor) else type(t).__name__
            raise ValueError(f"{name} must be a 1-D tensor [N], got {shape}")
    n = est_yaw.shape[0]
    if any(t.shape[0] != n for t in tensors.values()):
        raise ValueError(f"inputs must have one length N, got { {k: t.shape[0] for k, t in tensors.items()} }")
    for name in ("est_yaw", "gt_yaw"):
        t = tensors[name]
        if not t.is_floating_point():
            raise ValueError(f"{name} must be a floating-point tensor of radians, got {t.dtype}")
        if not bool(torch.isfinite(t).all()):
            raise ValueError(f"{name} must be finite")
    for name in ("categories", "clusters"):
        t = tensors[name]
        if t.is_floating_point() or t.is_complex() or t.dtype == torch.bool:
            raise ValueError(f"{name} must be an integer tensor, got {t.dtype}")
    if n and (int(categories.min()) < 0 or int(categories.max()) >= num_categories):
        raise ValueError(
            f"categories must lie in [0, {num_categories}) (one symmetry_order entry each), got values in "
            f"[{int(categories.min())}, {int(categories.max())}]"
        )
    if n and int(clusters.min()) < 0:
        raise ValueError(f"clusters must be >= 0, got {int(clusters.min())}")


def _circular_distance(diff: Tensor, period: Tensor | float) -> Tensor:
    """``|diff|`` on a circle of circumference ``period``: a value in ``[0, period / 2]``."""
    r = torch.remainder(diff, period)
    return torch.minimum(r, period - r)


def relative_yaw_errors(
    est_yaw: Tensor,
    gt_yaw: Tensor,
    categories: Tensor,
    clusters: Tensor,
    symmetry_order: Sequence[int],
    max_pairs_per_group: int = 5000,
    seed: int = 0,
    order: int = 1,
) -> Tensor:
    """Relative yaw error of every pair of objects of an asymmetric category with the same prototype (``order`` 1),
    or of an ``order``-fold symmetric category, modulo its period ``2 pi / order``.

    Objects are grouped by (prototype, category). A group of ``m`` objects gives its ``m (m - 1) / 2``
    unordered pairs; if that exceeds ``max_pairs_per_group``, exactly ``max_pairs_per_group`` pairs
    ``(i, j != i)`` are drawn uniformly with replacement from a ``torch.Generator`` seeded with ``seed``
    (groups visited in increasing ``cluster * num_categories + category``, members ordered by their
    residual ``y + g``), so the result is deterministic and independent of the order of the objects.

    Args:
        est_yaw: ``[N]`` estimated (alignment) yaw ``y_o`` in radians (any range).
        gt_yaw: ``[N]`` ground-truth yaw ``g_o`` in radians, in the (z-up) frame the crops were cut in.
        categories: ``[N]`` true category ids in ``[0, len(symmetry_order))``.
        clusters: ``[N]`` prototype ids (``>= 0``).
        symmetry_order: per category, how many yaws in ``[0, 2 pi)`` map the shape onto itself: 1 =
            asymmetric, ``n >= 2`` = n-fold, 0 = continuous; only order-1 categories give pairs.
        max_pairs_per_group: cap on the pairs of one (prototype, category) group.
        seed: seed of the pair sampling of capped groups.
        order: the symmetry order whose categories give pairs (``>= 1``); the error is taken modulo
            ``2 pi / order`` (a cube's relative yaw is only known up to quarter turns).

    Returns:
        ``[P]`` float64 errors in radians, in ``[0, pi / order]``, grouped by (prototype, category).

    Raises:
        ValueError: on malformed inputs or options.
    """
    _check_options(symmetry_order, max_pairs_per_group)
    _check_inputs(est_yaw, gt_yaw, categories, clusters, len(symmetry_order))
    if isinstance(order, bool) or not isinstance(order, int) or order < 1:
        raise ValueError(f"order must be an int >= 1 (a continuous symmetry has no yaw to score), got {order!r}")
    est, gt = est_yaw.detach().cpu().double(), gt_yaw.detach().cpu().double()
    cats, clus = categories.detach().cpu().long(), clusters.detach().cpu().long()
    orders = torch.tensor(list(symmetry_order), dtype=torch.long)

    residual = est + gt  # constant within a group when perfect
    order_o = orders[cats] if cats.numel() else torch.zeros(0, dtype=torch.long)
    keep = order_o == order
    residual, cats, clus = residual[keep], cats[keep], clus[keep]
    if residual.numel() < 2:
        return torch.zeros(0, dtype=torch.float64)

    # Sort by (group key, residual): groups become contiguous, and members are in an order-independent order.
    key = clus * len(symmetry_order) + cats
    by_residual = torch.sort(residual, stable=True).indices
    perm = by_residual[torch.sort(key[by_residual], stable=True).indices]
    residual, key = residual[perm], key[perm]
    _, counts = torch.unique_consecutive(key, return_counts=True)

    gen = torch.Generator().manual_seed(seed)
    errors: list[Tensor] = []
    start = 0
    for m in counts.tolist():
        if m >= 2:
            r = residual[start : start + m]
            n_pairs = m * (m - 1) // 2
            if n_pairs <= max_pairs_per_group:
                i, j = torch.triu_indices(m, m, offset=1)
            else:
                i = torch.randint(m, (max_pairs_per_group,), generator=gen)
                j = torch.randint(m - 1, (max_pairs_per_group,), generator=gen)
                j = j + (j >= i).long()  # uniform over j != i
            errors.append(_circular_distance(r[j] - r[i], 2 * math.pi / order))
        start += m
    return torch.cat(errors) if errors else torch.zeros(0, dtype=torch.float64)


def _summary(errors: Tensor) -> dict[str, Tensor]:
    deg = torch.rad2deg(errors)
    n = deg.numel()
    out: dict[str, Tensor] = {}
    if n:
        s = torch.sort(deg).values
        median = s[n // 2] if n % 2 else 0.5 * (s[n // 2 - 1] + s[n // 2])
        out["median_deg"] = median.float()
    else:
        out["median_deg"] = torch.tensor(float("nan"))
    for t in THRESHOLDS_DEG:
        # 1e-6 deg of slack: an estimate exactly one 10-deg bin off counts as within 10 deg.
        out[f"acc_{t:g}"] = (deg <= t + 1e-6).double().mean().float() if n else torch.tensor(float("nan"))
    out["num_pairs"] = torch.tensor(n, dtype=torch.long)
    return out


def relative_yaw_error(
    est_yaw: Tensor,
    gt_yaw: Tensor,
    categories: Tensor,
    clusters: Tensor,
    symmetry_order: Sequence[int],
    max_pairs_per_group: int = 5000,
    seed: int = 0,
    order: int = 1,
) -> dict[str, Tensor]:
    """Summary of :func:`relative_yaw_errors` (same arguments): median error in degrees, accuracy within
    :data:`THRESHOLDS_DEG`, pairs.

    Returns:
        ``{"median_deg": float32 scalar, "acc_10": float32, "acc_20": float32, "num_pairs": int64}``;
        ``median_deg`` and the accuracies are ``nan`` without pairs. The median of an even count averages the two
        middle values.
    """
    return _summary(relative_yaw_errors(est_yaw, gt_yaw, categories, clusters, symmetry_order, max_pairs_per_group,
                                        seed, order))


class RelativeYawError(Metric):
    """Relative yaw error of same-prototype, same-category object pairs over all objects seen.

    Stores every object's estimated yaw, GT yaw, category and prototype id (list states,
    ``dist_reduce_fx="cat"``); pairs are formed in ``compute()`` over everything gathered, so pairs across
    batches and across DDP processes are counted.

    Args:
        symmetry_order: per category: 1 asymmetric, ``n >= 2`` n-fold, 0 continuous (``DatasetIndex.
            symmetry_order``).
        max_pairs_per_group: cap on the pairs of one (prototype, category) group.
        seed: seed of the pair sampling of capped groups.
        **kwargs: passed to :class:`torchmetrics.Metric`.

    Convention: ``update(est_yaw [N] float, gt_yaw [N] float, categories [N] long, clusters [N] long)``, yaws in
    radians counter-clockwise about +z; see :func:`relative_yaw_errors` for the sign convention.
    ``compute()`` returns the dict of :func:`relative_yaw_error` (log it with ``log_dict``, not ``log``).
    The result does not depend on the order of objects; each object must be fed exactly once.
    """

    is_differentiable = False
    higher_is_better = None
    full_state_update = False

    est_yaw: list[Tensor]
    gt_yaw: list[Tensor]
    categories: list[Tensor]
    clusters: list[Tensor]

    def __init__(
        self,
        symmetry_order: Sequence[int],
        max_pairs_per_group: int = 5000,
        seed: int = 0,
        **kwargs: Any,
    ) -> None:
        super().__init__(**kwargs)
        _check_options(symmetry_order, max_pairs_per_group)
        self.symmetry_order = [int(o) for o in symmetry_order]
        self.max_pairs_per_group = max_pairs_per_group
        self.seed = seed
        for name in ("est_yaw", "gt_yaw", "categories", "clusters"):
            self.add_state(name, default=[], dist_reduce_fx="cat")

    def update(self, est_yaw: Tensor, gt_yaw: Tensor, categories: Tensor, clusters: Tensor) -> None:
        """Add a batch of objects.

        Args:
            est_yaw: ``[N]`` estimated (alignment) yaw in radians.
            gt_yaw: ``[N]`` ground-truth yaw in radians, in the frame the crops were cut in.
            categories: ``[N]`` true category ids in ``[0, len(symmetry_order))``.
            clusters: ``[N]`` prototype ids (``>= 0``).
        """
        _check_inputs(est_yaw, gt_yaw, categories, clusters, len(self.symmetry_order))
        self.est_yaw.append(est_yaw.detach().double())
        self.gt_yaw.append(gt_yaw.detach().double())
        self.categories.append(categories.detach().long())
        self.clusters.append(clusters.detach().long())

    def compute(self) -> dict[str, Tensor]:
        """``{"median_deg", "acc_<t>" per threshold, "num_pairs"}`` over all objects seen."""
        if isinstance(self.est_yaw, list) and not self.est_yaw:
            return _summary(torch.zeros(0, dtype=torch.float64))
        errors = relative_yaw_errors(
            dim_zero_cat(self.est_yaw), dim_zero_cat(self.gt_yaw), dim_zero_cat(self.categories),
            dim_zero_cat(self.clusters), self.symmetry_order, self.max_pairs_per_group, self.seed,
        )
        return _summary(errors)
