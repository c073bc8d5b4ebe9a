"""Relative yaw error of objects assigned to the same prototype (a prototype's canonical pose is arbitrary).

``y_o`` is the yaw that, applied to object ``o``'s crop with :func:`threedq.geometry.rotate_yaw` (counter-clockwise
about +z seen from above), aligns it with its prototype; with ``g_o`` its true yaw, a pair's error is::

    error(o, p) = | wrap( -(y_o - y_p) - (g_o - g_p) ) | = | wrap( (y_p + g_p) - (y_o + g_o) ) |   in [0, pi]
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any

import torch
from torch import Tensor
from torchmetrics import Metric
from torchmetrics.utilities import dim_zero_cat

from threedq.metrics.clustering import _check_positive

__all__ = ["RelativeYawError", "relative_yaw_error", "relative_yaw_errors"]

#: accuracy thresholds of the summary, degrees (inclusive)
THRESHOLDS_DEG = (10.0, 20.0)


def _check_options(symmetry_order: Sequence[int], max_pairs_per_group: int) -> None:
    if isinstance(symmetry_order, (str, bytes)) or not isinstance(symmetry_order, Sequence):
        raise TypeError(f"symmetry_order must be a sequence of ints, one per category, got {symmetry_order!r}")
    for o in symmetry_order:
        if not isinstance(o, int) or isinstance(o, bool) or o < 0:
            raise ValueError(f"symmetry_order entries must be ints >= 0 (0 = continuous), got {list(symmetry_order)}")
    _check_positive(max_pairs_per_group=max_pairs_per_group)


def _check_inputs(est_yaw: Tensor, gt_yaw: Tensor, categories: Tensor, clusters: Tensor, num_categories: int) -> None:
    tensors = {"est_yaw": est_yaw, "gt_yaw": gt_yaw, "categories": categories, "clusters": clusters}
    for name, t in tensors.items():
        if not isinstance(t, Tensor) or t.ndim != 1:
            shape = tuple(t.shape) if isinstance(t, Tensor) else type(t).__name__
            raise ValueError(f"{name} must be a 1-D tensor [N], got {shape}")
    n = est_yaw.shape[0]
    if any(t.shape[0] != n for t in tensors.values()):
        raise ValueError(f"inputs must have one length N, got { {k: t.shape[0] for k, t in tensors.items()} }")
    for name, t in (("est_yaw", est_yaw), ("gt_yaw", gt_yaw)):
        if not t.is_floating_point():
            raise ValueError(f"{name} must be a floating-point tensor of radians, got {t.dtype}")
        if not bool(torch.isfinite(t).all()):
            raise ValueError(f"{name} must be finite")
    for name, t in (("categories", categories), ("clusters", clusters)):
        if t.is_floating_point() or t.is_complex() or t.dtype == torch.bool:
            raise ValueError(f"{name} must be an integer tensor, got {t.dtype}")
    if n and (int(categories.min()) < 0 or int(categories.max()) >= num_categories):
        got = f"got values in [{int(categories.min())}, {int(categories.max())}]"
        raise ValueError(f"categories must lie in [0, {num_categories}) (one symmetry_order entry each), {got}")
    if n and int(clusters.min()) < 0:
        raise ValueError(f"clusters must be >= 0, got {int(clusters.min())}")


def relative_yaw_errors(est_yaw: Tensor, gt_yaw: Tensor, categories: Tensor, clusters: Tensor,
                        symmetry_order: Sequence[int], max_pairs_per_group: int = 5000, seed: int = 0,
                        order: int = 1) -> Tensor:  # fmt: skip
    """Relative yaw error of every pair of same-prototype objects of a category of symmetry order ``order``, modulo
    its period ``2 pi / order``.

    A (prototype, category) group of ``m`` objects gives its ``m (m - 1) / 2`` pairs, or ``max_pairs_per_group``
    pairs drawn uniformly with replacement (generator seeded with ``seed``); the result does not depend on the order
    of the objects.

    Args:
        est_yaw, gt_yaw: ``[N]`` estimated (alignment) yaw ``y_o`` and true yaw ``g_o``, radians, crop frame (z up).
        categories: ``[N]`` true category ids in ``[0, len(symmetry_order))``. clusters: ``[N]`` prototype ids.
        symmetry_order: per category, how many yaws in ``[0, 2 pi)`` map the shape onto itself (0 = continuous).

    Returns ``[P]`` float64 errors in radians, in ``[0, pi / order]``; ``ValueError`` on malformed inputs or options.
    """
    _check_options(symmetry_order, max_pairs_per_group)
    _check_inputs(est_yaw, gt_yaw, categories, clusters, len(symmetry_order))
    if isinstance(order, bool) or not isinstance(order, int) or order < 1:
        raise ValueError(f"order must be an int >= 1 (a continuous symmetry has no yaw to score), got {order!r}")
    residual = est_yaw.detach().cpu().double() + gt_yaw.detach().cpu().double()  # constant within a perfect group
    cats, clus = categories.detach().cpu().long(), clusters.detach().cpu().long()
    keep = torch.tensor(list(symmetry_order), dtype=torch.long)[cats] == order
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
    period = 2 * math.pi / order
    for r in torch.split(residual, counts.tolist()):
        m = r.numel()
        if m < 2:
            continue
        if m * (m - 1) // 2 <= max_pairs_per_group:
            i, j = torch.triu_indices(m, m, offset=1)
        else:
            i = torch.randint(m, (max_pairs_per_group,), generator=gen)
            j = torch.randint(m - 1, (max_pairs_per_group,), generator=gen)
            j = j + (j >= i).long()  # uniform over j != i
        wrapped = torch.remainder(r[j] - r[i], period)
        errors.append(torch.minimum(wrapped, period - wrapped))  # |diff| on the circle, in [0, period / 2]
    return torch.cat(errors) if errors else torch.zeros(0, dtype=torch.float64)


def _summary(errors: Tensor) -> dict[str, Tensor]:
    deg = torch.rad2deg(errors)
    n, s = deg.numel(), torch.sort(deg).values
    median = (s[n // 2] if n % 2 else 0.5 * (s[n // 2 - 1] + s[n // 2])).float() if n else torch.tensor(float("nan"))
    out: dict[str, Tensor] = {"median_deg": median}
    for t in THRESHOLDS_DEG:
        # 1e-6 deg of slack: an estimate exactly one 10-deg bin off counts as within 10 deg.
        out[f"acc_{t:g}"] = (deg <= t + 1e-6).double().mean().float() if n else torch.tensor(float("nan"))
    out["num_pairs"] = torch.tensor(n, dtype=torch.long)
    return out


def relative_yaw_error(est_yaw: Tensor, gt_yaw: Tensor, categories: Tensor, clusters: Tensor,
                       symmetry_order: Sequence[int], max_pairs_per_group: int = 5000, seed: int = 0,
                       order: int = 1) -> dict[str, Tensor]:  # fmt: skip
    """Summary of :func:`relative_yaw_errors` (same arguments).

    Returns:
        ``{"median_deg": float32 scalar, "acc_10": float32, "acc_20": float32, "num_pairs": int64}`` (accuracy within
        :data:`THRESHOLDS_DEG`); ``nan`` without pairs. The median of an even count averages the two middle values.
    """
    args = (max_pairs_per_group, seed, order)
    return _summary(relative_yaw_errors(est_yaw, gt_yaw, categories, clusters, symmetry_order, *args))


class RelativeYawError(Metric):
    """Relative yaw error of same-prototype, same-category object pairs (order 1) over all objects seen: list states
    (``"cat"``) of every object's yaws, category and prototype; ``compute()`` returns :func:`relative_yaw_error`.

    Convention: ``update(est_yaw [N] float, gt_yaw [N] float, categories [N] long, clusters [N] long)`` as
    :func:`relative_yaw_errors`; each object must be fed exactly once.
    """

    is_differentiable = False
    higher_is_better = None
    full_state_update = False

    est_yaw: list[Tensor]
    gt_yaw: list[Tensor]
    categories: list[Tensor]
    clusters: list[Tensor]

    def __init__(self, symmetry_order: Sequence[int], max_pairs_per_group: int = 5000, seed: int = 0,
                 **kwargs: Any) -> None:  # fmt: skip
        super().__init__(**kwargs)
        _check_options(symmetry_order, max_pairs_per_group)
        self.symmetry_order = [int(o) for o in symmetry_order]
        self.max_pairs_per_group, self.seed = max_pairs_per_group, seed
        for name in ("est_yaw", "gt_yaw", "categories", "clusters"):
            self.add_state(name, default=[], dist_reduce_fx="cat")

    def update(self, est_yaw: Tensor, gt_yaw: Tensor, categories: Tensor, clusters: Tensor) -> None:
        """Add a batch of objects (``[N]`` each, as :func:`relative_yaw_errors`)."""
        _check_inputs(est_yaw, gt_yaw, categories, clusters, len(self.symmetry_order))
        self.est_yaw.append(est_yaw.detach().double())
        self.gt_yaw.append(gt_yaw.detach().double())
        self.categories.append(categories.detach().long())
        self.clusters.append(clusters.detach().long())

    def compute(self) -> dict[str, Tensor]:
        """``{"median_deg", "acc_<t>" per threshold, "num_pairs"}`` over all objects seen."""
        if isinstance(self.est_yaw, list) and not self.est_yaw:
            return _summary(torch.zeros(0, dtype=torch.float64))
        states = [dim_zero_cat(t) for t in (self.est_yaw, self.gt_yaw, self.categories, self.clusters)]
        return _summary(relative_yaw_errors(*states, self.symmetry_order, self.max_pairs_per_group, self.seed))
