"""Detected boxes refined against what the detector's own input views observe.

A detector box is regressed from a feature cell (16 cm on the packaged grid: the 8 cm feature voxels at stride 2),
while the depth map of the very view the detector looks at says where the object's visible surface and the ground
under it are. :func:`observed_boxes` computes the label-free pseudo-boxes of those views (:mod:`threedq.proposals`
with :data:`OBSERVED_PARAMS`: a voxel seen by one view counts), and :func:`refine_boxes` replaces each detection by
the observed box it overlaps most when that IoU reaches ``min_iou``, keeps the detection's score, and suppresses
again (two detections snapped onto one observed box become one). A detection no observed box supports keeps its
regressed box: the detector still finds what the geometry misses (an object the ground-plane split cuts, a
partly hidden one); the geometry places what the detector finds.

Why (``docs/studies/detector.md``, "Where the detector loses IoU 0.5"): where a detector box meets an object, its
height and centre are the error, which the single-view pseudo-boxes (extended to the fitted ground plane) do not make.

The observed boxes of one set of views are kept in memory per process (keyed by the bytes of the depth maps,
intrinsics and poses and the bounds), so an evaluation that sees the same scenes every round computes them once.

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

#: The pseudo-box parameters of the views a detector sees: the packaged defaults, every view used, a voxel seen
#: by one view counted (the training pseudo-boxes ask for two views of a voxel; one input view cannot give two), and
#: the ground margin measured from the ground's own spread in the depth maps (``ground_margin=None``, at least 5 mm,
#: so that 2-3 cm flat objects keep their height: these boxes are how the detector reports them, see
#: :func:`add_flat_boxes`).
OBSERVED_PARAMS = ProposalParams(view_stride=1, min_views=1, ground_margin=None, min_height=None)

_CACHE: OrderedDict[bytes, tuple[np.ndarray, np.ndarray]] = OrderedDict()
_CACHE_SIZE = 20000  # sets of views (about 100 bytes each)


def _as_numpy(x: Any, dtype: Any) -> np.ndarray:
    if isinstance(x, Tensor):
        x = x.detach().to("cpu", torch.float64 if dtype == np.float64 else torch.float32).numpy()
    return np.ascontiguousarray(x, dtype=dtype)


def observed_boxes(
    depth: Any, K: Any, world_T_cam: Any, bounds: Any = None, params: ProposalParams = OBSERVED_PARAMS
) -> tuple[np.ndarray, np.ndarray]:
    """The label-free pseudo-boxes of a set of views (:func:`~threedq.proposals.propose_boxes` of only these views).

    Args:
        depth: ``[V, H, W]`` metres, 0 = invalid (array or tensor). K: ``[V, 3, 3]``. world_T_cam: ``[V, 4, 4]``.
        bounds: ``((xmin, ymin, zmin), (xmax, ymax, zmax))``: points outside are ignored (a detector passes its
            feature grid's bounds); ``None``: none.
        params: the pseudo-box parameters (default :data:`OBSERVED_PARAMS`).

    Returns:
        ``aabb [P, 6]`` float32 and ``scores [P]`` float32 (sorted by decreasing score); cached per process.

    Raises:
        ValueError: naming the field, for malformed views (NaN depth, wrong shapes) or bounds.
    """
    d = _as_numpy(depth, np.float32)
    k = _as_numpy(K, np.float32)
    t = _as_numpy(world_T_cam, np.float32)
    b = None if bounds is None else np.asarray(bounds, dtype=np.float64).reshape(2, 3)
    h = hashlib.blake2b(digest_size=20)
    for a in (d, k, t, np.asarray(d.shape), np.zeros(0) if b is None else b):
        h.update(a.tobytes())
    h.update(repr(sorted(asdict(params).items())).encode())
    key = h.digest()
    if key in _CACHE:
        _CACHE.move_to_end(key)
        return _CACHE[key]
    record = SceneRecord(rgb=None, depth=d, K=k, world_T_cam=t, boxes=np.zeros((0, 7), np.float32),  # type: ignore[arg-type]
                         categories=np.zeros((0,), np.int64))  # fmt: skip
    out = propose_boxes(record, bounds=None if b is None else (b[0], b[1]), **asdict(params))
    _CACHE[key] = out
    if len(_CACHE) > _CACHE_SIZE:
        _CACHE.popitem(last=False)
    return out


def refine_boxes(
    boxes: Tensor, scores: Tensor, observed: Tensor, min_iou: float, nms_iou: float, nms_iomin: float = 1.0
) -> tuple[Tensor, Tensor, Tensor]:
    """Each detection replaced by the observed box it overlaps most (IoU >= ``min_iou``), then 3D NMS again.

    Args:
        boxes: ``[N, 6]`` detections (``N = 0`` allowed). scores: ``[N]``.
        observed: ``[P, 6]`` observed boxes (:func:`observed_boxes`; ``P = 0``: nothing changes but the NMS).
        min_iou: in ``(0, 1]``: the least IoU with an observed box that moves a detection onto it.
        nms_iou, nms_iomin: the suppression after snapping (:func:`~threedq.boxes.nms_3d`; the detector's own).

    Returns:
        ``boxes [K, 6]``, ``scores [K]`` (descending) and ``snapped [K]`` bool (the box is an observed one). A
        detection keeps its score; of several snapped onto one observed box the highest-scoring stays.

    Raises:
        ValueError: for ``min_iou`` outside ``(0, 1]`` or bad shapes.
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


def add_flat_boxes(
    boxes: Tensor, scores: Tensor, observed: Tensor, observed_scores: Tensor, max_height: float, score_scale: float,
    min_score: float, overlap_iou: float,
) -> tuple[Tensor, Tensor]:
    """Detections plus the observed boxes too flat for the detector to learn, ranked by the geometry's confidence.

    A detector trained with ``min_box_height`` ignores the boxes below it (their height is under half a feature voxel:
    the grid cannot tell them from the floor), so it never finds them. The label-free pseudo-boxes of its own input
    view can: each observed box less tall than ``max_height`` that overlaps no detection at IoU ``overlap_iou`` or
    more is added, scored ``score_scale * observed score`` (in ``(0, score_scale]``: below every detection the
    detector is confident of when ``score_scale`` is its score threshold), when that reaches ``min_score``.

    Args:
        boxes: ``[N, 6]`` detections; scores: ``[N]``.
        observed: ``[P, 6]`` observed boxes (:func:`observed_boxes`); observed_scores: ``[P]`` their scores in (0, 1].
        max_height: metres; an observed box is flat when ``zmax - zmin < max_height``.
        score_scale: factor on the observed scores; min_score: the least score a flat box needs to be added.
        overlap_iou: a flat box overlapping a detection at this IoU or more is left out (it is found already).

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
