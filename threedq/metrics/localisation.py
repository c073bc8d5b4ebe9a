"""Where a set of boxes loses IoU: per GT object, whether it is found at each IoU and how the best box misses it.

:func:`localisation_errors` describes one scene's GT boxes against a set of predicted boxes (a detector's, the
label-free pseudo-boxes): found or not at each IoU threshold (the one-to-one matching of
:func:`~threedq.metrics.detection.assign_detections`, so "found at 0.5" sums to the recall at 0.5), the best IoU of
any box, and, for the box of best IoU, its centre error (horizontal and vertical) and its size error per axis.
:func:`by_size_band` pools many scenes into a table per object size band.

Convention: boxes axis-aligned ``(xmin, ymin, zmin, xmax, ymax, zmax)``, metres, z up; size errors are
``log(predicted / true extent)`` per axis (0: right size; +0.69: twice as large); a band is the GT box's largest
extent.
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Sequence
from typing import Any

import numpy as np
import torch
from torch import Tensor

from threedq.boxes import aabb_iou_3d
from threedq.metrics.detection import assign_detections

__all__ = ["SIZE_BANDS", "by_size_band", "localisation_errors"]

#: Object size bands, metres of the GT box's largest extent (fixed lengths, not fitted to any dataset).
SIZE_BANDS: tuple[float, ...] = (0.0, 0.1, 0.2, 0.4, math.inf)


def localisation_errors(pred_boxes: Tensor, pred_scores: Tensor, gt_boxes: Tensor,
                        iou_thresholds: Sequence[float] = (0.25, 0.5)) -> dict[str, np.ndarray]:
    """How the boxes of one scene find its GT boxes.

    Args:
        pred_boxes: ``[P, 6]`` boxes; pred_scores: ``[P]`` their scores (the matching visits them by score).
        gt_boxes: ``[G, 6]`` GT boxes.
        iou_thresholds: thresholds at which "found" is reported.

    Returns:
        per GT box (``G`` rows): ``extent`` ``[G, 3]``; ``best_iou`` ``[G]`` (0 with no overlapping box);
        ``found`` ``[G, T]`` bool (taken by a box at each threshold, one box per object); for the box of best IoU
        (NaN where none overlaps): ``centre_error_xy`` ``[G]`` and ``centre_error_z`` ``[G]`` (metres, signed for
        z: predicted minus true), ``log_size_ratio`` ``[G, 3]``.

    Raises:
        ValueError: bad shapes or boxes (as :func:`~threedq.metrics.detection.assign_detections`).
    """
    pred = torch.as_tensor(pred_boxes, dtype=torch.float64)
    scores = torch.as_tensor(pred_scores, dtype=torch.float64)
    gt = torch.as_tensor(gt_boxes, dtype=torch.float64)
    for name, t, shape in (("pred_boxes", pred, "[P, 6]"), ("gt_boxes", gt, "[G, 6]")):
        if t.ndim != 2 or t.shape[1] != 6:
            raise ValueError(f"{name}: expected {shape} boxes, got shape {tuple(t.shape)}")
    if scores.shape != (pred.shape[0],):
        raise ValueError(f"pred_scores: expected [{pred.shape[0]}] scores, got shape {tuple(scores.shape)}")
    G, T = gt.shape[0], len(iou_thresholds)
    extent = (gt[:, 3:] - gt[:, :3]).numpy()
    found = np.zeros((G, T), dtype=bool)
    out = {"extent": extent, "best_iou": np.zeros(G), "found": found, "centre_error_xy": np.full(G, np.nan),
           "centre_error_z": np.full(G, np.nan), "log_size_ratio": np.full((G, 3), np.nan)}
    if G == 0 or pred.shape[0] == 0:
        return out
    for t, thr in enumerate(iou_thresholds):
        taken = assign_detections(pred, scores, gt, thr).numpy()
        found[taken[taken >= 0], t] = True
    iou = aabb_iou_3d(pred, gt).numpy()  # [P, G]
    best = iou.argmax(axis=0)
    out["best_iou"] = iou[best, np.arange(G)]
    hit = out["best_iou"] > 0
    b = pred.numpy()[best]
    g = gt.numpy()
    dc = (b[:, :3] + b[:, 3:]) / 2 - (g[:, :3] + g[:, 3:]) / 2
    out["centre_error_xy"] = np.where(hit, np.hypot(dc[:, 0], dc[:, 1]), np.nan)
    out["centre_error_z"] = np.where(hit, dc[:, 2], np.nan)
    with np.errstate(divide="ignore", invalid="ignore"):
        ratio = np.log((b[:, 3:] - b[:, :3]) / extent)
    out["log_size_ratio"] = np.where(hit[:, None], ratio, np.nan)
    return out


def by_size_band(per_scene: Sequence[dict[str, np.ndarray]], iou_thresholds: Sequence[float] = (0.25, 0.5),
                 bands: Sequence[float] = SIZE_BANDS, flat_height: float | None = None) -> list[dict[str, Any]]:
    """Pool :func:`localisation_errors` of many scenes into one row per size band (and a last row, all objects).

    ``flat_height``: also a row, before the last, of the objects less tall than this (band ``"flat: < H m tall"``,
    whatever their largest extent: a detector's ``min_box_height``, under which it is not trained).

    Returns:
        rows ``{"band": "0.10-0.20 m" | "all", "objects", "found_25", "found_50", ... (share of the band's objects
        found at each threshold), "median_best_iou", "median_centre_error_xy", "median_centre_error_z" (signed),
        "median_abs_log_size_ratio": [x, y, z]}`` (medians over the objects some box overlaps; NaN when none).
    """
    if not per_scene:
        cat = {"extent": np.zeros((0, 3)), "best_iou": np.zeros(0), "found": np.zeros((0, len(iou_thresholds)), bool),
               "centre_error_xy": np.zeros(0), "centre_error_z": np.zeros(0), "log_size_ratio": np.zeros((0, 3))}
    else:
        cat = {k: np.concatenate([s[k] for s in per_scene]) for k in per_scene[0]}
    largest = cat["extent"].max(axis=1) if len(cat["extent"]) else np.zeros(0)
    masks = [(f"{lo:.2f}-{hi:.2f} m" if math.isfinite(hi) else f">= {lo:.2f} m", (largest >= lo) & (largest < hi))
             for lo, hi in itertools.pairwise(bands)]
    rows = []
    if flat_height is not None:
        height = cat["extent"][:, 2] if len(cat["extent"]) else np.zeros(0)
        masks.append((f"flat: < {flat_height:.3f} m tall", height < flat_height))
    for name, m in [*masks, ("all", np.ones(len(largest), bool))]:
        n = int(m.sum())
        hit = m & (cat["best_iou"] > 0)

        def median(x: np.ndarray) -> float:
            return float(np.median(x)) if len(x) else float("nan")

        row: dict[str, Any] = {"band": name, "objects": n}
        for t, thr in enumerate(iou_thresholds):
            row[f"found_{round(thr * 100):02d}"] = float(cat["found"][m, t].mean()) if n else float("nan")
        row["median_best_iou"] = median(cat["best_iou"][m])
        row["median_centre_error_xy"] = median(cat["centre_error_xy"][hit])
        row["median_centre_error_z"] = median(cat["centre_error_z"][hit])
        row["median_abs_log_size_ratio"] = ([float(np.median(np.abs(cat["log_size_ratio"][hit, a]))) for a in range(3)]
                                            if hit.any() else [float("nan")] * 3)
        rows.append(row)
    return rows
