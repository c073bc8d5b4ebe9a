"""3D object detection mean average precision (axis-aligned boxes, IoU thresholds such as 0.25 and 0.5).

A detection is a true positive when matched one-to-one to a ground-truth (GT) box of its frame with IoU at least the
threshold (:func:`assign_detections`); AP is the area under the precision-recall curve with monotone precision (VOC
all-point interpolation, :func:`average_precision`). AP is dataset-level: the detections of all frames are ranked
together by score and recall is over all GT boxes (:class:`DetectionMAP`), not a mean of per-frame APs.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np
import torch
from torch import Tensor
from torchmetrics.utilities import dim_zero_cat

from threedq.boxes import _check_aabb_rows, aabb_iou_3d
from threedq.metrics.clustering import _UnitMetric

__all__ = ["DetectionMAP", "assign_detections", "average_precision", "match_detections"]


def _check_scores(scores: Tensor, name: str, length: int | None = None) -> None:
    if not isinstance(scores, Tensor) or scores.ndim != 1 or (length is not None and scores.shape[0] != length):
        shape = tuple(scores.shape) if isinstance(scores, Tensor) else type(scores).__name__
        want = f"[{length}]" if length is not None else "[D]"
        raise ValueError(f"{name}: expected a 1-D tensor of shape {want}, got {shape}")
    if scores.dtype == torch.bool or scores.is_complex():
        raise ValueError(f"{name}: expected real-valued scores, got {scores.dtype}")
    if scores.numel() and not bool(torch.isfinite(scores).all()):
        raise ValueError(f"{name}: scores must be finite")


def _check_threshold(value: Any, name: str = "iou_threshold") -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not 0 < value <= 1:
        raise ValueError(f"{name} must be a number in (0, 1], got {value!r}")
    return float(value)


def average_precision(scores: Tensor, is_true_positive: Tensor, num_gt: int) -> float:
    """VOC (2010+) all-point interpolated AP in ``[0, 1]`` of detections ``scores`` ``[D]`` with flags
    ``is_true_positive`` ``[D]`` (bool or 0/1) against ``num_gt`` GT boxes; ``nan`` when ``num_gt == 0``, ``0.0``
    without detections. Equal scores enter the curve together (one PR point per distinct score).

    Raises:
        ValueError: on shapes that differ or are not 1-D, non-finite scores, flags other than 0/1, a negative
            ``num_gt``, or more true positives than ``num_gt``.
    """
    _check_scores(scores, "scores")
    flags_in = is_true_positive.to(torch.float64) if isinstance(is_true_positive, Tensor) else is_true_positive
    _check_scores(flags_in, "is_true_positive", scores.shape[0])
    if isinstance(num_gt, bool) or not isinstance(num_gt, (int, np.integer)) or num_gt < 0:
        raise ValueError(f"num_gt must be an int >= 0, got {num_gt!r}")
    flags = is_true_positive.detach().cpu().to(torch.float64).numpy()
    if not np.isin(flags, (0.0, 1.0)).all():
        raise ValueError("is_true_positive must hold only 0/1 (or bool) flags")
    num_tp = int(flags.sum())
    if num_tp > num_gt:
        raise ValueError(f"is_true_positive has {num_tp} true positives but num_gt is {num_gt}")
    if num_gt == 0:
        return float("nan")
    if flags.size == 0:
        return 0.0
    s = scores.detach().cpu().to(torch.float64).numpy()
    order = np.argsort(-s, kind="stable")
    s, flags = s[order], flags[order]
    last_of_tie = np.append(s[1:] != s[:-1], True)  # one PR point after each run of equal scores
    tp, fp = np.cumsum(flags)[last_of_tie], np.cumsum(1.0 - flags)[last_of_tie]
    recall = np.concatenate([[0.0], tp / num_gt, [1.0]])
    precision = np.concatenate([[0.0], tp / (tp + fp), [0.0]])
    precision = np.maximum.accumulate(precision[::-1])[::-1]  # envelope: max precision at recall >= r
    step = np.nonzero(recall[1:] != recall[:-1])[0]
    return float(np.sum((recall[step + 1] - recall[step]) * precision[step + 1]))


def match_detections(pred_boxes: Tensor, pred_scores: Tensor, gt_boxes: Tensor, iou_threshold: float) -> Tensor:
    """``[P]`` bool true-positive flags of one frame's detections: :func:`assign_detections` ``(...) >= 0``."""
    return assign_detections(pred_boxes, pred_scores, gt_boxes, iou_threshold) >= 0


