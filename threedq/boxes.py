"""Oriented 3D boxes ``(cx, cy, cz, sx, sy, sz, yaw)`` (centre, full extents along the object's own axes, yaw turning
its x axis towards world +y), their axis-aligned hulls ``(xmin, ymin, zmin, xmax, ymax, zmax)``, IoU and NMS.

Convention: world frame, metres, z up, right-handed; yaw about +z, counter-clockwise seen from above, radians.
Corner order (object frame, before yaw): index bits (x, y, z) = (i & 1, i >> 1 & 1, i >> 2 & 1), 0 -> min, 1 -> max;
corners 0-3 are the bottom face.
"""

from __future__ import annotations

import numpy as np
import torch

__all__ = ["aabb_iomin_3d", "aabb_iou_3d", "best_aabb_iou", "box_corners", "boxes_to_aabb", "nms_3d"]

_SIGNS = np.array([[(i & 1), (i >> 1) & 1, (i >> 2) & 1] for i in range(8)], dtype=np.float64) - 0.5


def box_corners(boxes: np.ndarray | torch.Tensor) -> np.ndarray | torch.Tensor:
    """Corners ``[..., 8, 3]`` of oriented boxes ``[..., 7]``, same type (numpy or torch) as the input."""
    was_numpy = not isinstance(boxes, torch.Tensor)
    t = torch.as_tensor(np.asarray(boxes)) if was_numpy else boxes
    if t.shape[-1] != 7:
        raise ValueError(f"boxes: expected shape [..., 7], got {tuple(t.shape)}")
    signs = torch.as_tensor(_SIGNS, dtype=t.dtype, device=t.device)
    local = signs * t[..., None, 3:6]  # [..., 8, 3]
    c, s = torch.cos(t[..., 6])[..., None], torch.sin(t[..., 6])[..., None]
    x = local[..., 0] * c - local[..., 1] * s
    y = local[..., 0] * s + local[..., 1] * c
    out = torch.stack([x, y, local[..., 2]], dim=-1) + t[..., None, 0:3]
    return out.numpy() if was_numpy else out


def boxes_to_aabb(boxes: np.ndarray | torch.Tensor) -> np.ndarray | torch.Tensor:
    """Tight axis-aligned hull ``[..., 6]`` ``(xmin, ymin, zmin, xmax, ymax, zmax)`` of oriented boxes ``[..., 7]``."""
    corners = box_corners(boxes)
    if isinstance(corners, np.ndarray):
        return np.concatenate([corners.min(axis=-2), corners.max(axis=-2)], axis=-1)
    return torch.cat([corners.amin(dim=-2), corners.amax(dim=-2)], dim=-1)


def _check_aabb_rows(t: torch.Tensor, name: str) -> None:
    if not isinstance(t, torch.Tensor) or t.ndim != 2 or t.shape[-1] != 6:
        shape = tuple(t.shape) if isinstance(t, torch.Tensor) else type(t).__name__
        raise ValueError(f"{name}: expected a tensor of shape [N, 6] (xmin, ymin, zmin, xmax, ymax, zmax), got {shape}")
    if t.dtype == torch.bool or t.is_complex():
        raise ValueError(f"{name}: expected a real-valued tensor, got {t.dtype}")
    if t.numel() == 0:
        return
    if not bool(torch.isfinite(t).all()):
        raise ValueError(f"{name}: boxes must be finite")
    bad = (t[:, 3:] < t[:, :3]).any(dim=1)
    if bool(bad.any()):
        i = int(bad.nonzero()[0, 0])
        raise ValueError(f"{name}: max < min in box {i}: {t[i].tolist()}")


