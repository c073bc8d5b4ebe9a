"""Turn a parsed capture (any orientation, any origin) into a canonical scene: z up, centred on its objects.

Steps (:func:`normalise_capture`): depth beyond ``max_depth``, non-finite or negative becomes 0; at most
``max_views`` views are kept (farthest camera positions from view 0); the support plane, fitted
(:func:`threedq.geometry.ground.fit_ground_plane`) to the fused depth near the mean camera up vector, becomes ``z = 0``
with normal +z; x, y are centred on what stands on the plane (the midpoint of the 2nd-98th percentiles of the points
between ``margin`` and ``object_max_height`` above it); ``canonical_T_capture`` goes into the record's ``meta``
(:func:`boxes_to_capture_frame` maps boxes back).

Convention: canonical frame metres, right-handed, z up, centred; yaw counter-clockwise about +z;
``a_T_b`` maps points in frame b to frame a; OpenCV camera axes throughout.
"""

from __future__ import annotations

import math

import numpy as np
import torch

from threedq.boxes import box_corners
from threedq.data.formats.capture import Capture, farthest_order
from threedq.geometry.camera import depth_to_points
from threedq.geometry.ground import fit_ground_plane
from threedq.scene import SceneRecord, SceneValidationError

__all__ = ["boxes_to_capture_frame", "farthest_views", "normalise_capture", "rotation_between"]

_BOX_TILT_DEG = 5.0


def farthest_views(centres: np.ndarray, n: int) -> np.ndarray:
    """Indices (ascending) of ``n`` camera positions ``[V,3]`` chosen by farthest-point sampling from view 0."""
    return np.sort(farthest_order(np.asarray(centres, np.float64))[:n])


