"""Class-agnostic, label-free 3D box proposals from posed multi-view depth.

The paper triangulates COCO-trained 2D proposals; we have no pretrained weights, so proposals come from
geometry alone: objects are whatever sticks out of the ground plane inside the scene bounds.

Pipeline of :func:`propose_boxes` (only ``depth``, ``K``, ``world_T_cam`` and the scene bounds are used;
``rgb`` only for a shape check; never ``instance``, ``boxes`` or ``categories``):

1. back-project the valid depth pixels of a subset of views (``view_stride``, ``pixel_stride``) into the
   world frame;
2. fit the ground plane with RANSAC: the plane with the most inliers among hypotheses whose normal is
   within ``max_ground_tilt_deg`` of world +z (seeded, deterministic), refined by least squares on its
   inliers and oriented so the cameras lie above it. The plane need not be ``z = 0``;
3. keep the points more than ``ground_margin`` above the plane and inside the scene bounds (or, ``None``, a margin
   measured per scene: three robust standard deviations of the ground points' heights, at least
   ``min_ground_margin``);
4. voxelise them (``voxel_size``, raised to ``min_voxel_pixels`` pixel footprints for coarse depth maps);
   keep voxels seen by at least ``min_views`` distinct views (a real
   surface is seen from several cameras; depth noise and stray pixels are not);
5. 3D connected components (26-connectivity, after a ``dilation`` of the occupancy by that many voxels
   that bridges the gaps between thin parts of one object, e.g. an airplane's wings and wheels; the
   boxes come from the undilated voxels' points);
6. each component -> an axis-aligned box: z from its points' ``[extent_percentile, 100 -
   extent_percentile]`` percentiles, extended down to the ground plane under the box centre (prior:
   objects rest on the ground, so their unseen, margin-removed bottom reaches it); x, y from the
   footprint (the xy points):

   - ``footprint="min_area_rect"``: the axis-aligned hull of the footprint's minimum-area rectangle
     (an estimate of the object's yawed box; ground-truth boxes are yawed boxes, so their axis-aligned
     hull is larger than the points' extents for elongated, non-box-like shapes);
   - ``footprint="aabb"``: the points' percentile extents;
   - a *round* footprint (convex hull fills less than 0.85 of its min-area rectangle: spheres,
     cylinders, ...) has no visible yaw; its xy extents are scaled by ``round_inflate`` about the centre
     instead (the hull of a box of unknown yaw around a disc is 1 to sqrt(2) times the disc's extent);

   then grown by ``xy_padding``. Components with fewer than ``min_component_voxels`` voxels, or whose
   top is less than ``min_height`` above the ground, are dropped;
7. score in (0, 1]: the fraction of the used views that see the component (contribute at least one point
   to it) times ``1 - exp(-voxels / score_voxel_scale)`` (small components rank below large ones).
   Proposals are sorted by decreasing score; no NMS is needed (components are disjoint).

Touching objects are not split (one component, one box). ``dilation``, ``footprint="min_area_rect"`` and
``round_inflate`` are what round objects and objects of thin parts (a toy airplane) need; the defaults are tuned on
the embedded data (AP@0.5 of the pseudo-boxes against the GT boxes' hulls).

:func:`threedq.data.proposal_cache.propose_dataset` runs this over a split of a dataset folder and caches
the result in a box file (:mod:`threedq.data.box_files`).

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
from threedq.scene import SceneRecord

__all__ = ["PROPOSALS_VERSION", "ProposalParams", "fit_ground_plane", "propose_boxes"]

#: Bump when equal parameters would give different proposals (caches of older versions are recomputed).
PROPOSALS_VERSION = 1
_MAX_GRID_CELLS = 64_000_000
_ROUND_FILL = 0.85  # convex-hull area / min-area-rectangle area below which a footprint counts as round

_FOOTPRINTS = ("aabb", "min_area_rect")
Bounds = tuple[tuple[float, float, float], tuple[float, float, float]]


@dataclass(frozen=True)
class ProposalParams:
    """The keyword parameters of :func:`propose_boxes` (defaults tuned on the embedded data).

    Attributes:
        view_stride: use views ``0, s, 2s, ...``.
        pixel_stride: use every ``s``-th pixel row and column.
        voxel_size: voxel edge, metres (at least; see ``min_voxel_pixels``).
        min_voxel_pixels: the voxel edge is raised to this many pixel footprints when the depth maps are
            coarse: ``max(voxel_size, min_voxel_pixels * pixel_stride * median(z / f))`` over the
            above-ground points (``z`` their depth, ``f`` the focal length in pixels), so that views'
            samples of a surface still fall in shared voxels. 0 = always ``voxel_size``.
        ground_margin: points less than this above the ground plane (or below it) are ground. ``None``:
            measured per scene, ``max(min_ground_margin, 3 sigma)`` with ``sigma`` the robust spread of the ground
            points' heights about the fitted plane (:func:`~threedq.geometry.ground.ground_spread`): the ground's
            own thickness in the depth maps, so a clean depth map (a renderer's) keeps objects 1-2 cm tall and a
            noisy sensor's floor stays ground. The observed boxes a detector is refined against use it
            (:data:`threedq.box_refinement.OBSERVED_PARAMS`; ``docs/studies/detector.md``); the training pseudo-boxes
            keep the fixed 1.5 cm (the detector ignores boxes flatter than its ``min_box_height`` in any case).
        min_ground_margin: the least measured ground margin, metres.
        ransac_iters, ransac_threshold, ransac_sample, max_ground_tilt_deg: ground-plane RANSAC
            (see :func:`fit_ground_plane`).
        min_views: a voxel counts as occupied when points of at least this many views fall in it (at most the
            number of views used).
        dilation: voxels of binary dilation before labelling components (bridges gaps; 0 = none).
        min_component_voxels: smaller components are dropped.
        min_height: components whose top is less than this above the ground plane (under the box centre)
            are dropped. ``None``: the ground margin used plus ``min_rise``.
        min_rise: see ``min_height``.
        extent_percentile: per-axis percentile of the points used as the box extents (0 = min/max).
        xy_padding: the box grows by this much on each side in x and y, metres.
        footprint: ``"min_area_rect"`` (axis-aligned hull of the footprint's minimum-area rectangle) or
            ``"aabb"`` (the points' extents) for x and y.
        round_inflate: scale of the xy extents of round footprints (1 = none), see the module docstring.
        extend_to_ground: extend each box's ``zmin`` down to the ground plane under its centre.
        score_voxel_scale: voxel count at which the size factor of the score is ``1 - 1/e``.
        align_floor: first correct the poses by the floor each view sees
            (:func:`~threedq.geometry.floor_alignment.align_to_floor`: a tracker's tilt and height errors), for
            sensor captures; the boxes are then in the corrected frame, as the DataModule's samples are.
        seed: RANSAC seed.

    Convention: lengths in metres, angles in degrees, world z up.
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

    def __post_init__(self) -> None:
        def put(name: str, value: Any) -> None:  # normalise types so equal settings compare (and cache) equal
            object.__setattr__(self, name, value)

        for name, low in (("view_stride", 1), ("pixel_stride", 1), ("ransac_iters", 1), ("ransac_sample", 3),
                          ("min_views", 1), ("dilation", 0), ("min_component_voxels", 0), ("seed", 0)):  # fmt: skip
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, (int, np.integer)) or v < low:
                raise ValueError(f"{name}: expected an int >= {low}, got {v!r}")
            put(name, int(v))
        # (name, low, low inclusive, high, high inclusive)
        ranges = (
            ("voxel_size", 0.0, False, math.inf, False),
            ("ransac_threshold", 0.0, False, math.inf, False),
            ("score_voxel_scale", 0.0, False, math.inf, False),
            ("min_voxel_pixels", 0.0, True, math.inf, False),
            ("ground_margin", 0.0, True, math.inf, False),
            ("min_ground_margin", 0.0, True, math.inf, False),
            ("min_height", 0.0, True, math.inf, False),
            ("min_rise", 0.0, True, math.inf, False),
            ("xy_padding", 0.0, True, math.inf, False),
            ("extent_percentile", 0.0, True, 50.0, False),
            ("max_ground_tilt_deg", 0.0, False, 90.0, True),
            ("round_inflate", 1.0, True, 2.0, True),
        )
        for name, lo, lo_inc, hi, hi_inc in ranges:
            v = getattr(self, name)
            if v is None and name in ("ground_margin", "min_height"):  # measured per scene (see propose_boxes)
                continue
            ok = not isinstance(v, bool) and isinstance(v, (int, float, np.integer, np.floating)) and math.isfinite(v)
            ok = ok and (v >= lo if lo_inc else v > lo) and (v <= hi if hi_inc else v < hi)
            if not ok:
                interval = f"{'[' if lo_inc else '('}{lo:g}, {hi:g}{']' if hi_inc else ')'}"
                raise ValueError(f"{name}: expected a finite number in {interval}, got {v!r}")
            put(name, float(v))
        if self.footprint not in _FOOTPRINTS:
            raise ValueError(f"footprint: expected one of {_FOOTPRINTS}, got {self.footprint!r}")
        for name in ("extend_to_ground", "align_floor"):
            if not isinstance(getattr(self, name), bool):
                raise ValueError(f"{name}: expected a bool, got {getattr(self, name)!r}")  # noqa: TRY004 - ValueError naming the field


# --------------------------------------------------------------------------------------------------
# input checks
# --------------------------------------------------------------------------------------------------
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


def _check_bounds(bounds: Any) -> tuple[np.ndarray, np.ndarray] | None:
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


# --------------------------------------------------------------------------------------------------
# geometry
# --------------------------------------------------------------------------------------------------
def _world_points(
    depth: np.ndarray, K: np.ndarray, world_T_cam: np.ndarray, pixel_stride: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Valid pixels of ``depth [V,H,W]`` -> world points ``[N,3]`` f64, their view ``[N]`` and pixel footprint.

    The footprint is ``z / sqrt(fx * fy)`` ``[N]``, metres per pixel at the point.
    """
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


def _plane_z(n: np.ndarray, d: float, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Height ``z`` of the plane ``n . p + d = 0`` above ``(x, y)`` (requires ``n_z != 0``)."""
    return -(n[0] * x + n[1] * y + d) / n[2]


# --------------------------------------------------------------------------------------------------
# proposals
# --------------------------------------------------------------------------------------------------
def _footprint_xy(
    xy: np.ndarray, lo: np.ndarray, hi: np.ndarray, mode: str, round_inflate: float
) -> tuple[np.ndarray, np.ndarray]:
    """xy extents of a component from its points ``xy [N,2]`` (see ``footprint`` / ``round_inflate``)."""
    import cv2

    pts = np.ascontiguousarray(xy, dtype=np.float32)
    if pts.shape[0] < 3:
        return lo, hi
    hull = cv2.convexHull(pts)
    (cx, cy), (w, h), ang = cv2.minAreaRect(hull)
    fill = float(cv2.contourArea(hull)) / (w * h) if w * h > 0 else 1.0
    if round_inflate != 1.0 and fill < _ROUND_FILL:
        # a round footprint (its convex hull fills ~pi/4 of its min-area rectangle) hides the object's yaw;
        # the hull of a yawed box around it is on average larger than the points' extents
        c, half = (lo + hi) / 2, (hi - lo) / 2 * round_inflate
        return c - half, c + half
    if mode == "min_area_rect":
        corners = cv2.boxPoints(((cx, cy), (w, h), ang)).astype(np.float64)
        lo, hi = np.minimum(lo, corners.min(axis=0)), np.maximum(hi, corners.max(axis=0))
    return lo, hi


def _propose(
    record: SceneRecord, bnd: tuple[np.ndarray, np.ndarray] | None, p: ProposalParams
) -> tuple[np.ndarray, np.ndarray]:
    """:func:`propose_boxes` of a checked record with checked bounds ``bnd`` and parameters ``p``."""
    views = np.arange(0, record.depth.shape[0], p.view_stride)
    depth, K, pose = record.depth[views], record.K[views], record.world_T_cam[views]
    n_views = len(views)
    pts, view, zf = _world_points(depth, K, pose, p.pixel_stride)
    if pts.shape[0] < 3:
        return _empty()

    plane = fit_ground_plane(
        pts, camera_centres=pose[:, :3, 3].astype(np.float64), iters=p.ransac_iters,
        threshold=p.ransac_threshold, max_tilt_deg=p.max_ground_tilt_deg, sample=p.ransac_sample, seed=p.seed,
    )  # fmt: skip
    if plane is None:
        return _empty()
    n, d, _ = plane
    pts, view, zf, min_height = _above_ground(pts, view, zf, n, d, bnd, p)
    if pts.shape[0] == 0:
        return _empty()
    vs = max(p.voxel_size, p.min_voxel_pixels * p.pixel_stride * float(np.median(zf)))
    flat, shape = _voxel_indices(pts, bnd, vs, p.dilation)
    comps = _components(flat, view, n_views, shape, min(p.min_views, n_views), p.dilation)
    if comps is None:
        return _empty()
    labels_grid, n_comp, occ_vox = comps
    return _component_boxes(pts, view, flat, labels_grid, n_comp, occ_vox, n_views, n, d, min_height, p)


def _component_boxes(
    pts: np.ndarray, view: np.ndarray, flat: np.ndarray, labels_grid: np.ndarray, n_comp: int, occ_vox: np.ndarray,
    n_views: int, n: np.ndarray, d: float, min_height: float, p: ProposalParams,
) -> tuple[np.ndarray, np.ndarray]:
    """One box per large enough component that rises ``min_height`` above the ground (steps 6-7), sorted by
    decreasing score: ``aabb`` ``[P,6]`` and ``scores`` ``[P]`` float32.

    Args:
        pts: ``[N,3]`` above-ground points; ``view`` ``[N]`` their view index; ``flat`` ``[N]`` their flat voxel
            index; ``labels_grid`` the voxels' component labels (0 = none); ``occ_vox`` the occupied voxels.
    """
    point_label = labels_grid[flat]  # 0 for points in unoccupied (rejected) voxels
    sel = point_label > 0
    point_label, pts_l, view_l = point_label[sel], pts[sel], view[sel]
    vox_count = np.bincount(labels_grid[occ_vox], minlength=n_comp + 1)
    order = np.argsort(point_label, kind="stable")
    point_label, pts_l, view_l = point_label[order], pts_l[order], view_l[order]
    starts = np.searchsorted(point_label, np.arange(1, n_comp + 2))

    boxes, scores = [], []
    for lab in range(1, n_comp + 1):
        s0, s1 = starts[lab - 1], starts[lab]
        if s1 <= s0 or vox_count[lab] < p.min_component_voxels:
            continue
        box = _component_box(pts_l[s0:s1], view_l[s0:s1], vox_count[lab], n_views, n, d, min_height, p)
        if box is not None:
            boxes.append(box[0])
            scores.append(box[1])
    if not boxes:
        return _empty()
    aabb = np.asarray(boxes, dtype=np.float32)
    sc = np.asarray(scores, dtype=np.float32)
    order = np.argsort(-sc, kind="stable")
    return aabb[order], sc[order]


def _above_ground(
    pts: np.ndarray, view: np.ndarray, zf: np.ndarray, n: np.ndarray, d: float,
    bnd: tuple[np.ndarray, np.ndarray] | None, p: ProposalParams,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, float]:
    """The points above the ground margin and inside the bounds (step 3 of the module docstring).

    Args:
        pts: ``[N,3]`` world points; ``view`` ``[N]`` their view index; ``zf`` ``[N]`` their depth over the focal
            length (metres per pixel).
        n, d: the ground plane ``n . x + d = 0`` (``n`` ``[3]`` unit, pointing up).
        bnd: the scene bounds, or ``None``.

    Returns:
        The kept ``pts``, ``view`` and ``zf``, and the least height of a component's top (``min_height``, or the
        ground margin used plus ``min_rise``).
    """
    height = pts @ n + d
    margin = p.ground_margin
    if margin is None:  # the ground's own spread about the plane (0 for exact depth)
        margin = max(p.min_ground_margin, 3.0 * ground_spread(height, p.ransac_threshold))
    min_height = margin + p.min_rise if p.min_height is None else p.min_height
    keep = height > margin
    if bnd is not None:
        keep &= np.all((pts >= bnd[0]) & (pts <= bnd[1]), axis=1)
    return pts[keep], view[keep], zf[keep], min_height


def _voxel_indices(
    pts: np.ndarray, bnd: tuple[np.ndarray, np.ndarray] | None, vs: float, dilation: int
) -> tuple[np.ndarray, np.ndarray]:
    """Voxel of each point ``[N,3]`` in a grid of edge ``vs`` anchored at the bounds' minimum (or the points').

    The grid is cut to the occupied sub-box plus ``dilation`` voxels: components and boxes do not depend on the
    empty voxels around it, and dilating and labelling the whole bounds' grid would dominate the cost.

    Returns:
        The points' flat voxel indices ``[N]`` and the sub-box's shape ``[3]``.

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
        raise ValueError(
            f"voxel_size: a grid of {shape.tolist()} voxels is too large ({cells} > {_MAX_GRID_CELLS}); "
            "pass scene bounds or a larger voxel_size"
        )
    lo_ijk = np.maximum(ijk.min(axis=0) - dilation, 0)
    ijk = ijk - lo_ijk
    shape = np.minimum(shape - lo_ijk, ijk.max(axis=0) + 1 + dilation)
    return np.ravel_multi_index(ijk.T, shape), shape


def _components(
    flat: np.ndarray, view: np.ndarray, n_views: int, shape: np.ndarray, min_views: int, dilation: int
) -> tuple[np.ndarray, int, np.ndarray] | None:
    """Connected components of the voxels seen by at least ``min_views`` distinct views (steps 4-5).

    Args:
        flat: ``[N]`` flat voxel index of each point in a grid of ``shape``; ``view`` ``[N]`` its view index.

    Returns:
        The component label of every voxel (flat ``[cells]``; 0 = unoccupied, including voxels only the
        dilation filled), the number of components and the occupied voxels' flat indices; ``None`` when no
        voxel is occupied or no component is found.
    """
    cells = int(np.prod(shape))
    pairs = np.unique(flat * n_views + view)
    vox_of_pair = pairs // n_views
    uniq_vox, views_per_vox = np.unique(vox_of_pair, return_counts=True)
    occ_vox = uniq_vox[views_per_vox >= min_views]
    if occ_vox.size == 0:
        return None
    occ = np.zeros(cells, dtype=bool)
    occ[occ_vox] = True
    occ = occ.reshape(shape)
    struct = np.ones((3, 3, 3), dtype=bool)
    grown = ndimage.binary_dilation(occ, structure=struct, iterations=dilation) if dilation > 0 else occ
    labels_grid, n_comp = ndimage.label(grown, structure=struct)
    if n_comp == 0:
        return None
    return np.where(occ, labels_grid, 0).reshape(-1), n_comp, occ_vox


def _component_box(
    cp: np.ndarray, cview: np.ndarray, voxels: int, n_views: int, n: np.ndarray, d: float, min_height: float,
    p: ProposalParams,
) -> tuple[np.ndarray, float] | None:
    """The axis-aligned box ``[6]`` and score of one component (steps 6-7), or ``None`` when its top is less than
    ``min_height`` above the ground plane ``n . x + d = 0`` under the box centre.

    Args:
        cp: ``[N,3]`` the component's points; ``cview`` ``[N]`` their view indices; ``voxels`` its voxel count.
    """
    if p.extent_percentile > 0:
        lo = np.percentile(cp, p.extent_percentile, axis=0)
        hi = np.percentile(cp, 100 - p.extent_percentile, axis=0)
    else:
        lo, hi = cp.min(axis=0), cp.max(axis=0)
    if p.footprint == "min_area_rect" or p.round_inflate != 1.0:
        lo[:2], hi[:2] = _footprint_xy(cp[:, :2], lo[:2], hi[:2], p.footprint, p.round_inflate)
    lo[:2] -= p.xy_padding
    hi[:2] += p.xy_padding
    zg = float(_plane_z(n, d, np.array((lo[0] + hi[0]) / 2), np.array((lo[1] + hi[1]) / 2)))
    if hi[2] - zg < min_height:
        return None
    if p.extend_to_ground:
        lo[2] = min(lo[2], zg)
    seen = np.unique(cview).size / n_views
    size_factor = 1.0 - math.exp(-voxels / p.score_voxel_scale)
    return np.concatenate([lo, hi]), max(seen * size_factor, 1e-6)


def _empty() -> tuple[np.ndarray, np.ndarray]:
    return np.zeros((0, 6), np.float32), np.zeros((0,), np.float32)


def propose_boxes(record: SceneRecord, *, bounds: Bounds | None = None, **params: Any) -> tuple[np.ndarray, np.ndarray]:
    """Class-agnostic 3D box proposals of one scene from its depth maps and poses (see the module docstring).

    Args:
        record: the scene; only ``depth`` ``[V,H,W]``, ``K`` ``[V,3,3]`` and ``world_T_cam`` ``[V,4,4]`` are read
            (``rgb`` only for a shape check). Labels (``instance``, ``boxes``, ``categories``) are never read.
        bounds: ``((xmin, ymin, zmin), (xmax, ymax, zmax))`` scene bounds (``DatasetIndex.scene_bounds``);
            points outside are ignored. ``None``: no cropping (the grid spans the above-ground points).
        **params: the :class:`ProposalParams` fields to set (the others at their defaults).

    Returns:
        ``aabb`` ``[P,6]`` float32 ``(xmin, ymin, zmin, xmax, ymax, zmax)`` and ``scores`` ``[P]`` float32 in
        ``(0, 1]``, sorted by decreasing score. A scene without valid depth, or without a ground plane,
        or with nothing above it gives ``P = 0``.

    Raises:
        ValueError: naming the field, for malformed input (e.g. NaN depth) or parameters.

    Convention: world frame in metres, z up; depth is camera z-depth with 0 = invalid; OpenCV camera
    axes, ``world_T_cam`` camera-to-world; integer pixel centres.
    """
    p = ProposalParams(**params)
    _check_record(record)
    if p.align_floor:
        record = dataclasses.replace(record, world_T_cam=align_to_floor(record.depth, record.K,
                                                                        record.world_T_cam).world_T_cam)
    return _propose(record, _check_bounds(bounds), p)
