"""Where a set of boxes loses IoU: per GT object, whether it is found at each IoU and how the best box misses it.

:func:`localisation_errors` describes one scene's GT boxes against predicted boxes (found at each IoU threshold by
the one-to-one matching of :func:`~threedq.metrics.detection.assign_detections`, best IoU, and the best box's centre
and size errors); :func:`by_size_band` pools many scenes into a table per object size band.

Convention: boxes axis-aligned ``(xmin, ymin, zmin, xmax, ymax, zmax)``, metres, z up; size errors are
``log(predicted / true extent)`` per axis; a band is the GT box's largest extent.
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
                        iou_thresholds: Sequence[float] = (0.25, 0.5)) -> dict[str, np.ndarray]:  # fmt: skip
    """How the boxes ``[P, 6]`` (scores ``[P]``) of one scene find its GT boxes ``[G, 6]``.

    Returns per GT box: ``extent`` ``[G, 3]``; ``best_iou`` ``[G]`` (0 with no overlapping box); ``found`` ``[G, T]``
    bool (taken by a box at each of ``iou_thresholds``); for the box of best IoU (NaN where none overlaps):
    ``centre_error_xy`` ``[G]``, ``centre_error_z`` ``[G]`` (predicted minus true), ``log_size_ratio`` ``[G, 3]``.
    ``ValueError`` on bad shapes or boxes.
    """
    pred, scores, gt = (torch.as_tensor(x, dtype=torch.float64) for x in (pred_boxes, pred_scores, gt_boxes))
    for name, t, shape in (("pred_boxes", pred, "[P, 6]"), ("gt_boxes", gt, "[G, 6]")):
        if t.ndim != 2 or t.shape[1] != 6:
            raise ValueError(f"{name}: expected {shape} boxes, got shape {tuple(t.shape)}")
    if scores.shape != (pred.shape[0],):
        raise ValueError(f"pred_scores: expected [{pred.shape[0]}] scores, got shape {tuple(scores.shape)}")
    G, T = gt.shape[0], len(iou_thresholds)
    extent = (gt[:, 3:] - gt[:, :3]).numpy()
    found = np.zeros((G, T), dtype=bool)
    out = {"extent": extent, "best_iou": np.zeros(G), "found": found, "centre_error_xy": np.full(G, np.nan)}
    out |= {"centre_error_z": np.full(G, np.nan), "log_size_ratio": np.full((G, 3), np.nan)}
    if G == 0 or pred.shape[0] == 0:
        return out
    for t, thr in enumerate(iou_thresholds):
        taken = assign_detections(pred, scores, gt, thr).numpy()
        found[taken[taken >= 0], t] = True
    iou = aabb_iou_3d(pred, gt).numpy()  # [P, G]
    best = iou.argmax(axis=0)
    out["best_iou"] = iou[best, np.arange(G)]
    hit = out["best_iou"] > 0
    b, g = pred.numpy()[best], gt.numpy()
    dc = (b[:, :3] + b[:, 3:]) / 2 - (g[:, :3] + g[:, 3:]) / 2
    out["centre_error_xy"] = np.where(hit, np.hypot(dc[:, 0], dc[:, 1]), np.nan)
    out["centre_error_z"] = np.where(hit, dc[:, 2], np.nan)
    with np.errstate(divide="ignore", invalid="ignore"):
        ratio = np.log((b[:, 3:] - b[:, :3]) / extent)
    out["log_size_ratio"] = np.where(hit[:, None], ratio, np.nan)
    return out


def by_size_band(
    per_scene: Sequence[dict[str, np.ndarray]], iou_thresholds: Sequence[float] = (0.25, 0.5),
    bands: Sequence[float] = SIZE_BANDS, flat_height: float | None = None,
) -> list[dict[str, Any]]:  # fmt: skip
    """Pool :func:`localisation_errors` of many scenes into one row per size band (and a last row, all objects).

    ``flat_height``: also a row, before the last, of the objects less tall than this (whatever their largest extent).

    Returns:
        rows ``{"band": "0.10-0.20 m" | "all", "objects", "found_25", "found_50", ... (share of the band's objects
        found at each threshold), "median_best_iou", "median_centre_error_xy", "median_centre_error_z" (signed),
        "median_abs_log_size_ratio": [x, y, z]}`` (medians over the objects some box overlaps; NaN when none).
    """
    if not per_scene:
        per_scene = [localisation_errors(torch.zeros(0, 6), torch.zeros(0), torch.zeros(0, 6), iou_thresholds)]
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
        for key, sel in (("best_iou", m), ("centre_error_xy", hit), ("centre_error_z", hit)):
            row[f"median_{key}"] = median(cat[key][sel])
        ratio = np.abs(cat["log_size_ratio"][hit])
        row["median_abs_log_size_ratio"] = [median(ratio[:, a]) for a in range(3)]
        rows.append(row)
    return rows