def rotation_between(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """The smallest rotation ``[3,3]`` taking unit vector ``a`` onto unit vector ``b`` (Rodrigues)."""
    a = np.asarray(a, np.float64) / np.linalg.norm(a)
    b = np.asarray(b, np.float64) / np.linalg.norm(b)
    v, c = np.cross(a, b), float(a @ b)
    if c < -1 + 1e-12:  # opposite: half turn about any axis orthogonal to a
        axis = np.cross(a, [1.0, 0, 0] if abs(a[0]) < 0.9 else [0, 1.0, 0])
        axis /= np.linalg.norm(axis)
        return 2 * np.outer(axis, axis) - np.eye(3)
    vx = np.array([[0, -v[2], v[1]], [v[2], 0, -v[0]], [-v[1], v[0], 0]])
    return np.eye(3) + vx + vx @ vx / (1 + c)


def _points(depth: np.ndarray, K: np.ndarray, pose: np.ndarray, stride: int) -> np.ndarray:
    """Back-projected valid depth of all views (every ``stride``-th pixel), ``[N,3]`` float64 in the pose frame."""
    s = stride
    Ks = K * np.array([1.0 / s, 1.0 / s, 1.0])[:, None]  # u' = u / s
    pts, ok = depth_to_points(torch.from_numpy(np.ascontiguousarray(depth[:, ::s, ::s], np.float64)),
                              torch.from_numpy(Ks), torch.from_numpy(pose))
    return pts[ok].numpy()


def normalise_capture(capture: Capture, categories: list[str] | None = None, max_views: int = 28,
                      max_depth: float = 10.0, plane_threshold: float = 0.02, max_tilt_deg: float = 45.0,
                      margin: float = 0.02, object_max_height: float = 1.5, fit_stride: int = 2) -> SceneRecord:
    """The canonical record of a capture (steps in the module docstring).

    Args:
        categories: category names; annotated objects take the id of their name (new names are appended to the
            caller's list). ``None`` = a fresh list.
        plane_threshold: RANSAC inlier distance of the support plane, metres; max_tilt_deg: largest angle between its
            normal and the mean camera up vector; fit_stride: pixel stride of the points it is fitted to.
        margin: points this far above the plane count as standing on it; object_max_height: points higher are ignored.

    Returns:
        A :class:`SceneRecord` with ``min(V, max_views)`` views; ``meta`` holds ``canonical_T_capture`` (4x4 rows),
        ``scene_bounds`` (``{"min", "max"}``), ``source``, ``source_format``, ``frame_ids``, ``skipped`` (count) and
        ``unannotated``.

    Raises:
        SceneValidationError: no support plane was found (naming ``depth``), or an annotated box is not upright in the
            canonical frame (naming ``objects``).
    """
    if max_views < 1:
        raise ValueError(f"max_views: expected >= 1, got {max_views}")
    categories = [] if categories is None else categories
    depth = capture.depth.astype(np.float32).copy()
    depth[~np.isfinite(depth) | (depth < 0) | (depth > max_depth)] = 0
    keep = farthest_views(capture.world_T_cam[:, :3, 3], max_views)
    poses = capture.world_T_cam[keep].astype(np.float64)
    K = capture.K[keep].astype(np.float64)
    depth = depth[keep]

    c_T, lo, hi, cxy, above_h = _canonical_frame(capture.source, depth, K, poses, fit_stride, plane_threshold,
                                                 max_tilt_deg, margin, object_max_height)
    boxes, cats = np.zeros((0, 7)), np.zeros((0,), np.int64)
    if capture.objects is not None and len(capture.objects.categories):
        boxes, cats = _canonical_boxes(capture, c_T, categories)
    bmin, bmax = _scene_bounds(lo, hi, cxy, above_h, boxes, margin)
    meta = {"source": capture.source, "source_format": capture.format,
            "frame_ids": [capture.frame_ids[i] for i in keep], "canonical_T_capture": c_T.tolist(),
            "scene_bounds": {"min": bmin.tolist(), "max": bmax.tolist()}, "skipped": len(capture.skipped),
            "unannotated": boxes.shape[0] == 0}
    return SceneRecord(rgb=capture.rgb[keep], depth=depth, K=K.astype(np.float32),
                       world_T_cam=(c_T @ poses).astype(np.float32), boxes=boxes.astype(np.float32), categories=cats,
                       meta=meta)


def _canonical_frame(source: str, depth: np.ndarray, K: np.ndarray, poses: np.ndarray, fit_stride: int,
                     plane_threshold: float, max_tilt_deg: float, margin: float,
                     object_max_height: float) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Fit the support plane to ``depth`` ``[V,H,W]`` and centre on what stands on it: ``canonical_T_capture``
    ``[4,4]``, the 2nd/98th percentiles ``lo``, ``hi`` ``[2]`` of the x-y of the points on the plane (before centring),
    their midpoint ``cxy`` and those points' heights ``[N]``."""
    up = -poses[:, :3, 1].mean(axis=0)
    R0 = rotation_between(up, [0, 0, 1]) if np.linalg.norm(up) > 1e-6 else np.eye(3)
    T0 = np.eye(4)
    T0[:3, :3] = R0
    pts = _points(depth, K, T0 @ poses, fit_stride)
    centres = (T0 @ poses)[:, :3, 3]
    plane = fit_ground_plane(pts, camera_centres=centres, threshold=plane_threshold, max_tilt_deg=max_tilt_deg)
    if plane is None:
        raise SceneValidationError(source, "depth", "no support plane found in the fused depth")
    n, d, _ = plane
    R1 = rotation_between(n, [0, 0, 1])
    height = pts @ n + d
    sel = (height > margin) & (height < object_max_height)
    if np.count_nonzero(sel) < 10:  # nothing stands on the plane: centre on the plane itself
        sel = np.abs(height) <= plane_threshold
    xy, above_h = (pts[sel] @ R1.T)[:, :2], height[sel]
    lo, hi = np.percentile(xy, 2, axis=0), np.percentile(xy, 98, axis=0)
    cxy = (lo + hi) / 2
    c_T = np.eye(4)
    c_T[:3, :3] = R1 @ R0
    c_T[:3, 3] = [-cxy[0], -cxy[1], d]
    return c_T, lo, hi, cxy, above_h


def _scene_bounds(lo: np.ndarray, hi: np.ndarray, cxy: np.ndarray, above_h: np.ndarray, boxes: np.ndarray,
                  margin: float) -> tuple[np.ndarray, np.ndarray]:
    """Canonical scene bounds ``(min [3], max [3])``: x-y symmetric about the origin, z from the plane to the 98th
    percentile height, the ``boxes``' corners included, padded by ``margin`` (z at least ``-margin`` below)."""
    half = np.maximum(np.abs(lo - cxy), np.abs(hi - cxy))
    zmax = float(np.percentile(above_h, 98))
    bmin = np.array([-half[0], -half[1], 0.0])
    bmax = np.array([half[0], half[1], max(zmax, margin)])
    if boxes.shape[0]:
        corners = box_corners(boxes).reshape(-1, 3)
        bmin, bmax = np.minimum(bmin, corners.min(0)), np.maximum(bmax, corners.max(0))
    bmin, bmax = bmin - margin, bmax + margin
    bmin[2] = min(bmin[2], -margin)
    return bmin, bmax


def _canonical_boxes(capture: Capture, c_T: np.ndarray, categories: list[str]) -> tuple[np.ndarray, np.ndarray]:
    objs = capture.objects
    assert objs is not None
    boxes, ids = [], []
    for m, (p, size, name) in enumerate(zip(objs.capture_T_box, objs.size, objs.categories)):
        q = c_T @ p
        tilt = math.degrees(math.acos(float(np.clip(q[2, 2], -1, 1))))
        if tilt > _BOX_TILT_DEG:
            why = f"box is tilted {tilt:.1f} deg from the support plane's normal"
            raise SceneValidationError(capture.source, f"objects[{m}]", why)
        boxes.append([*q[:3, 3], *size, math.atan2(q[1, 0], q[0, 0])])
        if name not in categories:
            categories.append(name)
        ids.append(categories.index(name))
    return np.array(boxes, np.float64), np.array(ids, np.int64)


def boxes_to_capture_frame(boxes: np.ndarray, canonical_T_capture: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Map canonical boxes ``[M,7]`` back to the capture's own frame with ``canonical_T_capture`` ``[4,4]``: returns
    ``capture_T_box`` ``[M,4,4]`` (box-local centre at the origin, local z up) and ``size`` ``[M,3]``."""
    boxes = np.asarray(boxes, np.float64).reshape(-1, 7)
    c, s = np.cos(boxes[:, 6]), np.sin(boxes[:, 6])
    can_T_box = np.tile(np.eye(4), (boxes.shape[0], 1, 1))
    can_T_box[:, 0, 0], can_T_box[:, 0, 1], can_T_box[:, 1, 0], can_T_box[:, 1, 1] = c, -s, s, c
    can_T_box[:, :3, 3] = boxes[:, :3]
    return np.linalg.inv(np.asarray(canonical_T_capture, np.float64)) @ can_T_box, boxes[:, 3:6].copy()
