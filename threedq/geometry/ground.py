"""The ground plane of a scene from its depth alone (label-free), and which pixels lie above it.

Convention:
    Metres; the reference frame R is right-handed with z up. A plane is ``n . p + d = 0`` with unit normal
    ``n`` pointing up (towards the cameras); the signed height of a point ``p`` above it is ``n . p + d``.
    Cameras use OpenCV axes; ``R_T_cam`` maps camera points to R.
"""

from __future__ import annotations

import math

import numpy as np
import torch
from torch import Tensor

from .camera import depth_to_points

__all__ = ["above_ground_mask", "fit_ground_plane", "ground_spread"]


def fit_ground_plane(points: np.ndarray, *, camera_centres: np.ndarray | None = None, iters: int = 200,
                     threshold: float = 0.01, max_tilt_deg: float = 30.0, sample: int = 20000,
                     seed: int = 0) -> tuple[np.ndarray, float, int] | None:
    """RANSAC fit of the dominant near-horizontal plane ``n . p + d = 0``.

    Args:
        points: ``[N,3]`` world points.
        camera_centres: ``[C,3]``; when given, the normal is flipped so most cameras lie on its positive side
            (above the plane); otherwise it points towards +z.
        iters: hypotheses (3-point samples).
        threshold: inlier distance, metres.
        max_tilt_deg: hypotheses whose normal is further than this from +z are rejected.
        sample: the hypotheses are scored on at most this many random points.
        seed: RNG seed (the fit is deterministic for equal inputs).

    Returns:
        ``(n [3] unit normal, d, inliers)`` (``inliers`` counted on the scored sample), or ``None`` when no
        valid hypothesis exists (fewer than 3 points, or all candidate planes too tilted).

    Convention: world frame, z up; signed height of ``p`` above the plane is ``n . p + d``.
    """
    pts = np.asarray(points, dtype=np.float64)
    if pts.ndim != 2 or pts.shape[1] != 3:
        raise ValueError(f"points: expected shape [N,3], got {list(pts.shape)}")
    if pts.shape[0] < 3:
        return None
    rng = np.random.default_rng(seed)
    eval_pts = pts if pts.shape[0] <= sample else pts[rng.choice(pts.shape[0], sample, replace=False)]
    idx = rng.integers(0, eval_pts.shape[0], size=(iters, 3))
    a, b, c = eval_pts[idx[:, 0]], eval_pts[idx[:, 1]], eval_pts[idx[:, 2]]
    n = np.cross(b - a, c - a)
    norm = np.linalg.norm(n, axis=1)
    ok = norm > 1e-12
    n[ok] /= norm[ok, None]
    n[n[:, 2] < 0] *= -1
    ok &= n[:, 2] >= math.cos(math.radians(max_tilt_deg)) - 1e-12
    if not np.any(ok):
        return None
    n, a = n[ok], a[ok]
    d = -np.einsum("ij,ij->i", n, a)
    counts = np.zeros(n.shape[0], dtype=np.int64)
    chunk = max(1, 4_000_000 // max(eval_pts.shape[0], 1))
    for s in range(0, n.shape[0], chunk):
        dist = n[s : s + chunk] @ eval_pts.T  # [hypotheses, points]: each hypothesis's count is a contiguous row
        dist += d[s : s + chunk, None]
        np.abs(dist, out=dist)
        counts[s : s + chunk] = np.count_nonzero(dist <= threshold, axis=1)
    best = int(np.argmax(counts))  # first maximum: deterministic
    nb, db = n[best], float(d[best])
    # least-squares refinement on the inliers of all points (two rounds)
    for _ in range(2):
        inl = pts[np.abs(pts @ nb + db) <= threshold]
        if inl.shape[0] < 3:
            break
        centroid = inl.mean(axis=0)
        centred = inl - centroid
        # the normal: the scatter matrix's eigenvector of the least eigenvalue
        cand = np.linalg.eigh(centred.T @ centred)[1][:, 0]
        if cand[2] < 0:
            cand = -cand
        if cand[2] < math.cos(math.radians(max_tilt_deg)) - 1e-12:
            break
        nb, db = cand, float(-cand @ centroid)
    if camera_centres is not None and camera_centres.size:
        side = camera_centres @ nb + db
        if np.count_nonzero(side < 0) > np.count_nonzero(side > 0):
            nb, db = -nb, -db
    return nb, db, int(counts[best])


def ground_spread(heights: np.ndarray, threshold: float) -> float:
    """Robust standard deviation of the ground points' heights about a fitted plane.

    Args:
        heights: ``[N]`` signed heights of points above the plane (``n . p + d``), metres.
        threshold: the points within this of the plane are the ground (the RANSAC inlier distance).

    Returns:
        ``1.4826 * median(|h - median(h)|)`` over the ground points; 0.0 when there are none.

    Convention: metres, heights along the plane's upward normal.
    """
    h = np.asarray(heights, dtype=np.float64).reshape(-1)
    h = h[np.abs(h) <= threshold]
    if h.size == 0:
        return 0.0
    return float(1.4826 * np.median(np.abs(h - np.median(h))))


@torch.no_grad()
def above_ground_mask(depth: Tensor, K: Tensor, R_T_cam: Tensor, *, margin: float = 0.02, fit_stride: int = 4,
                      iters: int = 100, sample: int = 2000, max_tilt_deg: float = 30.0, seed: int = 0,
                      views: slice = slice(None)) -> Tensor:
    """Pixels whose observed surface lies more than ``margin`` above the scene's ground plane.

    Per scene, the ground plane is fitted with RANSAC (:func:`fit_ground_plane`) to the back-projected depth of
    all ``S`` views (every ``fit_stride``-th pixel in x and y), oriented towards the cameras. A scene with no
    acceptable plane has no ground: all its valid pixels count as above it.

    Args:
        depth: ``[B, S, H, W]`` metric z-depth, 0 (or non-finite) = invalid.
        K: ``[B, S, 3, 3]`` pinhole intrinsics.
        R_T_cam: ``[B, S, 4, 4]`` camera-to-R poses.
        margin: minimum height above the plane, metres.
        fit_stride: pixel stride of the points the plane is fitted to.
        iters, sample, max_tilt_deg, seed: RANSAC settings (see :func:`fit_ground_plane`).
        views: the views whose pixels are tested (the plane is fitted to all ``S`` either way).

    Returns:
        ``[B, S', H, W]`` bool for the ``S'`` views of ``views`` (all ``S`` by default): valid depth and height
        above the fitted plane ``> margin``.

    Raises:
        ValueError: if the shapes do not agree.

    Convention:
        z-depth, OpenCV camera axes, R z up; the fit runs in float64 on the CPU (deterministic for equal inputs).
    """
    if depth.ndim != 4 or K.shape != (*depth.shape[:2], 3, 3) or R_T_cam.shape != (*depth.shape[:2], 4, 4):
        raise ValueError(f"depth, K, R_T_cam must be [B, S, H, W], [B, S, 3, 3], [B, S, 4, 4]; got "
                         f"{tuple(depth.shape)}, {tuple(K.shape)}, {tuple(R_T_cam.shape)}")
    if fit_stride < 1:
        raise ValueError(f"fit_stride must be >= 1, got {fit_stride}")
    B, s = depth.shape[0], fit_stride
    # pixel (s*i, s*j) of the full image is pixel (i, j) of the strided one: u' = u / s
    k_strided = K * torch.tensor([1.0 / s, 1.0 / s, 1.0], dtype=K.dtype, device=K.device)[:, None]
    fit_pts, fit_ok = depth_to_points(depth[:, :, ::s, ::s].flatten(0, 1).contiguous(), k_strided.flatten(0, 1),
                                      R_T_cam.flatten(0, 1))
    fit_pts, fit_ok = fit_pts.view(B, -1, 3), fit_ok.view(B, -1)
    tested = depth[:, views]
    points, ok = depth_to_points(tested.flatten(0, 1), K[:, views].flatten(0, 1), R_T_cam[:, views].flatten(0, 1))
    points, ok = points.view(*tested.shape, 3), ok.view(tested.shape)
    masks = []
    for b in range(B):
        plane = fit_ground_plane(fit_pts[b][fit_ok[b]].double().cpu().numpy(),
                                 camera_centres=R_T_cam[b, :, :3, 3].double().cpu().numpy(), iters=iters,
                                 threshold=0.01, max_tilt_deg=max_tilt_deg, sample=sample, seed=seed)
        if plane is None:
            masks.append(ok[b])
            continue
        n, d, _ = plane
        height = points[b].double() @ torch.as_tensor(n, dtype=torch.float64, device=depth.device) + d
        masks.append(ok[b] & (height > margin))
    return torch.stack(masks)
