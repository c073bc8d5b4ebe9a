"""A coloured point cloud fused from posed RGB-D views, thinned on a voxel grid (what a 3D viewer draws).

Convention: points in the record's world frame R (metres, z up); OpenCV cameras, z-depth, 0 or non-finite = no depth
(:func:`threedq.geometry.camera.depth_to_points`); colours ``uint8`` RGB.
"""

from __future__ import annotations

import numpy as np
import torch

from .camera import depth_to_points

__all__ = ["fuse_views", "points_in_aabb", "voxel_downsample"]


def voxel_downsample(points: np.ndarray, colours: np.ndarray, voxel_size: float) -> tuple[np.ndarray, np.ndarray]:
    """One point per occupied voxel: the mean position and the mean colour of the points in it.

    Args:
        points: ``[N, 3]`` positions.
        colours: ``[N, 3]`` ``uint8`` colours of the same points.
        voxel_size: the voxel's edge (metres, > 0); voxels are cells of ``floor(p / voxel_size)``.

    Returns:
        ``[M, 3]`` float32 positions and ``[M, 3]`` uint8 colours, voxels in ascending lexicographic order of their
        integer cell ``(i, j, k)``.
    """
    if not voxel_size > 0:
        raise ValueError(f"voxel_size: expected a positive edge in metres, got {voxel_size}")
    points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    colours = np.asarray(colours).reshape(-1, 3)
    if points.shape[0] != colours.shape[0]:
        raise ValueError(f"colours: expected one per point ({points.shape[0]}), got {colours.shape[0]}")
    if points.shape[0] == 0:
        return np.zeros((0, 3), np.float32), np.zeros((0, 3), np.uint8)
    cells = np.floor(points / voxel_size).astype(np.int64)
    cells -= cells.min(0)
    span = cells.max(0) + 1
    if float(span[0]) * float(span[1]) * float(span[2]) < 2.0**62:  # one integer per cell, ordered as (i, j, k)
        key = (cells[:, 0] * span[1] + cells[:, 1]) * span[2] + cells[:, 2]
        _, inverse, counts = np.unique(key, return_inverse=True, return_counts=True)
    else:  # points kilometres apart: the rows themselves (slower)
        _, inverse, counts = np.unique(cells, axis=0, return_inverse=True, return_counts=True)
    inverse = inverse.reshape(-1)
    m = counts.shape[0]
    mean_p = np.stack([np.bincount(inverse, points[:, d], m) for d in range(3)], 1) / counts[:, None]
    mean_c = np.stack([np.bincount(inverse, colours[:, d].astype(np.float64), m) for d in range(3)], 1)
    mean_c /= counts[:, None]
    return mean_p.astype(np.float32), np.clip(np.rint(mean_c), 0, 255).astype(np.uint8)


def fuse_views(rgb: np.ndarray, depth: np.ndarray, K: np.ndarray, world_T_cam: np.ndarray, voxel_size: float = 0.02,
               max_points: int | None = None, seed: int = 0,
               bounds: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Back-project every valid depth pixel of every view into R, thin the union on a voxel grid, keep the voxels
    inside ``bounds`` and, when more than ``max_points`` remain, a random ``max_points`` of them (drawn with ``seed``).

    Args:
        rgb: ``[V, H, W, 3]`` uint8.
        depth: ``[V, H, W]`` metric z-depth.
        K: ``[V, 3, 3]`` intrinsics.
        world_T_cam: ``[V, 4, 4]`` camera-to-R poses.
        voxel_size: see :func:`voxel_downsample`.
        max_points: the most points returned (None: all voxels).
        seed: the draw of the kept points.
        bounds: ``(xmin, ymin, zmin, xmax, ymax, zmax)`` of the region kept (None: everything).

    Returns:
        ``[M, 3]`` float32 positions and ``[M, 3]`` uint8 colours.
    """
    if max_points is not None and max_points < 1:
        raise ValueError(f"max_points: expected at least 1, got {max_points}")
    d = torch.from_numpy(np.ascontiguousarray(depth, dtype=np.float32))
    pts, valid = depth_to_points(d, torch.from_numpy(np.asarray(K, np.float32)),
                                 torch.from_numpy(np.asarray(world_T_cam, np.float32)))
    valid_np = valid.numpy().reshape(-1)
    points = pts.numpy().reshape(-1, 3)[valid_np]
    colours = np.asarray(rgb, np.uint8).reshape(-1, 3)[valid_np]
    points, colours = voxel_downsample(points, colours, voxel_size)
    if bounds is not None:
        inside = points_in_aabb(points, bounds)
        points, colours = points[inside], colours[inside]
    if max_points is not None and points.shape[0] > max_points:
        keep = np.sort(np.random.default_rng(seed).choice(points.shape[0], max_points, replace=False))
        points, colours = points[keep], colours[keep]
    return points, colours


def points_in_aabb(points: np.ndarray, aabb: np.ndarray) -> np.ndarray:
    """``[N]`` bool: the points inside (or on) the box ``(xmin, ymin, zmin, xmax, ymax, zmax)``."""
    aabb = np.asarray(aabb, dtype=np.float64).reshape(6)
    return np.all((points >= aabb[:3]) & (points <= aabb[3:]), axis=1)
