"""Class-agnostic, label-free 3D box proposals from posed multi-view depth: objects are whatever sticks out of the
ground plane inside the scene bounds. :func:`propose_boxes` reads only depth, intrinsics, poses and bounds:

1. back-project the valid depth pixels of the used views into the world frame;
2. fit the ground plane by seeded RANSAC (normal near +z, least-squares refit, cameras above it);
3. keep the points more than ``ground_margin`` above the plane and inside the bounds;
4. voxelise them and keep the voxels seen by at least ``min_views`` distinct views;
5. 3D connected components (26-connectivity) after a ``dilation`` of the occupancy (boxes from undilated voxels);
6. one axis-aligned box per component: z from its points' percentile extents, ``zmin`` extended down to the ground
   plane under the box centre; x, y from the footprint (``"min_area_rect"``: the hull of its minimum-area rectangle;
   ``"aabb"``: the points' extents; a round footprint, whose convex hull fills less than 0.85 of that rectangle, is
   scaled by ``round_inflate`` instead); small or low components are dropped;
7. score in (0, 1]: the fraction of the used views that see the component times
   ``1 - exp(-voxels / score_voxel_scale)``; sorted by decreasing score (components are disjoint: no NMS).

Convention: world frame in metres, z up (see :mod:`threedq.scene`); boxes are axis-aligned
``(xmin, ymin, zmin, xmax, ymax, zmax)`` float32, as :func:`threedq.boxes.boxes_to_aabb` returns them.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from typing import Any

import numpy as np
from scipy import ndimage

from threedq.geometry.floor_alignment import align_to_floor
from threedq.geometry.ground import fit_ground_plane, ground_spread
from threedq.scene import Bounds, SceneRecord

__all__ = ["PROPOSALS_VERSION", "ProposalParams", "fit_ground_plane", "propose_boxes"]

#: Bump when equal parameters would give different proposals (caches of older versions are recomputed).
PROPOSALS_VERSION = 1
_MAX_GRID_CELLS = 64_000_000
_ROUND_FILL = 0.85  # convex-hull area / min-area-rectangle area below which a footprint counts as round

_FOOTPRINTS = ("aabb", "min_area_rect")
_Pair = tuple[np.ndarray, np.ndarray]


@dataclass(frozen=True)
class ProposalParams:
    """The keyword parameters of :func:`propose_boxes` (steps in the module docstring; metres, degrees, z up).

    Attributes:
        view_stride, pixel_stride: use every ``s``-th view, and every ``s``-th pixel row and column.
        voxel_size: voxel edge, at least ``min_voxel_pixels * pixel_stride * median(z / f)`` over the above-ground
            points (``z`` depth, ``f`` focal length in pixels).
        ground_margin: points less than this above the ground plane are ground. ``None``: ``max(min_ground_margin,
            3 sigma)``, ``sigma`` the ground points' height spread (:func:`~threedq.geometry.ground.ground_spread`).
        ransac_iters, ransac_threshold, ransac_sample, max_ground_tilt_deg, seed: ground-plane RANSAC.
        min_views: a voxel is occupied when points of at least this many views fall in it (at most the views used).
        dilation, min_component_voxels: dilation (voxels) before labelling components; smaller ones are dropped.
        min_height: least height of a component's top above the ground plane (``None``: the margin plus ``min_rise``).
        extent_percentile: per-axis percentile of the points used as the box extents (0 = min/max).
        xy_padding, footprint, round_inflate, extend_to_ground: the box's growth in x and y, footprint and ``zmin``.
        score_voxel_scale: voxel count at which the size factor of the score is ``1 - 1/e``.
        align_floor: first correct the poses by the floor each view sees
            (:func:`~threedq.geometry.floor_alignment.align_to_floor`); the boxes are then in the corrected frame.
    """

    view_stride: int = 1
    pixel_stride: int = 1
    voxel_size: float = 0.02
    min_voxel_pixels: float = 0.75
    ground_margin: float | None = 0.015
    min_ground_margin: float = 0.005
    ransac_iters: int = 200
    ransac_threshold: float = 0.01
    ransac_sample: int = 20000
    max_ground_tilt_deg: float = 30.0
    min_views: int = 2
    dilation: int = 1
    min_component_voxels: int = 8
    min_height: float | None = 0.02
    min_rise: float = 0.005
    extent_percentile: float = 0.0
    xy_padding: float = 0.0
    footprint: str = "min_area_rect"
    round_inflate: float = 1.2
    extend_to_ground: bool = True
    score_voxel_scale: float = 50.0
    align_floor: bool = False
    seed: int = 0

    def __post_init__(self) -> None:  # also normalises types, so equal settings compare (and cache) equal
        for name, low in (("view_stride", 1), ("pixel_stride", 1), ("ransac_iters", 1), ("ransac_sample", 3),
                          ("min_views", 1), ("dilation", 0), ("min_component_voxels", 0), ("seed", 0)):  # fmt: skip
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, (int, np.integer)) or v < low:
                raise ValueError(f"{name}: expected an int >= {low}, got {v!r}")
            object.__setattr__(self, name, int(v))
        # (name, low, low inclusive, high, high inclusive)
        non_neg = ("min_voxel_pixels", "ground_margin", "min_ground_margin", "min_height", "min_rise", "xy_padding")
        positive = ("voxel_size", "ransac_threshold", "score_voxel_scale")
        ranges = [(name, 0.0, name in non_neg, math.inf, False) for name in (*positive, *non_neg)]
        ranges += [("extent_percentile", 0.0, True, 50.0, False), ("max_ground_tilt_deg", 0.0, False, 90.0, True)]
        ranges += [("round_inflate", 1.0, True, 2.0, True)]
        for name, lo, lo_inc, hi, hi_inc in ranges:
            v = getattr(self, name)
            if v is None and name in ("ground_margin", "min_height"):  # measured per scene (see propose_boxes)
                continue
            ok = not isinstance(v, bool) and isinstance(v, (int, float, np.integer, np.floating)) and math.isfinite(v)
            ok = ok and (v >= lo if lo_inc else v > lo) and (v <= hi if hi_inc else v < hi)
            if not ok:
                interval = f"{'[' if lo_inc else '('}{lo:g}, {hi:g}{']' if hi_inc else ')'}"
                raise ValueError(f"{name}: expected a finite number in {interval}, got {v!r}")
            object.__setattr__(self, name, float(v))
        if self.footprint not in _FOOTPRINTS:
            raise ValueError(f"footprint: expected one of {_FOOTPRINTS}, got {self.footprint!r}")
        for name in ("extend_to_ground", "align_floor"):
            if not isinstance(getattr(self, name), bool):
                raise ValueError(f"{name}: expected a bool, got {getattr(self, name)!r}")  # noqa: TRY004


def _check_record(record: SceneRecord) -> None:
    depth, K, pose = record.depth, record.K, record.world_T_cam
    if not isinstance(depth, np.ndarray) or depth.ndim != 3:
        raise ValueError(f"depth: expected a [V,H,W] array, got shape {list(np.shape(depth))}")
    V = depth.shape[0]
    if V < 1:
        raise ValueError("depth: no views (V = 0)")
    if not np.issubdtype(depth.dtype, np.floating):
        raise ValueError(f"depth: expected a float dtype (metres), got {depth.dtype}")
    if not np.all(np.isfinite(depth)):
        bad = int(depth.size - np.count_nonzero(np.isfinite(depth)))
        raise ValueError(f"depth: {bad} non-finite value(s) (NaN or inf); use 0 for invalid pixels")
    if np.any(depth < 0):
        raise ValueError(f"depth: {int(np.count_nonzero(depth < 0))} negative value(s); use 0 for invalid pixels")
    if np.shape(K) != (V, 3, 3):
        raise ValueError(f"K: expected shape {[V, 3, 3]} to match depth, got {list(np.shape(K))}")
    if not np.all(np.isfinite(K)) or np.any(K[:, 0, 0] <= 0) or np.any(K[:, 1, 1] <= 0):
        raise ValueError("K: expected finite intrinsics with positive focal lengths K[0,0], K[1,1]")
    if np.shape(pose) != (V, 4, 4):
        raise ValueError(f"world_T_cam: expected shape {[V, 4, 4]} to match depth, got {list(np.shape(pose))}")
    if not np.all(np.isfinite(pose)):
        raise ValueError("world_T_cam: non-finite value(s) (NaN or inf)")
    rgb = record.rgb
    if rgb is not None and np.shape(rgb)[:3] != depth.shape:
        raise ValueError(f"rgb: expected shape {[*depth.shape, 3]} to match depth, got {list(np.shape(rgb))}")


def _check_bounds(bounds: Any) -> _Pair | None:
    if bounds is None:
        return None
    try:
        lo = np.asarray(bounds[0], dtype=np.float64).reshape(3)
        hi = np.asarray(bounds[1], dtype=np.float64).reshape(3)
    except (TypeError, ValueError, IndexError):
        raise ValueError(f"bounds: expected ((xmin, ymin, zmin), (xmax, ymax, zmax)) or None, got {bounds!r}") from None
    if not (np.all(np.isfinite(lo)) and np.all(np.isfinite(hi)) and np.all(lo < hi)):
        raise ValueError(f"bounds: expected finite min < max per axis, got {bounds!r}")
    return lo, hi


def _world_points(depth: np.ndarray, K: np.ndarray, world_T_cam: np.ndarray,
                  pixel_stride: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:  # fmt: skip
    """Valid pixels of ``depth [V,H,W]`` -> world points ``[N,3]`` f64, their view ``[N]`` and pixel footprint
    ``z / sqrt(fx * fy)`` ``[N]`` (metres per pixel at the point)."""
    _, H, W = depth.shape
    vs = np.arange(0, H, pixel_stride)
    us = np.arange(0, W, pixel_stride)
    sub = depth[:, vs][:, :, us]
    Kd, T = K.astype(np.float64), world_T_cam.astype(np.float64)
    world, views, foot = [], [], []
    for i in range(sub.shape[0]):  # one view at a time: its intrinsics and pose are scalars, not gathered per point
        iv, iu = np.nonzero(sub[i] > 0)
        z = sub[i][iv, iu].astype(np.float64)
        fx, fy, skew, cx, cy = Kd[i, 0, 0], Kd[i, 1, 1], Kd[i, 0, 1], Kd[i, 0, 2], Kd[i, 1, 2]
        y = (vs[iv] - cy) / fy
        x = (us[iu] - cx - skew * y) / fx
        cam = (x * z, y * z, z)
        w = np.empty((z.size, 3))
        for r in range(3):
            w[:, r] = T[i, r, 0] * cam[0] + T[i, r, 1] * cam[1] + T[i, r, 2] * cam[2] + T[i, r, 3]
        world.append(w)
        views.append(np.full(z.size, i, dtype=np.int64))
        foot.append(z / np.sqrt(fx * fy))
    if not world:
        return np.zeros((0, 3)), np.zeros((0,), np.int64), np.zeros((0,))
    return np.concatenate(world), np.concatenate(views), np.concatenate(foot)


def _footprint_xy(xy: np.ndarray, lo: np.ndarray, hi: np.ndarray, mode: str, round_inflate: float) -> _Pair:
    """xy extents of a component from its points ``xy [N,2]`` (see ``footprint`` / ``round_inflate``)."""
    import cv2

    pts = np.ascontiguousarray(xy, dtype=np.float32)
    if pts.shape[0] < 3:
        return lo, hi
    hull = cv2.convexHull(pts)
    (cx, cy), (w, h), ang = cv2.minAreaRect(hull)
    fill = float(cv2.contourArea(hull)) / (w * h) if w * h > 0 else 1.0
    if round_inflate != 1.0 and fill < _ROUND_FILL:
        c, half = (lo + hi) / 2, (hi - lo) / 2 * round_inflate
        return c - half, c + half
    if mode == "min_area_rect":
        corners = cv2.boxPoints(((cx, cy), (w, h), ang)).astype(np.float64)
        lo, hi = np.minimum(lo, corners.min(axis=0)), np.maximum(hi, corners.max(axis=0))
    return lo, hi


def _voxel_indices(pts: np.ndarray, bnd: _Pair | None, vs: float, dilation: int) -> _Pair:
    """Flat voxel index ``[N]`` of each point ``[N,3]`` in a grid of edge ``vs`` anchored at the bounds' minimum (or
    the points'), cut to the occupied sub-box plus ``dilation`` voxels, and that sub-box's shape ``[3]``.

    Raises:
        ValueError: the full grid would exceed ``_MAX_GRID_CELLS`` voxels (naming ``voxel_size``).
    """
    origin = bnd[0] if bnd is not None else pts.min(axis=0)
    ijk = np.floor((pts - origin) / vs).astype(np.int64)
    ijk = np.maximum(ijk, 0)
    shape = ijk.max(axis=0) + 1
    if bnd is not None:
        shape = np.minimum(shape, np.ceil((bnd[1] - bnd[0]) / vs).astype(np.int64))
        ijk = np.minimum(ijk, shape - 1)
    cells = int(np.prod(shape))
    if cells > _MAX_GRID_CELLS:
        raise ValueError(f"voxel_size: a grid of {shape.tolist()} voxels is too large ({cells} > {_MAX_GRID_CELLS}); "
                         "pass scene bounds or a larger voxel_size")
    lo_ijk = np.maximum(ijk.min(axis=0) - dilation, 0)
    ijk = ijk - lo_ijk
    shape = np.minimum(shape - lo_ijk, ijk.max(axis=0) + 1 + dilation)
    return np.ravel_multi_index(ijk.T, shape), shape


def _components(flat: np.ndarray, view: np.ndarray, n_views: int, shape: np.ndarray, min_views: int,
                dilation: int) -> tuple[np.ndarray, int, np.ndarray] | None:  # fmt: skip
    """Connected components of the voxels (of ``shape``, points' flat indices ``flat`` ``[N]`` and views ``view``
    ``[N]``) seen by at least ``min_views`` views: the label of every voxel (flat; 0 = unoccupied), the number of
    components and the occupied voxels' flat indices; ``None`` when there is none."""
    uniq_vox, views_per_vox = np.unique(np.unique(flat * n_views + view) // n_views, return_counts=True)
    occ_vox = uniq_vox[views_per_vox >= min_views]
    if occ_vox.size == 0:
        return None
    occ = np.zeros(int(np.prod(shape)), dtype=bool)
    occ[occ_vox] = True
    occ = occ.reshape(shape)
    struct = np.ones((3, 3, 3), dtype=bool)
    grown = ndimage.binary_dilation(occ, structure=struct, iterations=dilation) if dilation > 0 else occ
    labels_grid, n_comp = ndimage.label(grown, structure=struct)
    if n_comp == 0:
        return None
    return np.where(occ, labels_grid, 0).reshape(-1), n_comp, occ_vox


def _component_box(cp: np.ndarray, n: np.ndarray, d: float, min_height: float, p: ProposalParams) -> np.ndarray | None:
    """The axis-aligned box ``[6]`` of one component's points ``cp [N,3]`` (step 6), or ``None`` when its top is less
    than ``min_height`` above the ground plane ``n . x + d = 0`` under the box centre."""
    if p.extent_percentile > 0:
        lo = np.percentile(cp, p.extent_percentile, axis=0)
        hi = np.percentile(cp, 100 - p.extent_percentile, axis=0)
    else:
        lo, hi = cp.min(axis=0), cp.max(axis=0)
    if p.footprint == "min_area_rect" or p.round_inflate != 1.0:
        lo[:2], hi[:2] = _footprint_xy(cp[:, :2], lo[:2], hi[:2], p.footprint, p.round_inflate)
    lo[:2] -= p.xy_padding
    hi[:2] += p.xy_padding
    cx, cy = np.array((lo[0] + hi[0]) / 2), np.array((lo[1] + hi[1]) / 2)
    zg = float(-(n[0] * cx + n[1] * cy + d) / n[2])  # the ground plane's height under the box centre
    if hi[2] - zg < min_height:
        return None
    if p.extend_to_ground:
        lo[2] = min(lo[2], zg)
    return np.concatenate([lo, hi])


def _empty() -> _Pair:
    return np.zeros((0, 6), np.float32), np.zeros((0,), np.float32)


def propose_boxes(record: SceneRecord, *, bounds: Bounds | None = None, **params: Any) -> _Pair:
    """Class-agnostic 3D box proposals of one scene from its depth maps and poses (see the module docstring).

    Args:
        record: the scene (``depth`` ``[V,H,W]``, ``K`` ``[V,3,3]``, ``world_T_cam`` ``[V,4,4]``).
        bounds: scene bounds (``DatasetIndex.scene_bounds``); points outside are ignored. ``None``: no cropping.
        **params: the :class:`ProposalParams` fields to set.

    Returns ``aabb`` ``[P,6]`` float32 and ``scores`` ``[P]`` float32 in ``(0, 1]``, sorted by decreasing score;
    ``ValueError`` naming the field for malformed input (e.g. NaN depth) or parameters.

    Convention: depth is camera z-depth with 0 = invalid; OpenCV camera axes, ``world_T_cam`` camera-to-world;
    integer pixel centres.
    """
    p = ProposalParams(**params)
    _check_record(record)
    if p.align_floor:
        aligned = align_to_floor(record.depth, record.K, record.world_T_cam)
        record = dataclasses.replace(record, world_T_cam=aligned.world_T_cam)
    bnd = _check_bounds(bounds)
    views = np.arange(0, record.depth.shape[0], p.view_stride)
    depth, K, pose = record.depth[views], record.K[views], record.world_T_cam[views]
    n_views = len(views)
    pts, view, zf = _world_points(depth, K, pose, p.pixel_stride)
    if pts.shape[0] < 3:
        return _empty()
    plane = fit_ground_plane(pts, camera_centres=pose[:, :3, 3].astype(np.float64), iters=p.ransac_iters,
                             threshold=p.ransac_threshold, max_tilt_deg=p.max_ground_tilt_deg, sample=p.ransac_sample,
                             seed=p.seed)  # fmt: skip
    if plane is None:
        return _empty()
    n, d, _ = plane
    height = pts @ n + d
    margin = p.ground_margin
    if margin is None:  # the ground's own spread about the plane (0 for exact depth)
        margin = max(p.min_ground_margin, 3.0 * ground_spread(height, p.ransac_threshold))
    min_height = margin + p.min_rise if p.min_height is None else p.min_height
    keep = height > margin
    if bnd is not None:
        keep &= np.all((pts >= bnd[0]) & (pts <= bnd[1]), axis=1)
    pts, view, zf = pts[keep], view[keep], zf[keep]
    if pts.shape[0] == 0:
        return _empty()
    vs = max(p.voxel_size, p.min_voxel_pixels * p.pixel_stride * float(np.median(zf)))
    flat, shape = _voxel_indices(pts, bnd, vs, p.dilation)
    comps = _components(flat, view, n_views, shape, min(p.min_views, n_views), p.dilation)
    if comps is None:
        return _empty()
    labels_grid, n_comp, occ_vox = comps
    point_label = labels_grid[flat]  # 0 for points in unoccupied (rejected) voxels
    sel = np.nonzero(point_label > 0)[0]
    order = sel[np.argsort(point_label[sel], kind="stable")]
    point_label, pts_l, view_l = point_label[order], pts[order], view[order]
    vox_count = np.bincount(labels_grid[occ_vox], minlength=n_comp + 1)
    starts = np.searchsorted(point_label, np.arange(1, n_comp + 2))
    boxes, scores = [], []
    for lab in range(1, n_comp + 1):
        s0, s1 = starts[lab - 1], starts[lab]
        if s1 <= s0 or vox_count[lab] < p.min_component_voxels:
            continue
        box = _component_box(pts_l[s0:s1], n, d, min_height, p)
        if box is not None:
            seen = np.unique(view_l[s0:s1]).size / n_views
            size_factor = 1.0 - math.exp(-vox_count[lab] / p.score_voxel_scale)
            boxes.append(box)
            scores.append(max(seen * size_factor, 1e-6))
    if not boxes:
        return _empty()
    aabb = np.asarray(boxes, dtype=np.float32)
    sc = np.asarray(scores, dtype=np.float32)
    order = np.argsort(-sc, kind="stable")
    return aabb[order], sc[order]
