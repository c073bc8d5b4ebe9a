"""Detected boxes refined against what the detector's own input views observe: :func:`observed_boxes` (their
label-free pseudo-boxes, cached per process), :func:`refine_boxes` (each detection snapped onto the observed box it
overlaps most) and :func:`add_flat_boxes` (observed boxes too flat for the detector).

Convention: world (= the DataModules' reference frame R) in metres, z up; boxes axis-aligned
``(xmin, ymin, zmin, xmax, ymax, zmax)``; ``world_T_cam`` camera-to-world, OpenCV camera axes; depth is camera
z-depth, 0 = invalid.
"""

from __future__ import annotations

import hashlib
from collections import OrderedDict
from dataclasses import asdict
from typing import Any

import numpy as np
import torch
from torch import Tensor

from threedq.boxes import aabb_iou_3d, nms_3d
from threedq.proposals import ProposalParams, propose_boxes
from threedq.scene import SceneRecord

__all__ = ["OBSERVED_PARAMS", "add_flat_boxes", "observed_boxes", "refine_boxes"]

#: The pseudo-box parameters of the views a detector sees: every view used, a voxel seen by one view counted, the
#: ground margin measured from the ground's own spread in the depth maps.
OBSERVED_PARAMS = ProposalParams(view_stride=1, min_views=1, ground_margin=None, min_height=None)

_CACHE: OrderedDict[bytes, tuple[np.ndarray, np.ndarray]] = OrderedDict()
_CACHE_SIZE = 20000  # sets of views (about 100 bytes each)


def _as_numpy(x: Any, dtype: Any) -> np.ndarray:
    if isinstance(x, Tensor):
        x = x.detach().to("cpu", torch.float64 if dtype == np.float64 else torch.float32).numpy()
    return np.ascontiguousarray(x, dtype=dtype)


def observed_boxes(depth: Any, K: Any, world_T_cam: Any, bounds: Any = None,
                   params: ProposalParams = OBSERVED_PARAMS) -> tuple[np.ndarray, np.ndarray]:  # fmt: skip
    """The label-free pseudo-boxes of a set of views (:func:`~threedq.proposals.propose_boxes` of only these views).

    Args:
        depth: ``[V, H, W]`` metres, 0 = invalid (array or tensor). K: ``[V, 3, 3]``. world_T_cam: ``[V, 4, 4]``.
        bounds: scene bounds (points outside are ignored) or ``None``. params: the pseudo-box parameters.

    Returns ``aabb [P, 6]`` float32 and ``scores [P]`` float32 (by decreasing score), cached per process;
    ``ValueError`` naming the field for malformed views (NaN depth, wrong shapes) or bounds.
    """
    d, k, t = (_as_numpy(a, np.float32) for a in (depth, K, world_T_cam))
    b = None if bounds is None else np.asarray(bounds, dtype=np.float64).reshape(2, 3)
    h = hashlib.blake2b(digest_size=20)
    for a in (d, k, t, np.asarray(d.shape), np.zeros(0) if b is None else b):
        h.update(a.tobytes())
    h.update(repr(sorted(asdict(params).items())).encode())
    key = h.digest()
    if key in _CACHE:
        _CACHE.move_to_end(key)
        return _CACHE[key]
    no_boxes, no_categories = np.zeros((0, 7), np.float32), np.zeros((0,), np.int64)
    record = SceneRecord(None, d, k, t, no_boxes, no_categories)  # type: ignore[arg-type]
    out = propose_boxes(record, bounds=None if b is None else (b[0], b[1]), **asdict(params))
    _CACHE[key] = out
    if len(_CACHE) > _CACHE_SIZE:
        _CACHE.popitem(last=False)
    return out


def refine_boxes(boxes: Tensor, scores: Tensor, observed: Tensor, min_iou: float, nms_iou: float,
                 nms_iomin: float = 1.0) -> tuple[Tensor, Tensor, Tensor]:  # fmt: skip
    """Each detection replaced by the observed box it overlaps most (IoU >= ``min_iou``), then 3D NMS again.

    Args:
        boxes: ``[N, 6]`` detections; scores: ``[N]``. observed: ``[P, 6]`` observed boxes (:func:`observed_boxes`).
        min_iou: in ``(0, 1]``. nms_iou, nms_iomin: the suppression after snapping (:func:`~threedq.boxes.nms_3d`).

    Returns ``boxes [K, 6]``, ``scores [K]`` (descending) and ``snapped [K]`` bool (the box is an observed one);
    ``ValueError`` for ``min_iou`` outside ``(0, 1]`` or bad shapes.
    """
    if not 0.0 < min_iou <= 1.0:
        raise ValueError(f"min_iou: expected in (0, 1], got {min_iou}")
    if boxes.ndim != 2 or boxes.shape[-1] != 6 or scores.shape != boxes.shape[:1]:
        raise ValueError(f"boxes/scores: expected [N, 6] and [N], got {list(boxes.shape)} and {list(scores.shape)}")
    obs = torch.as_tensor(observed).to(boxes).reshape(-1, 6)
    snapped = torch.zeros(boxes.shape[0], dtype=torch.bool, device=boxes.device)
    out = boxes
    if boxes.shape[0] and obs.shape[0]:
        best, j = aabb_iou_3d(boxes, obs).max(1)
        snapped = best >= min_iou
        out = torch.where(snapped[:, None], obs[j], boxes)
    keep = nms_3d(out, scores, nms_iou, nms_iomin)
    return out[keep], scores[keep], snapped[keep]


def add_flat_boxes(boxes: Tensor, scores: Tensor, observed: Tensor, observed_scores: Tensor, max_height: float,
                   score_scale: float, min_score: float, overlap_iou: float) -> tuple[Tensor, Tensor]:  # fmt: skip
    """Detections ``boxes`` ``[N, 6]`` (``scores`` ``[N]``) plus each ``observed`` box ``[P, 6]`` less tall than
    ``max_height`` (metres) that overlaps no detection at IoU ``overlap_iou`` or more, scored ``score_scale *
    observed_scores`` (``[P]``, in (0, 1]) when that reaches ``min_score``.

    Returns:
        ``boxes [K, 6]`` and ``scores [K]``, sorted by decreasing score (detections and added flat boxes).

    Raises:
        ValueError: for bad shapes, a negative ``max_height`` or ``score_scale`` outside ``[0, 1]``.
    """
    if boxes.ndim != 2 or boxes.shape[-1] != 6 or scores.shape != boxes.shape[:1]:
        raise ValueError(f"boxes/scores: expected [N, 6] and [N], got {list(boxes.shape)} and {list(scores.shape)}")
    obs = torch.as_tensor(observed).to(boxes).reshape(-1, 6)
    obs_s = torch.as_tensor(observed_scores).to(scores).reshape(-1)
    if obs_s.shape[0] != obs.shape[0]:
        raise ValueError(f"observed_scores: expected [{obs.shape[0]}], got {list(obs_s.shape)}")
    if not max_height >= 0 or not 0.0 <= score_scale <= 1.0:
        raise ValueError(f"max_height >= 0 and score_scale in [0, 1] expected, got {max_height}, {score_scale}")
    flat = (obs[:, 5] - obs[:, 2]) < max_height
    flat &= obs_s * score_scale >= min_score
    if flat.any() and boxes.shape[0]:
        flat &= aabb_iou_3d(obs, boxes).max(1).values < overlap_iou
    if not flat.any():
        return boxes, scores
    b = torch.cat([boxes, obs[flat]])
    s = torch.cat([scores, obs_s[flat] * score_scale])
    order = torch.argsort(s, descending=True, stable=True)
    return b[order], s[order]