def assign_detections(pred_boxes: Tensor, pred_scores: Tensor, gt_boxes: Tensor, iou_threshold: float) -> Tensor:
    """Greedy one-to-one matching of one frame's detections to its GT boxes (the one matching rule of threedq).

    Detections are visited by descending score; each takes, among the GT boxes not yet taken, the one of highest IoU
    (:func:`threedq.boxes.aabb_iou_3d`) if that IoU is ``>= iou_threshold`` (a true positive), else none.

    Args:
        pred_boxes: ``[P, 6]`` detections; pred_scores: ``[P]`` real scores. gt_boxes: ``[G, 6]``, same frame.
        iou_threshold: in ``(0, 1]``.

    Returns:
        ``[P]`` long: the GT box each detection took, or -1, in the detections' input order (equal scores visited in
        index order, equal IoUs going to the lower GT index).

    Raises:
        ValueError: on bad shapes or boxes, non-finite scores, or a threshold outside ``(0, 1]``.
    """
    _check_aabb_rows(pred_boxes, "pred_boxes")
    _check_scores(pred_scores, "pred_scores", pred_boxes.shape[0])
    _check_aabb_rows(gt_boxes, "gt_boxes")
    iou_threshold = _check_threshold(iou_threshold)
    num_pred, num_gt = pred_boxes.shape[0], gt_boxes.shape[0]
    match = np.full(num_pred, -1, dtype=np.int64)
    if num_pred and num_gt:
        iou = aabb_iou_3d(pred_boxes.detach(), gt_boxes.detach()).cpu().to(torch.float64).numpy()
        order = torch.sort(pred_scores.detach(), descending=True, stable=True).indices.cpu().numpy()
        free = np.ones(num_gt, dtype=bool)
        for i in order:
            cand = np.where(free, iou[i], -1.0)
            j = int(np.argmax(cand))  # first index among equal maxima
            if cand[j] >= iou_threshold:
                match[i] = j
                free[j] = False
                if not free.any():
                    break
    return torch.as_tensor(match, device=pred_boxes.device)


def _check_frame_list(items: Any, name: str, keys: tuple[str, ...]) -> None:
    if isinstance(items, Mapping) or not isinstance(items, Sequence):
        raise TypeError(f"{name} must be a list of dicts, one per frame, got {type(items).__name__}")
    for i, d in enumerate(items):
        if not isinstance(d, Mapping):
            raise TypeError(f"{name}[{i}] must be a dict, got {type(d).__name__}")
        for k in keys:
            if k not in d:
                raise ValueError(f"{name}[{i}] lacks the key {k!r} (needs {list(keys)})")


