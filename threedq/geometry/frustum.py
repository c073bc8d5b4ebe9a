"""Resampling of a voxel volume into a camera's frustum (the "perspective-transformed" tensor of GIGNs).

Convention:
    Grid in the reference frame R (metres, z up), volumes ``[B, C, Z, Y, X]``, cell-centred voxels, every
    ``grid_sample`` with ``align_corners=False``. Cameras: OpenCV axes (x right, y down, z forward), ``K`` with
    pixel centres at integer coordinates (skew honoured), poses ``R_T_cam`` (camera-to-R). Frustum tensors are
    ``[B, C, D, H, W]`` with ``D`` depth planes (near to far) and ``H x W`` pixels.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor

from .camera import _check_view, _pixel_rays
from .grid import VoxelGridSpec, _check_grid

__all__ = ["frustum_depth_max", "frustum_points", "resample_to_frustum", "scale_intrinsics"]


def _check_frustum_args(image_size: tuple[int, int], depth_range: tuple[float, float], num_planes: int) -> None:
    if len(image_size) != 2 or any(isinstance(s, bool) or int(s) != s or s < 1 for s in image_size):
        raise ValueError(f"image_size must be (H, W) with positive ints, got {image_size!r}")
    if len(depth_range) != 2 or not 0.0 < float(depth_range[0]) < float(depth_range[1]):
        raise ValueError(f"depth_range must be (near, far) with 0 < near < far, got {depth_range!r}")
    if isinstance(num_planes, bool) or int(num_planes) != num_planes or num_planes < 1:
        raise ValueError(f"num_planes must be a positive int, got {num_planes!r}")


def scale_intrinsics(K: Tensor, sx: float, sy: float) -> Tensor:
    """Intrinsics of an image of size ``(H, W)`` resampled to ``(H * sy, W * sx)``.

    Args:
        K: ``[..., 3, 3]`` pinhole intrinsics.
        sx: horizontal scale factor (new width / old width), > 0.
        sy: vertical scale factor (new height / old height), > 0.

    Returns:
        ``[..., 3, 3]`` new intrinsics: ``fx' = fx * sx``, ``skew' = skew * sx``, ``cx' = (cx + 0.5) * sx - 0.5``,
        ``fy' = fy * sy``, ``cy' = (cy + 0.5) * sy - 0.5``.

    Convention:
        Pixel centres at integer coordinates: pixel ``u`` covers ``[u - 0.5, u + 0.5)``, so the image edge is at
        ``-0.5`` and a continuous coordinate ``c`` maps to ``(c + 0.5) * s - 0.5``; a 3D point keeps its relative
        position ``(u + 0.5) / W`` in the image.
    """
    if K.ndim < 2 or K.shape[-2:] != (3, 3):
        raise ValueError(f"K must have shape [..., 3, 3], got {tuple(K.shape)}")
    if not (sx > 0 and sy > 0):
        raise ValueError(f"scale factors must be positive, got sx={sx}, sy={sy}")
    row_scale = torch.tensor([sx, sy, 1.0], dtype=K.dtype, device=K.device)
    shift = torch.tensor([0.5 * sx - 0.5, 0.5 * sy - 0.5, 0.0], dtype=K.dtype, device=K.device)
    # K' = S K with S = [[sx, 0, 0.5 sx - 0.5], [0, sy, 0.5 sy - 0.5], [0, 0, 1]]
    out = K * row_scale[:, None]
    return out + shift[:, None] * K[..., 2:3, :]


def frustum_points(K: Tensor, R_T_cam: Tensor, image_size: tuple[int, int], depth_range: tuple[float, float],
                   num_planes: int) -> Tensor:
    """Points in R at the centre of every frustum sample.

    Args:
        K: ``[B, 3, 3]`` intrinsics for an image of size ``image_size``.
        R_T_cam: ``[B, 4, 4]`` camera-to-R poses.
        image_size: ``(H, W)`` of the frustum's pixel grid.
        depth_range: ``(near, far)`` camera z range in metres, ``0 < near < far``.
        num_planes: number ``D`` of depth planes.

    Returns:
        ``[B, D, H, W, 3]`` points ``(x, y, z)`` in R, in the dtype of ``K`` (at least float32).

    Convention:
        Sample ``(d, v, u)`` is the back-projection of pixel centre ``(u, v)`` at camera z-depth
        ``z_d = near + (d + 0.5) * (far - near) / D`` (planes cell-centred like voxels), mapped to R by ``R_T_cam``.
    """
    _check_view(K, R_T_cam, K.shape[0])
    _check_frustum_args(image_size, depth_range, num_planes)
    height, width = (int(s) for s in image_size)
    depth_planes = int(num_planes)
    near, far = (float(d) for d in depth_range)
    dtype = torch.promote_types(K.dtype, torch.float32)
    device = K.device
    K = K.to(dtype)
    R_T_cam = R_T_cam.to(dtype)
    u = torch.arange(width, device=device, dtype=dtype)
    v = torch.arange(height, device=device, dtype=dtype)
    rays = _pixel_rays(K, u, v[:, None])  # [B, H, W, 3], camera frame, z = 1
    rays_R = rays @ R_T_cam[:, None, :3, :3].transpose(-1, -2)  # rotated into R, [B, H, W, 3]
    z = near + (torch.arange(depth_planes, device=device, dtype=dtype) + 0.5) * ((far - near) / depth_planes)
    origin = R_T_cam[:, None, None, None, :3, 3]  # [B, 1, 1, 1, 3]
    return z[None, :, None, None, None] * rays_R[:, None] + origin


def resample_to_frustum(volume: Tensor, grid: VoxelGridSpec, K: Tensor, R_T_cam: Tensor, image_size: tuple[int, int],
                        depth_range: tuple[float, float], num_planes: int) -> Tensor:
    """Trilinearly resample a volume in R into a camera's frustum.

    Args:
        volume: ``[B, C, Z, Y, X]`` volume on ``grid`` (e.g. the encoder's features on ``grid.half()``).
        grid: the grid ``volume`` lives on; its ``volume_shape`` must equal ``volume.shape[2:]``.
        K: ``[B, 3, 3]`` intrinsics **for the output resolution** ``image_size`` (see :func:`scale_intrinsics`).
        R_T_cam: ``[B, 4, 4]`` camera-to-R poses of the target views.
        image_size: ``(H, W)`` of the output frustum grid.
        depth_range: ``(near, far)`` camera z range in metres, ``0 < near < far``.
        num_planes: number ``D`` of depth planes.

    Returns:
        ``[B, C, D, H, W]`` samples in the dtype of ``volume`` (fp16/bf16 volumes are sampled in float32); zero
        where the sample point is outside the grid (trilinear with zero padding, so values fade out over the last
        half voxel). Differentiable w.r.t. ``volume``.

    Raises:
        ValueError: on inconsistent shapes, a grid that does not match ``volume`` or invalid frustum arguments.

    Convention:
        Sample ``(d, v, u)`` is at pixel centre ``(u, v)`` (integer pixel coordinates, OpenCV axes) and camera
        z-depth ``z_d = near + (d + 0.5) * (far - near) / D``; one ``grid_sample`` with ``align_corners=False``.
    """
    coords, sample_dtype = _frustum_coords(volume, grid, K, R_T_cam, image_size, depth_range, num_planes)
    return _sample(volume, coords, sample_dtype)


def _sample(volume: Tensor, coords: Tensor, dtype: torch.dtype) -> Tensor:
    """Trilinear ``grid_sample`` (zero padding, ``align_corners=False``) in ``dtype``, cast to ``volume``'s dtype."""
    out = F.grid_sample(volume.to(dtype), coords.to(dtype), mode="bilinear", padding_mode="zeros", align_corners=False)
    return out.to(volume.dtype)


def _frustum_coords(volume: Tensor, grid: VoxelGridSpec, K: Tensor, R_T_cam: Tensor,
                    *frustum) -> tuple[Tensor, torch.dtype]:
    """The frustum's ``grid_sample`` coordinates ``[B, D, H, W, 3]`` and the dtype to sample in (float32 for
    fp16/bf16 volumes), after the checks; ``frustum``: ``image_size, depth_range, num_planes``."""
    _check_grid(grid)
    if volume.ndim != 5:
        raise ValueError(f"volume must have shape [B, C, Z, Y, X], got {tuple(volume.shape)}")
    if tuple(volume.shape[2:]) != grid.volume_shape:
        raise ValueError(f"volume spatial shape {tuple(volume.shape[2:])} does not match grid.volume_shape "
                         f"{grid.volume_shape} (features of the encoder live on grid.half())")
    _check_view(K, R_T_cam, volume.shape[0])
    coords = grid.world_to_normalized(frustum_points(K, R_T_cam, *frustum))  # [B, D, H, W, 3]
    if not volume.is_floating_point():
        raise ValueError(f"volume must be a floating tensor, got {volume.dtype}")
    return coords, torch.promote_types(volume.dtype, torch.float32)


def frustum_depth_max(volume: Tensor, grid: VoxelGridSpec, K: Tensor, R_T_cam: Tensor, image_size: tuple[int, int],
                      depth_range: tuple[float, float], num_planes: int, pool: int) -> Tensor:
    """The max of :func:`resample_to_frustum` over each group of ``pool`` depth planes, without the whole frustum.

    Bit for bit, values and gradient, ``depth_max_pool(resample_to_frustum(...), pool)``
    (:func:`threedq.nets.depth_max_pool`). A window of ``pool`` samples (one pixel, one group of planes) with no
    sample within half a voxel of the grid is zero and neither sampled nor stored; the other windows' samples are
    taken by one ``grid_sample`` in the whole frustum's order (plane, then pixel).

    Args:
        volume, grid, K, R_T_cam, image_size, depth_range, num_planes: as for :func:`resample_to_frustum`.
        pool: planes a group; must divide ``num_planes``.

    Returns:
        ``[B, C, num_planes / pool, H, W]`` in the dtype of ``volume``.

    Raises:
        ValueError: as :func:`resample_to_frustum`, and if ``pool`` does not divide ``num_planes``.

    Convention:
        As :func:`resample_to_frustum`; group ``g`` covers planes ``g * pool .. (g + 1) * pool - 1`` (near to far).
    """
    if isinstance(pool, bool) or int(pool) != pool or pool < 1 or int(num_planes) % int(pool):
        raise ValueError(f"pool must be a positive int dividing num_planes={num_planes}, got {pool!r}")
    coords, sample_dtype = _frustum_coords(volume, grid, K, R_T_cam, image_size, depth_range, num_planes)
    pool = int(pool)
    B, D, H, W, _ = coords.shape
    C, G, n = volume.shape[1], D // pool, H * W
    dev = coords.device
    # A sample is non-zero only with a corner inside the volume: within half a voxel of the grid (1/size in
    # normalised units); a full voxel is kept, and NaN (never "outside") is sampled as grid_sample would.
    size = torch.tensor(volume.shape[2:][::-1], dtype=coords.dtype, device=dev)  # X, Y, Z for x, y, z
    near = ~(coords.abs() > 1.0 + 2.0 / size).any(-1)  # [B, D, H, W]
    windows = near.view(B, G, pool, n).any(2)  # [B, G, n]
    counts = windows.sum(-1)  # [B, G] windows of each group
    per_sample = counts.sum(-1)  # [B]
    W_max = max(int(per_sample.max()), 1)  # one empty window keeps the graph when nothing is near
    L = W_max * pool
    b, g, p = windows.nonzero(as_tuple=True)  # sample-major, then group, then pixel
    k = torch.arange(b.numel(), device=dev) - (torch.cumsum(per_sample, 0) - per_sample)[b]  # window within its sample
    group_start = torch.cumsum(counts, 1) - counts  # [B, G] first window of each group
    rank = k - group_start[b, g]
    j = torch.arange(pool, device=dev)
    # sample j of a window goes to slot (group's first window) * pool + j * (group's windows) + rank: plane-major
    slot = (group_start[b, g] * pool + rank)[:, None] + j * counts[b, g][:, None]  # [N, pool]
    source = (g[:, None] * pool + j) * n + p[:, None]  # the frustum sample (plane, pixel), flattened
    taken = torch.full((B, L), D * n, dtype=torch.long, device=dev)  # unused slots: the point appended below
    taken[b[:, None].expand_as(slot), slot] = source
    window_slots = torch.zeros(B, W_max, pool, dtype=torch.long, device=dev)
    window_slots[b, k] = slot
    target = torch.full((B, W_max), G * n, dtype=torch.long, device=dev)  # G * n: a slot for the padding windows
    target[b, k] = g * n + p
    far = coords.new_full((B, 1, 3), 4.0)  # far outside the grid: a zero sample that takes no gradient
    pts = torch.gather(torch.cat([coords.reshape(B, D * n, 3), far], 1), 1, taken[..., None].expand(B, L, 3))
    samples = _sample(volume, pts.view(B, 1, 1, L, 3), sample_dtype).view(B, C, L)
    per_window = torch.gather(samples, 2, window_slots.view(B, 1, L).expand(B, C, L)).view(B, C, W_max, pool)
    best = per_window.max(dim=3).values  # [B, C, W_max]
    out = best.new_zeros(B, C, G * n + 1).scatter(2, target[:, None].expand(B, C, W_max), best)
    return out[..., : G * n].view(B, C, G, H, W)