def _aabb_intersection(a: torch.Tensor, b: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Checked pairwise intersection volumes ``[N, M]`` and the volumes ``[N]``, ``[M]`` of two box sets."""
    _check_aabb_rows(a, "a")
    _check_aabb_rows(b, "b")
    dtype = torch.promote_types(a.dtype, b.dtype)
    if not dtype.is_floating_point:
        dtype = torch.get_default_dtype()
    a, b = a.to(dtype), b.to(dtype)
    lo = torch.maximum(a[:, None, :3], b[None, :, :3])
    hi = torch.minimum(a[:, None, 3:], b[None, :, 3:])
    inter = (hi - lo).clamp(min=0).prod(dim=-1)  # [N, M]
    return inter, (a[:, 3:] - a[:, :3]).prod(dim=-1), (b[:, 3:] - b[:, :3]).prod(dim=-1)


def aabb_iou_3d(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Pairwise intersection-over-union ``[N, M]`` in ``[0, 1]`` of axis-aligned boxes ``a [N, 6]`` and ``b [M, 6]``
    (dtype promoted from the inputs, the default float dtype for integers); a zero-volume box has IoU 0 with every box.

    Raises:
        ValueError: if an input is not an ``[N, 6]`` real tensor, holds non-finite values, or has ``max < min``.
    """
    inter, vol_a, vol_b = _aabb_intersection(a, b)
    union = vol_a[:, None] + vol_b[None, :] - inter
    return torch.where(union > 0, inter / union.clamp(min=torch.finfo(inter.dtype).tiny), torch.zeros_like(inter))


def best_aabb_iou(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """``[N]``: each box of ``a [N, 6]``'s highest :func:`aabb_iou_3d` with ``b [M, 6]`` (0 when ``M = 0``)."""
    iou = aabb_iou_3d(a, b)
    return iou.amax(dim=1) if iou.shape[1] else iou.new_zeros(iou.shape[0])


def aabb_iomin_3d(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Pairwise intersection over the smaller volume ``[N, M]`` of ``a [N, 6]`` and ``b [M, 6]`` (1 when one box
    lies inside the other); dtype and errors as :func:`aabb_iou_3d`, 0 when either box has zero volume."""
    inter, vol_a, vol_b = _aabb_intersection(a, b)
    smaller = torch.minimum(vol_a[:, None], vol_b[None, :])
    return torch.where(smaller > 0, inter / smaller.clamp(min=torch.finfo(inter.dtype).tiny), torch.zeros_like(inter))


def nms_3d(boxes: torch.Tensor, scores: torch.Tensor, iou_threshold: float,
           iomin_threshold: float = 1.0) -> torch.Tensor:  # fmt: skip
    """Greedy non-maximum suppression of axis-aligned 3D boxes.

    Boxes are visited by descending score; a box is kept unless, with an already kept box, its IoU is strictly
    greater than ``iou_threshold`` or its :func:`aabb_iomin_3d` strictly greater than ``iomin_threshold``.

    Args:
        boxes: ``[N, 6]`` boxes; ``N = 0`` allowed. scores: ``[N]`` real scores, higher is better.
        iou_threshold: in ``[0, 1]``. iomin_threshold: in ``[0, 1]``; 1 never suppresses by it (plain IoU NMS).

    Returns:
        ``[K]`` int64 indices into ``boxes`` of the kept boxes, sorted by descending score (ties in index order).

    Raises:
        ValueError: on bad shapes (see :func:`aabb_iou_3d`), non-finite scores, or a threshold outside ``[0, 1]``.
    """
    _check_aabb_rows(boxes, "boxes")
    if not isinstance(scores, torch.Tensor) or scores.ndim != 1 or scores.shape[0] != boxes.shape[0]:
        shape = tuple(scores.shape) if isinstance(scores, torch.Tensor) else type(scores).__name__
        raise ValueError(f"scores: expected shape [{boxes.shape[0]}] (one per box), got {shape}")
    if scores.dtype == torch.bool or scores.is_complex() or not bool(torch.isfinite(scores).all()):
        raise ValueError("scores: expected finite real values")
    for name, thr in (("iou_threshold", iou_threshold), ("iomin_threshold", iomin_threshold)):
        if isinstance(thr, bool) or not isinstance(thr, (int, float)) or not 0 <= thr <= 1:
            raise ValueError(f"{name} must be a number in [0, 1], got {thr!r}")
    n = boxes.shape[0]
    if n == 0:
        return torch.zeros(0, dtype=torch.long, device=boxes.device)
    order = torch.sort(scores, descending=True, stable=True).indices
    sorted_boxes = boxes[order]
    over = aabb_iou_3d(sorted_boxes, sorted_boxes) > iou_threshold
    if iomin_threshold < 1:
        over |= aabb_iomin_3d(sorted_boxes, sorted_boxes) > iomin_threshold
    over = over.cpu().numpy()
    suppressed = np.zeros(n, dtype=bool)
    keep: list[int] = []
    for i in range(n):
        if suppressed[i]:
            continue
        keep.append(i)
        suppressed |= over[i]
    return order[torch.as_tensor(keep, dtype=torch.long, device=order.device)]
