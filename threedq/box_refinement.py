"""Detected boxes refined against what the detector's own input views observe.

A detector box is regressed from a feature cell (16 cm on the packaged grid: the 8 cm feature voxels at stride 2),
while the depth map of the very view the detector looks at says where the object's visible surface and the ground
under it are. :func:`observed_boxes` computes the label-free pseudo-boxes of those views (:mod:`threedq.proposals`
with :data:`OBSERVED_PARAMS`: a voxel seen by one view counts), and :func:`refine_boxes` replaces each detection by
the observed box it overlaps most when that IoU reaches ``min_iou``, keeps the detection's score, and suppresses
again (two detections snapped onto one observed box become one). A detection no observed box supports keeps its
regressed box: the detector still finds what the geometry misses (an object the ground-plane split cuts, a
partly hidden one); the geometry places what the detector finds.

Why (``docs/results.md``, "Where the detector loses IoU 0.5"): where a detector box meets an object, its height and
centre are the error (|log z ratio| 0.08-0.14, centre 2.7-6.1 cm), which the single-view pseudo-boxes do not make
(they extend every box to the fitted ground plane: 0.00, 0.7-1.4 cm).

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

__all__ = ["OBSERVED_PARAMS", "observed_boxes", "refine_boxes"]

#: The pseudo-box parameters of the views a detector sees: the packaged defaults, every view used and a voxel seen
#: by one view counted (the training pseudo-boxes ask for two views of a voxel; one input view cannot give two).
OBSERVED_PARAMS = ProposalParams(view_stride=1, min_views=1)

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
