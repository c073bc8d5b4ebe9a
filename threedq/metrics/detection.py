"""3D object detection mean average precision (axis-aligned boxes, IoU thresholds such as 0.25 and 0.5).

A detection is a true positive when it is matched to a ground-truth (GT) box of its frame with IoU at least
the threshold (:func:`match_detections`); every GT box takes at most one detection. Average precision (AP) is
the area under the precision-recall curve with the precision made monotone (VOC all-point interpolation,
:func:`average_precision`).

AP is a dataset-level number: the detections of all frames are ranked together by score, and recall is taken
over all GT boxes of the dataset. The original authors averaged a per-frame AP over frames instead, which is
wrong: it weighs a frame with one object as much as a frame with twenty, lets a frame without GT boxes
either be skipped or count arbitrarily, and ignores how scores compare across frames (a confident false
positive in one frame does not rank above the true positives of another). :class:`DetectionMAP` computes the
dataset-level number.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np
import torch
from torch import Tensor
from torchmetrics import Metric
from torchmetrics.utilities import dim_zero_cat

from threedq.boxes import _check_aabb_rows, aabb_iou_3d

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
    """VOC all-point interpolated average precision of a ranked list of detections.

    Detections are ranked by descending score; at each rank ``recall = TP / num_gt`` and
    ``precision = TP / (TP + FP)``. The precision envelope ``p_interp(r) = max_{r' >= r} precision(r')`` is
    integrated over recall in ``[0, 1]``, summing rectangles where recall changes (precision 0 beyond the
    largest recall reached). GT boxes never detected lower the reachable recall.

    Args:
        scores: ``[D]`` real detection scores (any frames, already pooled).
        is_true_positive: ``[D]`` bool (or 0/1) flags, e.g. from :func:`match_detections`.
        num_gt: number of GT boxes the detections compete for (``>=`` the number of true positives).

    Returns:
        AP in ``[0, 1]`` as a Python float; ``nan`` when ``num_gt == 0`` (undefined: there is no recall).
        ``0.0`` when ``num_gt > 0`` and there is no detection.

    Raises:
        ValueError: on shapes that differ or are not 1-D, non-finite scores, flags other than 0/1, a negative
            ``num_gt``, or more true positives than ``num_gt``.

    Convention: detections of equal score enter the curve together (one PR point per distinct score), so the
    result does not depend on their order; with distinct scores this is exactly the PASCAL VOC 2010+
    all-point AP.
    """
    _check_scores(scores, "scores")
    _check_scores(is_true_positive.to(torch.float64) if isinstance(is_true_positive, Tensor) else is_true_positive,
                  "is_true_positive", scores.shape[0])
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
    tp = np.cumsum(flags)
    fp = np.cumsum(1.0 - flags)
    last_of_tie = np.append(s[1:] != s[:-1], True)  # one PR point after each run of equal scores
    tp, fp = tp[last_of_tie], fp[last_of_tie]
    recall = np.concatenate([[0.0], tp / num_gt, [1.0]])
    precision = np.concatenate([[0.0], tp / (tp + fp), [0.0]])
    precision = np.maximum.accumulate(precision[::-1])[::-1]  # envelope: max precision at recall >= r
    step = np.nonzero(recall[1:] != recall[:-1])[0]
    return float(np.sum((recall[step + 1] - recall[step]) * precision[step + 1]))


def match_detections(pred_boxes: Tensor, pred_scores: Tensor, gt_boxes: Tensor, iou_threshold: float) -> Tensor:
    """True-positive flags of one frame's detections: ``assign_detections(...) >= 0``.

    See :func:`assign_detections` for the matching rule and the arguments.

    Returns:
        ``[P]`` bool true-positive flags, in the input order of the detections.
    """
    return assign_detections(pred_boxes, pred_scores, gt_boxes, iou_threshold) >= 0


def assign_detections(pred_boxes: Tensor, pred_scores: Tensor, gt_boxes: Tensor, iou_threshold: float) -> Tensor:
    """Greedy one-to-one matching of one frame's detections to its GT boxes (the one matching rule of threedq).

    Used by the mAP (:func:`match_detections`) and by the DataModules that turn detections into objects
    (``threedq.datamodules.scene_folder.detections_as_objects``).

    Detections are visited by descending score; each takes, among the GT boxes not yet taken, the one with
    the highest IoU (:func:`threedq.boxes.aabb_iou_3d`), if that IoU is ``>= iou_threshold``, and is then a
    true positive; otherwise it is a false positive. A second detection of an already taken object is thus a
    false positive unless another free GT box overlaps it enough.

    Args:
        pred_boxes: ``[P, 6]`` detections ``(xmin, ymin, zmin, xmax, ymax, zmax)``.
        pred_scores: ``[P]`` real scores, higher is more confident.
        gt_boxes: ``[G, 6]`` GT boxes, same layout and frame.
        iou_threshold: in ``(0, 1]``.

    Returns:
        ``[P]`` long: the index of the GT box each detection took, or -1 (a false positive), in the input
        order of the detections.

    Raises:
        ValueError: on bad shapes or boxes (see :func:`threedq.boxes.aabb_iou_3d`), non-finite scores, or a
            threshold outside ``(0, 1]``.

    Convention: greedy by score, best free GT (COCO-style). The PASCAL VOC devkit differs slightly: it takes
    the best GT among all of them and counts the detection as false positive if that one is already taken.
    Equal scores are visited in index order, equal IoUs go to the lower GT index.
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


