"""Unprojection of posed RGB-D views into a voxel grid: colour, occupancy and free space.

Convention:
    Grid in the reference frame R (metres, z up), volumes ``[B, C, Z, Y, X]``, cell-centred voxels.
    Views: OpenCV camera axes, ``K`` with integer pixel centres (skew honoured), pose ``R_T_cam`` (camera-to-R),
    metric z-depth with 0 = invalid.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor

from .camera import _check_view, depth_to_points, invert_rigid, project, transform_points, unproject_depth
from .grid import VoxelGridSpec, _check_grid

__all__ = ["free_space_from_depth", "occupancy_from_depth", "sample_image_at_points", "unproject_rgb",
           "unproject_rgbd_occupied"]

#: Voxels whose camera depth is at most this (metres) count as behind the camera.
BEHIND_EPS = 1e-4


def _check_depth_view(depth: Tensor, K: Tensor, R_T_cam: Tensor, grid: VoxelGridSpec) -> None:
    _check_grid(grid)
    if depth.ndim != 3 or not depth.is_floating_point():
        raise ValueError(f"depth must be a float tensor of shape [B, H, W], got {tuple(depth.shape)} {depth.dtype}")
    _check_view(K, R_T_cam, depth.shape[0])


def _voxelize(points: Tensor, keep: Tensor, grid: VoxelGridSpec) -> Tensor:
    """Scatter points into a 0/1 volume: cell ``floor((p - bounds_min) / voxel_size)``; points outside the grid or
    not finite are dropped.

    Args:
        points: ``[B, N, 3]`` points in R.
        keep: ``[B, N]`` bool, points to use.
        grid: the voxel grid.

    Returns:
        ``[B, 1, Z, Y, X]`` volume (dtype of ``points``), 1 where at least one kept point falls in the voxel.
    """
    batch = points.shape[0]
    nx, ny, nz = grid.resolution
    n_vox = nx * ny * nz
    dump = batch * n_vox  # one extra slot collects the dropped points, avoiding a data-dependent mask
    index_dtype = torch.int32 if dump < 2**31 - 1 else torch.int64
    lo = torch.tensor(grid.bounds_min, device=points.device, dtype=points.dtype)
    size = torch.tensor(grid.voxel_size, device=points.device, dtype=points.dtype)
    flat = torch.arange(batch, device=points.device, dtype=index_dtype)[:, None] * n_vox
    for axis, (n, stride) in enumerate(zip(grid.resolution, (1, nx, nx * ny), strict=True)):
        cell = torch.floor((points[..., axis] - lo[axis]) / size[axis])  # [B, N]
        keep = keep & (cell >= 0) & (cell < n)  # NaN compares false: dropped
        cell = cell.clamp_(0, n - 1).to(index_dtype)  # finite and in range wherever kept
        flat = flat + cell * stride
    flat = torch.where(keep, flat, torch.full_like(flat, dump))
    out = torch.zeros(dump + 1, device=points.device, dtype=points.dtype)
    out[flat.flatten()] = 1.0
    return out[:dump].view(batch, 1, nz, ny, nx)


def unproject_rgb(rgb: Tensor, K: Tensor, R_T_cam: Tensor, grid: VoxelGridSpec) -> Tensor:
    """Gather-unproject an image into a voxel grid: every voxel centre, projected, bilinearly samples the image.

    Args:
        rgb: ``[B, C, H, W]`` float image (C = 3 for RGB; any C works).
        K: ``[B, 3, 3]`` pinhole intrinsics.
        R_T_cam: ``[B, 4, 4]`` camera-to-R poses.
        grid: the voxel grid in R.

    Returns:
        ``[B, C, Z, Y, X]`` volume. Voxels with camera depth ``z <= 1e-4`` (behind the camera) or whose
        projection falls outside the image footprint ``u in [-0.5, W - 0.5]``, ``v in [-0.5, H - 0.5]`` are
        zero. Inside the footprint, sampling is bilinear with border clamping (the half-pixel rim takes the
        edge pixel's value). Differentiable w.r.t. ``rgb``.

    Convention:
        OpenCV camera axes, integer pixel centres (pixel u -> normalised ``(2u + 1) / W - 1``,
        ``align_corners=False``), ``R_T_cam`` maps camera to R; cell-centred voxels.
    """
    _check_grid(grid)
    if rgb.ndim != 4:
        raise ValueError(f"rgb must have shape [B, C, H, W], got {tuple(rgb.shape)}")
    batch, channels = rgb.shape[:2]
    centres = grid.voxel_centres(device=rgb.device, dtype=rgb.dtype).reshape(1, -1, 3).expand(batch, -1, -1)
    return sample_image_at_points(rgb, K, R_T_cam, centres).view(batch, channels, *grid.volume_shape)


def sample_image_at_points(rgb: Tensor, K: Tensor, R_T_cam: Tensor, points: Tensor) -> Tensor:
    """Project points into an image and sample it bilinearly (the gather of :func:`unproject_rgb`, at any points).

    Args:
        rgb: ``[B, C, H, W]`` float image; K ``[B, 3, 3]``; R_T_cam ``[B, 4, 4]`` camera-to-R.
        points: ``[B, N, 3]`` points in R.

    Returns:
        ``[B, C, N]``: zero for points behind the camera or outside the image footprint (as :func:`unproject_rgb`).

    Convention: as :func:`unproject_rgb`.
    """
    if rgb.ndim != 4:
        raise ValueError(f"rgb must have shape [B, C, H, W], got {tuple(rgb.shape)}")
    if not rgb.is_floating_point():
        raise ValueError(f"rgb must be a floating-point tensor, got {rgb.dtype}")
    batch, _, height, width = rgb.shape
    _check_view(K, R_T_cam, batch)
    if points.ndim != 3 or points.shape[0] != batch or points.shape[2] != 3:
        raise ValueError(f"points must have shape [B, N, 3] with B={batch}, got {tuple(points.shape)}")
    centres = points.to(rgb.dtype)
    cam_T_R = invert_rigid(R_T_cam.to(rgb.dtype))
    uv, z = project(transform_points(cam_T_R, centres), K.to(rgb.dtype))
    u, v = uv.unbind(-1)
    visible = (z > BEHIND_EPS) & (u >= -0.5) & (u <= width - 0.5) & (v >= -0.5) & (v <= height - 0.5)
    norm = torch.stack(((2.0 * u + 1.0) / width - 1.0, (2.0 * v + 1.0) / height - 1.0), dim=-1)
    norm = torch.where(visible[..., None], norm, torch.zeros_like(norm))  # keep invisible coords finite
    sampled = F.grid_sample(rgb, norm[:, None], mode="bilinear", padding_mode="border", align_corners=False)
    return sampled[:, :, 0] * visible[:, None].to(rgb.dtype)  # [B, C, N]


def occupancy_from_depth(depth: Tensor, K: Tensor, R_T_cam: Tensor, grid: VoxelGridSpec) -> Tensor:
    """Scatter the points of a depth map into the grid.

    Args:
        depth: ``[B, H, W]`` metric z-depth, 0 (or non-finite) = invalid.
        K: ``[B, 3, 3]`` pinhole intrinsics.
        R_T_cam: ``[B, 4, 4]`` camera-to-R poses.
        grid: the voxel grid in R.

    Returns:
        ``[B, 1, Z, Y, X]`` float 0/1 (dtype of ``depth``): 1 where a valid depth point lies in the voxel;
        points outside the grid are dropped.

    Convention:
        OpenCV camera axes, integer pixel centres, z-depth; a point belongs to the voxel
        ``floor((p - bounds_min) / voxel_size)`` (half-open cells, as ``grid.contains``).
    """
    _check_depth_view(depth, K, R_T_cam, grid)
    points, valid = depth_to_points(depth, K.to(depth.dtype), R_T_cam.to(depth.dtype))
    return _voxelize(points, valid, grid)


def free_space_from_depth(depth: Tensor, K: Tensor, R_T_cam: Tensor, grid: VoxelGridSpec, samples_per_ray: int = 32,
                          margin: float | None = None) -> Tensor:
    """Voxels seen as empty: those crossed by camera rays before the observed surface.

    For each valid pixel with depth ``d``, ``samples_per_ray`` points are placed on its ray at z-depths
    ``(d - margin) * (s + 0.5) / S``, ``s = 0 .. S-1``, and voxelised; voxels occupied by
    :func:`occupancy_from_depth` are removed. Pixels with ``d <= margin`` contribute nothing.

    Args:
        depth: ``[B, H, W]`` metric z-depth, 0 (or non-finite) = invalid.
        K: ``[B, 3, 3]`` pinhole intrinsics.
        R_T_cam: ``[B, 4, 4]`` camera-to-R poses.
        grid: the voxel grid in R.
        samples_per_ray: ``S``, number of samples per pixel ray (positive int).
        margin: z-depth kept clear in front of the surface, in metres (``>= 0``); default the largest voxel edge,
            ``max(grid.voxel_size)``.

    Returns:
        ``[B, 1, Z, Y, X]`` float 0/1 (dtype of ``depth``); never 1 where the occupancy is 1.

    Convention:
        OpenCV camera axes, integer pixel centres; depth and margin are camera z-depths (not ray lengths).
    """
    _check_depth_view(depth, K, R_T_cam, grid)
    if isinstance(samples_per_ray, bool) or not isinstance(samples_per_ray, int) or samples_per_ray < 1:
        raise ValueError(f"samples_per_ray must be a positive int, got {samples_per_ray!r}")
    margin = max(grid.voxel_size) if margin is None else float(margin)
    if not margin >= 0.0:
        raise ValueError(f"margin must be >= 0 metres, got {margin!r}")
    K, R_T_cam = K.to(depth.dtype), R_T_cam.to(depth.dtype)
    batch = depth.shape[0]

    valid = torch.isfinite(depth) & (depth > margin)
    reach = torch.where(valid, depth - margin, torch.zeros_like(depth)).flatten(1)  # [B, HW]
    rays_cam = unproject_depth(torch.ones_like(depth), K).flatten(1, 2)  # [B, HW, 3], z = 1
    rays = rays_cam @ R_T_cam[:, :3, :3].transpose(-1, -2)  # directions in R
    origin = R_T_cam[:, None, None, :3, 3]  # camera centre in R
    fractions = (torch.arange(samples_per_ray, device=depth.device, dtype=depth.dtype) + 0.5) / samples_per_ray
    steps = reach[:, :, None] * fractions  # [B, HW, S] z-depths of the samples
    samples = torch.addcmul(origin, rays[:, :, None, :], steps[..., None]).reshape(batch, -1, 3)
    keep = valid.flatten(1)[:, :, None].expand(-1, -1, samples_per_ray).reshape(batch, -1)
    seen = _voxelize(samples, keep, grid)
    occupied = occupancy_from_depth(depth, K, R_T_cam, grid)
    return seen * (1.0 - occupied)


def unproject_rgbd_occupied(rgb: Tensor, depth: Tensor, K: Tensor, R_T_cam: Tensor, grid: VoxelGridSpec) -> Tensor:
    """The 3D encoder input ``cat[occ, occ * unproject_rgb(rgb)]``, the image gathered only at occupied voxels.

    Args:
        rgb: ``[B, 3, H, W]`` float image; depth ``[B, H, W]`` metric z-depth, 0 = invalid; K ``[B, 3, 3]``;
            R_T_cam ``[B, 4, 4]`` camera-to-R poses; grid: the voxel grid in R.

    Returns:
        ``[B, 4, Z, Y, X]`` (dtype of ``rgb``).

    Convention: as :func:`unproject_rgb` and :func:`occupancy_from_depth`.
    """
    if rgb.ndim != 4 or rgb.shape[1] != 3:
        raise ValueError(f"rgb must have shape [B, 3, H, W], got {tuple(rgb.shape)}")
    occ = occupancy_from_depth(depth.to(rgb.dtype), K, R_T_cam, grid)  # [B, 1, Z, Y, X]
    B = rgb.shape[0]
    out = torch.zeros(B, 4, *grid.volume_shape, dtype=rgb.dtype, device=rgb.device)
    out[:, :1] = occ
    centres = grid.voxel_centres(device=rgb.device, dtype=rgb.dtype).reshape(-1, 3)
    flat = out.view(B, 4, -1)
    for b in range(B):
        idx = occ[b, 0].reshape(-1).nonzero().flatten()
        if idx.numel():
            view = (rgb[b : b + 1], K[b : b + 1], R_T_cam[b : b + 1])
            flat[b, 1:, idx] = sample_image_at_points(*view, centres[idx][None])[0]
    return out