class DetectionMAP(_UnitMetric):
    """Dataset-level 3D detection mAP of axis-aligned boxes at ``iou_thresholds`` (keys ``map_<100 t>``).

    Each frame is matched (:func:`match_detections`) once per threshold at ``update``, class-agnostic. States: the
    per-detection scores and flags (``[P, T]`` flattened; ``"cat"``), 1-D in the metric's float dtype (float32 by
    default) so a DDP gather never mixes dtypes or ranks, and the GT count (``"sum"``).

    Convention: ``update(preds, targets)`` with one entry per frame, ``preds[i] = {"boxes": [P, 6], "scores": [P]}``
    and ``targets[i] = {"boxes": [G, 6]}``, boxes ``(xmin, ymin, zmin, xmax, ymax, zmax)`` in one world frame per
    entry. ``compute()`` returns ``{"map_25": ..., "map_50": ..., "num_gt": ..., "num_det": ...}`` (APs float32,
    ``nan`` without GT boxes; counts int64). Each frame must be fed exactly once over all processes.
    """

    det_scores: list[Tensor]
    det_tp: list[Tensor]
    num_gt: Tensor

    def __init__(self, iou_thresholds: Sequence[float] = (0.25, 0.5), **kwargs: Any) -> None:
        super().__init__(**kwargs)
        if isinstance(iou_thresholds, (str, bytes)) or not isinstance(iou_thresholds, Sequence) or not iou_thresholds:
            raise ValueError(f"iou_thresholds must be a non-empty sequence of numbers, got {iou_thresholds!r}")
        self.iou_thresholds = tuple(_check_threshold(t, "iou_thresholds entries") for t in iou_thresholds)
        self.keys = tuple(f"map_{t * 100:g}" for t in self.iou_thresholds)
        if len(set(self.keys)) != len(self.keys):
            raise ValueError(f"iou_thresholds must be distinct, got {list(iou_thresholds)}")
        self.add_state("det_scores", default=[], dist_reduce_fx="cat")
        self.add_state("det_tp", default=[], dist_reduce_fx="cat")
        self.add_state("num_gt", default=torch.tensor(0, dtype=torch.long), dist_reduce_fx="sum")

    def update(self, preds: Sequence[Mapping[str, Tensor]], targets: Sequence[Mapping[str, Tensor]]) -> None:
        """Add frames, each checked first (``TypeError``: not lists of dicts; ``ValueError``: a bad key, length or
        tensor)."""
        _check_frame_list(preds, "preds", ("boxes", "scores"))
        _check_frame_list(targets, "targets", ("boxes",))
        if len(preds) != len(targets):
            n = f"{len(preds)} and {len(targets)}"
            raise ValueError(f"preds and targets must have one entry per frame each, got {n}")
        frames = []
        for i, (p, t) in enumerate(zip(preds, targets)):
            boxes, scores, gt = p["boxes"], p["scores"], t["boxes"]
            _check_aabb_rows(boxes, f"preds[{i}]['boxes']")
            _check_scores(scores, f"preds[{i}]['scores']", boxes.shape[0])
            _check_aabb_rows(gt, f"targets[{i}]['boxes']")
            frames.append((boxes.detach(), scores.detach(), gt.detach()))
        dev = self.num_gt.device
        for boxes, scores, gt in frames:
            tp = torch.stack([match_detections(boxes, scores, gt, thr) for thr in self.iou_thresholds], dim=1)
            self.det_scores.append(scores.to(dev, self.dtype))
            self.det_tp.append(tp.reshape(-1).to(dev, self.dtype))
            self.num_gt += gt.shape[0]

    def compute(self) -> dict[str, Tensor]:
        """``{"map_<t>" per threshold, "num_gt", "num_det"}`` over all frames seen."""
        dev = self.num_gt.device

        def cat(state: list[Tensor] | Tensor) -> Tensor:
            if isinstance(state, list) and not state:
                return torch.zeros(0, dtype=torch.float64)
            return dim_zero_cat(state).cpu().to(torch.float64)

        scores, tp = cat(self.det_scores), cat(self.det_tp).reshape(-1, len(self.iou_thresholds)).round().to(torch.bool)
        num_gt = int(self.num_gt)
        out = {key: torch.tensor(average_precision(scores, tp[:, k], num_gt), dtype=torch.float32, device=dev)
               for k, key in enumerate(self.keys)}
        out["num_gt"] = torch.tensor(num_gt, dtype=torch.long, device=dev)
        out["num_det"] = torch.tensor(scores.shape[0], dtype=torch.long, device=dev)
        return out
