"""Camera poses corrected by the floor they see (label-free): each view's floor brought onto one level plane at z = 0.

1. the scene's floor is fitted with RANSAC to the back-projected depth of all views
   (:func:`~threedq.geometry.ground.fit_ground_plane`), and one rigid motion (the same for every view, so the views
   stay consistent with each other) turns it level and moves it to z = 0;
2. each view's own floor is fitted to its points within ``band`` of the scene's floor, and the view is rotated about
   its camera centre (where a tracker's orientation error turns it) and moved vertically so that its floor is that
   same plane.

A correction smaller than ``min_angle_deg`` and ``min_offset`` is not applied (a clean render's poses are left as
they are, bit for bit); a view that sees too little floor (fewer than ``min_points`` points in the band), or whose
correction would be larger than ``max_angle_deg`` or ``max_offset``, keeps the scene-level motion only.

Convention: metres and degrees; world frame right-handed, z up; ``world_T_cam`` maps OpenCV camera points (x right,
y down, z forward) to the world; depth is metric z-depth with 0 (or non-finite) invalid.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from threedq.geometry.ground import fit_ground_plane

__all__ = ["FloorAlignment", "align_to_floor", "view_pixels_in_world"]


@dataclass(frozen=True)
class FloorAlignment:
    """What :func:`align_to_floor` did.

    Attributes:
        world_T_cam: ``[V, 4, 4]`` the corrected poses (the input's dtype).
        scene_tilt_deg: the angle between the scene's fitted floor normal and +z before the correction.
        scene_offset: the scene's floor height at its inliers' centroid before the correction, metres.
        view_angle_deg: ``[V]`` each view's own rotation (0 where none was applied).
        view_offset: ``[V]`` each view's own vertical move, metres (0 where none was applied).
        applied: whether any pose changed.
    """

    world_T_cam: np.ndarray
    scene_tilt_deg: float
    scene_offset: float
    view_angle_deg: np.ndarray
    view_offset: np.ndarray
    applied: bool


def _rotation_between(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """The smallest rotation taking unit vector ``a`` to unit vector ``b`` (Rodrigues), float64 ``[3, 3]``."""
    v = np.cross(a, b)
    s, c = np.linalg.norm(v), float(np.dot(a, b))
    if s < 1e-12:
        return np.eye(3)
    k = v / s
    kx = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + s * kx + (1 - c) * kx @ kx


def _rigid(R: np.ndarray, centre: np.ndarray, lift: float) -> np.ndarray:
    """``[4, 4]``: rotate by ``R`` about ``centre``, then move by ``lift`` along z."""
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = centre - R @ centre + np.array([0.0, 0.0, lift])
    return T


def view_pixels_in_world(depth: np.ndarray, K: np.ndarray, world_T_cam: np.ndarray,
                         stride: int) -> list[tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """Each view's valid depth pixels (every ``stride``-th row and column) back-projected: per view ``(points [N, 3]
    in the world frame, float64; their rows [N]; their columns [N])``."""
    out = []
    for d, k, T in zip(depth, K, world_T_cam):
        z = d[::stride, ::stride].astype(np.float64)
        v, u = np.nonzero(np.isfinite(z) & (z > 0))
        z = z[v, u]
        u, v = u * stride, v * stride
        x = (u - k[0, 2] - k[0, 1] * (v - k[1, 2]) / k[1, 1]) / k[0, 0] * z
        y = (v - k[1, 2]) / k[1, 1] * z
        cam = np.stack([x, y, z], axis=1)
        out.append((cam @ T[:3, :3].T.astype(np.float64) + T[:3, 3].astype(np.float64), v, u))
    return out


def _view_points(depth: np.ndarray, K: np.ndarray, world_T_cam: np.ndarray, stride: int) -> list[np.ndarray]:
    """Each view's valid depth pixels (every ``stride``-th row and column) in the world frame, float64."""
    return [p for p, _, _ in view_pixels_in_world(depth, K, world_T_cam, stride)]


