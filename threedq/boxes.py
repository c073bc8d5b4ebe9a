"""Oriented 3D boxes of the canonical scene record and their axis-aligned hulls.

A box is ``(cx, cy, cz, sx, sy, sz, yaw)``: centre, full extents along the object's own x, y, z
axes, and the yaw that turns the object's x axis towards world +y.

Convention: world frame, metres, z up, right-handed; yaw about +z, counter-clockwise seen from above,
radians. Corner order (object frame, before yaw): index bits (x, y, z) = (i & 1, i >> 1 & 1, i >> 2 & 1),
0 -> min, 1 -> max; corners 0-3 are the bottom face.
"""

from __future__ import annotations

import numpy as np
import torch

__all__ = ["box_corners", "boxes_to_aabb", "aabb_to_corners"]

_SIGNS = np.array([[(i & 1), (i >> 1) & 1, (i >> 2) & 1] for i in range(8)], dtype=np.float64) - 0.5


def _as_tensor(x: np.ndarray | torch.Tensor) -> tuple[torch.Tensor, bool]:
    if isinstance(x, torch.Tensor):
        return x, False
    return torch.as_tensor(np.asarray(x)), True


def box_corners(boxes: np.ndarray | torch.Tensor) -> np.ndarray | torch.Tensor:
    """Corners of oriented boxes.

    Args:
        boxes: ``[..., 7]`` ``(cx, cy, cz, sx, sy, sz, yaw)``.

    Returns:
        ``[..., 8, 3]`` corner coordinates, same type (numpy or torch) as the input.

    Convention: world frame, z up, yaw counter-clockwise about +z seen from above, radians.
    """
    t, was_numpy = _as_tensor(boxes)
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
    """Tight axis-aligned hull ``(xmin, ymin, zmin, xmax, ymax, zmax)`` of oriented boxes ``[..., 7]``.

    Convention: world frame, z up; the hull of a yawed box grows in x and y, never in z.
    """
    corners = box_corners(boxes)
    if isinstance(corners, np.ndarray):
        return np.concatenate([corners.min(axis=-2), corners.max(axis=-2)], axis=-1)
    return torch.cat([corners.amin(dim=-2), corners.amax(dim=-2)], dim=-1)


def aabb_to_corners(aabb: np.ndarray | torch.Tensor) -> np.ndarray | torch.Tensor:
    """Corners ``[..., 8, 3]`` of axis-aligned boxes ``[..., 6]`` (same corner order as :func:`box_corners`)."""
    t, was_numpy = _as_tensor(aabb)
    if t.shape[-1] != 6:
        raise ValueError(f"aabb: expected shape [..., 6], got {tuple(t.shape)}")
    centre = (t[..., :3] + t[..., 3:]) / 2
    size = t[..., 3:] - t[..., :3]
    boxes = torch.cat([centre, size, torch.zeros_like(size[..., :1])], dim=-1)
    out = box_corners(boxes)
    return out.numpy() if was_numpy else out
