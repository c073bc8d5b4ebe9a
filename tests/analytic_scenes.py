"""Analytic ray-cast RGB-D scenes for tests: a ground plane plus axis-aligned boxes, seen from cameras around them.

Exact z-depth (no renderer), so a test can compare a depth-based method with the geometry it came from.
"""

from __future__ import annotations

import math

import numpy as np

from threedq.scene import SceneRecord

SIZE = 96
FOCAL = 110.0


def look_at(eye, target, up=(0.0, 0.0, 1.0)) -> np.ndarray:
    """Camera-to-world pose with OpenCV axes (x right, y down, z forward) looking from eye at target."""
    eye, target, up = (np.asarray(a, dtype=np.float64) for a in (eye, target, up))
    fwd = target - eye
    fwd /= np.linalg.norm(fwd)
    right = np.cross(fwd, up)
    right /= np.linalg.norm(right)
    down = np.cross(fwd, right)
    T = np.eye(4)
    T[:3, :3] = np.stack([right, down, fwd], axis=1)
    T[:3, 3] = eye
    return T


def ray_aabb(o: np.ndarray, d: np.ndarray, box: np.ndarray) -> np.ndarray:
    """Entry parameter ``t`` of rays ``o + t d`` ``[N,3]`` into an axis-aligned box (inf where missed)."""
    with np.errstate(divide="ignore", invalid="ignore"):
        t1, t2 = (box[:3] - o) / d, (box[3:] - o) / d
    tmin = np.nanmax(np.minimum(t1, t2), axis=1)
    tmax = np.nanmin(np.maximum(t1, t2), axis=1)
    return np.where((tmax >= tmin) & (tmin > 0), tmin, np.inf)


def render(boxes: np.ndarray, normal=(0.0, 0.0, 1.0), offset: float = 0.0, num_views: int = 8) -> SceneRecord:
    """Exact z-depth of a ground plane ``n . p = offset`` plus axis-aligned boxes, from cameras around the scene."""
    n = np.asarray(normal, dtype=np.float64)
    n /= np.linalg.norm(n)
    K = np.array([[FOCAL, 0, (SIZE - 1) / 2], [0, FOCAL, (SIZE - 1) / 2], [0, 0, 1]])
    v, u = np.mgrid[0:SIZE, 0:SIZE].astype(np.float64)
    rays_cam = np.stack([(u - K[0, 2]) / FOCAL, (v - K[1, 2]) / FOCAL, np.ones_like(u)], -1).reshape(-1, 3)
    depths, poses = [], []
    for i in range(num_views):
        az = 2 * math.pi * i / num_views + 0.3
        el = math.radians(35 if i % 2 else 60)
        eye = 2.2 * np.array([math.cos(el) * math.cos(az), math.cos(el) * math.sin(az), math.sin(el)])
        T = look_at(eye, np.array([0.0, 0.0, 0.1]))
        d = rays_cam @ T[:3, :3].T  # world directions with camera z = 1, so t is z-depth
        with np.errstate(divide="ignore", invalid="ignore"):
            t_ground = (offset - eye @ n) / (d @ n)
        t = np.where(t_ground > 0, t_ground, np.inf)
        for b in boxes:
            t = np.minimum(t, ray_aabb(eye[None], d, b))
        t[~np.isfinite(t) | (t > 20)] = 0.0
        depths.append(t.reshape(SIZE, SIZE))
        poses.append(T)
    V = num_views
    return SceneRecord(
        rgb=np.zeros((V, SIZE, SIZE, 3), np.uint8),
        depth=np.stack(depths).astype(np.float32),
        K=np.repeat(K[None], V, 0).astype(np.float32),
        world_T_cam=np.stack(poses).astype(np.float32),
        boxes=None,  # type: ignore[arg-type]  # labels must never be read
        categories=None,  # type: ignore[arg-type]
    )