def align_to_floor(depth: np.ndarray, K: np.ndarray, world_T_cam: np.ndarray, *, stride: int = 2, band: float = 0.15,
                   threshold: float = 0.02, min_points: int = 200, min_angle_deg: float = 0.05,
                   min_offset: float = 0.001, max_angle_deg: float = 10.0, max_offset: float = 0.3,
                   seed: int = 0) -> FloorAlignment:
    """Correct camera poses so that the floor every view sees is the plane z = 0 (see the module docstring).

    Args:
        depth: ``[V, H, W]`` metric z-depth; K: ``[V, 3, 3]``; world_T_cam: ``[V, 4, 4]``.
        stride: every ``stride``-th pixel row and column is used.
        band: a view's floor is fitted among its points within this of the scene's floor, metres.
        threshold: RANSAC inlier distance, metres (about three times the depth noise on the floor).
        min_points: a view with fewer points in the band keeps the scene-level motion only.
        min_angle_deg, min_offset: smaller corrections are not applied.
        max_angle_deg, max_offset: a view whose own correction is larger keeps the scene-level motion only.
        seed: RANSAC seed (the result is deterministic).

    Returns:
        A :class:`FloorAlignment`; its ``world_T_cam`` is the input (the same values) where nothing was applied or no
        floor was found.

    Raises:
        ValueError: inconsistent shapes.
    """
    depth, K, poses = np.asarray(depth), np.asarray(K), np.asarray(world_T_cam)
    if depth.ndim != 3 or K.shape != (depth.shape[0], 3, 3) or poses.shape != (depth.shape[0], 4, 4):
        raise ValueError(f"depth [V,H,W], K [V,3,3], world_T_cam [V,4,4]: got {list(depth.shape)}, {list(K.shape)}, "
                         f"{list(poses.shape)}")
    V = depth.shape[0]
    none = FloorAlignment(poses, 0.0, 0.0, np.zeros(V), np.zeros(V), False)
    pts = _view_points(depth, K, poses, stride)
    centres = poses[:, :3, 3].astype(np.float64)
    fit = fit_ground_plane(np.concatenate(pts), camera_centres=centres, threshold=threshold, seed=seed)
    if fit is None:
        return none
    n, d, _ = fit
    ez = np.array([0.0, 0.0, 1.0])
    tilt = math.degrees(math.acos(min(1.0, float(n[2]))))
    allp = np.concatenate(pts)
    on = allp[np.abs(allp @ n + d) <= threshold]
    c = on.mean(axis=0) if len(on) else -d * n
    offset = float(c[2])  # the floor's height at the centroid of its points
    level = tilt >= min_angle_deg or abs(offset) >= min_offset
    scene = _rigid(_rotation_between(n, ez), c, -offset) if level else np.eye(4)
    angles, lifts = np.zeros(V), np.zeros(V)
    out = poses.astype(np.float64).copy()
    changed = not np.array_equal(scene, np.eye(4))
    for v in range(V):
        T = scene @ out[v]
        p = pts[v] @ scene[:3, :3].T + scene[:3, 3]
        near = p[np.abs(p[:, 2]) <= band]
        kw = {"camera_centres": T[None, :3, 3], "threshold": threshold, "iters": 60, "sample": 3000, "seed": seed}
        own = fit_ground_plane(near, **kw) if len(near) >= min_points else None
        if own is not None:
            nv, dv, _ = own
            ang = math.degrees(math.acos(min(1.0, float(nv[2]))))
            R = _rotation_between(nv, ez)
            cam = T[:3, 3]
            q = near[np.abs(near @ nv + dv) <= threshold]
            lift = -float(np.median((q - cam) @ R.T[:, 2] + cam[2])) if len(q) else 0.0  # floor height after R
            if (ang >= min_angle_deg or abs(lift) >= min_offset) and ang <= max_angle_deg and abs(lift) <= max_offset:
                T = _rigid(R, cam, lift) @ T
                angles[v], lifts[v] = ang, lift
                changed = True
        out[v] = T
    if not changed:
        return none
    return FloorAlignment(out.astype(poses.dtype), tilt, offset, angles, lifts, True)
