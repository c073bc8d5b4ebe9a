"""Per-view colour gains from the floor every view sees (label-free exposure and white-balance consistency).

A sensor's auto-exposure and white balance change from frame to frame, so one surface takes another colour in each
view. The floor (or table) an object stands on is seen by nearly every view of a scene: each view's gains are the
ratio, per channel, of the scene's median floor colour (the median over views of each view's median) to the view's
own median floor colour. A view that sees too little floor keeps gains of 1, and so does a view whose gains all lie
within ``min_change`` of 1 (the shading differences of clean renders: their colours are left as they are, bit for
bit).

Convention: metres; world frame z up with the floor at z = 0 (the poses of
:func:`~threedq.geometry.floor_alignment.align_to_floor`); ``world_T_cam`` maps OpenCV camera points (x right, y down,
z forward) to the world; depth is metric z-depth with 0 (or non-finite) invalid; RGB ``[V, H, W, 3]`` uint8 (0..255)
or float (0..1).
"""

from __future__ import annotations

import numpy as np

from threedq.geometry.floor_alignment import view_pixels_in_world

__all__ = ["apply_gains", "floor_colour_gains"]


def floor_colour_gains(rgb: np.ndarray, depth: np.ndarray, K: np.ndarray, world_T_cam: np.ndarray, *,
                       band: float = 0.03, stride: int = 2, min_floor: float = 0.05,
                       min_change: float = 0.06) -> np.ndarray:
    """Each view's per-channel gains that bring its floor's median colour to the scene's.

    Args:
        rgb: ``[V, H, W, 3]``; depth: ``[V, H, W]``; K: ``[V, 3, 3]``; world_T_cam: ``[V, 4, 4]`` with the floor at
            z = 0.
        band: a pixel is floor where its back-projected point lies within this of z = 0, metres.
        stride: every ``stride``-th pixel row and column is read.
        min_floor: a view whose floor covers less than this share of its (strided) pixels keeps gains of 1.
        min_change: a view whose gains all lie within this of 1 keeps gains of 1.

    Returns:
        ``[V, 3]`` float64 gains (all 1 where fewer than two views see enough floor).

    Raises:
        ValueError: inconsistent shapes.
    """
    rgb, depth, K, poses = (np.asarray(a) for a in (rgb, depth, K, world_T_cam))
    V = depth.shape[0] if depth.ndim == 3 else -1
    if (depth.ndim != 3 or rgb.shape != (*depth.shape, 3) or K.shape != (V, 3, 3) or poses.shape != (V, 4, 4)):
        raise ValueError(f"rgb [V,H,W,3], depth [V,H,W], K [V,3,3], world_T_cam [V,4,4]: got {list(rgb.shape)}, "
                         f"{list(depth.shape)}, {list(K.shape)}, {list(poses.shape)}")
    sampled = len(range(0, depth.shape[1], stride)) * len(range(0, depth.shape[2], stride))
    med = np.full((V, 3), np.nan)
    for v, (points, rows, cols) in enumerate(view_pixels_in_world(depth, K, poses, stride)):
        floor = np.abs(points[:, 2]) <= band
        if floor.sum() >= max(min_floor * sampled, 1):
            med[v] = np.median(rgb[v, rows[floor], cols[floor]].astype(np.float64), axis=0)
    seen = np.isfinite(med[:, 0]) & (med > 0).all(1)
    gains = np.ones((V, 3))
    if seen.sum() >= 2:
        gains[seen] = np.median(med[seen], axis=0) / med[seen]
    gains[(np.abs(gains - 1) <= min_change).all(1)] = 1.0
    return gains


def apply_gains(rgb: np.ndarray, gains: np.ndarray) -> np.ndarray:
    """``rgb`` ``[V, H, W, 3]`` times ``gains`` ``[V, 3]``, clipped to its range, in its dtype (uint8 rounded)."""
    rgb = np.asarray(rgb)
    full = 255.0 if rgb.dtype == np.uint8 else 1.0
    out = np.clip(rgb.astype(np.float64) * np.asarray(gains, np.float64)[:, None, None, :], 0.0, full)
    return np.round(out).astype(np.uint8) if rgb.dtype == np.uint8 else out.astype(rgb.dtype)