def _threshold_key(t: float) -> str:
    return f"map_{t * 100:g}"


def _check_frame_list(items: Any, name: str, keys: tuple[str, ...]) -> None:
    if isinstance(items, Mapping) or not isinstance(items, Sequence):
        raise TypeError(f"{name} must be a list of dicts, one per frame, got {type(items).__name__}")
    for i, d in enumerate(items):
        if not isinstance(d, Mapping):
            raise TypeError(f"{name}[{i}] must be a dict, got {type(d).__name__}")
        for k in keys:
            if k not in d:
                raise ValueError(f"{name}[{i}] lacks the key {k!r} (needs {list(keys)})")


class DetectionMAP(Metric):
    """Dataset-level 3D detection mAP of axis-aligned boxes at several IoU thresholds.

    All detections of all frames (and, under DDP, all processes) are ranked together and recall is over all
    GT boxes seen; this is NOT the mean of per-frame APs that the original authors computed (that average is
    wrong: it weighs frames instead of objects and never compares scores across frames).

    At ``update`` each frame is matched (:func:`match_detections`) once per threshold, class-agnostic; the states
    are the per-detection scores and true-positive flags (``[P, T]`` flattened row-major; ``dist_reduce_fx="cat"``)
    and the GT count (``"sum"``). ``compute`` sorts globally and calls
    :func:`average_precision`. The list states are 1-D and of the metric's float dtype (float32 unless
    changed with ``set_dtype(torch.float64)``; scores are thus rounded to float32 by default), like the empty
    tensor torchmetrics substitutes on a process that saw no frame, so the all-gather never mixes dtypes or
    ranks.

    Args:
        iou_thresholds: IoU thresholds in ``(0, 1]``; result keys are ``map_<100 t>`` (``0.25`` -> ``map_25``).
        **kwargs: passed to :class:`torchmetrics.Metric`.

    Convention: ``update(preds, targets)`` with one entry per frame/scene, ``preds[i] = {"boxes": [P, 6],
    "scores": [P]}`` and ``targets[i] = {"boxes": [G, 6]}`` in one world frame per entry, boxes
    ``(xmin, ymin, zmin, xmax, ymax, zmax)``. ``compute()`` returns ``{"map_25": ..., "map_50": ...,
    "num_gt": ..., "num_det": ...}`` (APs as float32 scalars, ``nan`` without GT boxes; counts int64). Each
    frame must be fed exactly once over all processes.
    """

    is_differentiable = False
    higher_is_better = True
    full_state_update = False
    plot_lower_bound = 0.0
    plot_upper_bound = 1.0

    det_scores: list[Tensor]
    det_tp: list[Tensor]
    num_gt: Tensor

    def __init__(self, iou_thresholds: Sequence[float] = (0.25, 0.5), **kwargs: Any) -> None:
        super().__init__(**kwargs)
        if isinstance(iou_thresholds, (str, bytes)) or not isinstance(iou_thresholds, Sequence) or not iou_thresholds:
            raise ValueError(f"iou_thresholds must be a non-empty sequence of numbers, got {iou_thresholds!r}")
        self.iou_thresholds = tuple(_check_threshold(t, "iou_thresholds entries") for t in iou_thresholds)
        self.keys = tuple(_threshold_key(t) for t in self.iou_thresholds)
        if len(set(self.keys)) != len(self.keys):
            raise ValueError(f"iou_thresholds must be distinct, got {list(iou_thresholds)}")
        self.add_state("det_scores", default=[], dist_reduce_fx="cat")
        self.add_state("det_tp", default=[], dist_reduce_fx="cat")
        self.add_state("num_gt", default=torch.tensor(0, dtype=torch.long), dist_reduce_fx="sum")

    def update(self, preds: Sequence[Mapping[str, Tensor]], targets: Sequence[Mapping[str, Tensor]]) -> None:
        """Add frames.

        Args:
            preds: one dict per frame: ``"boxes"`` ``[P, 6]``, ``"scores"`` ``[P]``.
            targets: one dict per frame, same length and order: ``"boxes"`` ``[G, 6]``.

        Raises:
            TypeError: if ``preds`` / ``targets`` are not lists of dicts.
            ValueError: on a missing key, lists of different lengths, or a bad tensor (the message names it,
                e.g. ``preds[3]['boxes']``). Every frame is checked before any is added.
        """
        _check_frame_list(preds, "preds", ("boxes", "scores"))
        _check_frame_list(targets, "targets", ("boxes",))
        if len(preds) != len(targets):
            raise ValueError(f"preds and targets must have one entry per frame each, got {len(preds)} and {len(targets)}")
        # Validate every frame before touching the state, so a bad batch leaves the metric unchanged.
        frames = []
        for i, (p, t) in enumerate(zip(preds, targets)):
            boxes, scores, gt = p["boxes"], p["scores"], t["boxes"]
            _check_aabb_rows(boxes, f"preds[{i}]['boxes']")
            _check_scores(scores, f"preds[{i}]['scores']", boxes.shape[0])
            _check_aabb_rows(gt, f"targets[{i}]['boxes']")
            frames.append((boxes.detach(), scores.detach(), gt.detach()))
        dev = self.num_gt.device
        for boxes, scores, gt in frames:
            tp = torch.zeros(boxes.shape[0], len(self.iou_thresholds), dtype=torch.bool, device=boxes.device)
            if boxes.shape[0]:
                for k, thr in enumerate(self.iou_thresholds):
                    tp[:, k] = match_detections(boxes, scores, gt, thr)
            # 1-D states of the metric's dtype: see the class docstring (DDP gather of a process without data).
            self.det_scores.append(scores.to(dev, self.dtype))
            self.det_tp.append(tp.reshape(-1).to(dev, self.dtype))
            self.num_gt += gt.shape[0]

    def compute(self) -> dict[str, Tensor]:
        """``{"map_<t>" per threshold, "num_gt", "num_det"}`` over all frames seen."""
        dev = self.num_gt.device
        nt = len(self.iou_thresholds)

        def cat(state: list[Tensor] | Tensor) -> Tensor:
            if isinstance(state, list) and not state:
                return torch.zeros(0, dtype=torch.float64)
            return dim_zero_cat(state).cpu().to(torch.float64)

        scores, tp = cat(self.det_scores), cat(self.det_tp).reshape(-1, nt).round().to(torch.bool)
        num_gt = int(self.num_gt)
        out: dict[str, Tensor] = {}
        for k, key in enumerate(self.keys):
            ap = average_precision(scores, tp[:, k], num_gt)
            out[key] = torch.tensor(ap, dtype=torch.float32, device=dev)
        out["num_gt"] = torch.tensor(num_gt, dtype=torch.long, device=dev)
        out["num_det"] = torch.tensor(scores.shape[0], dtype=torch.long, device=dev)
        return out
