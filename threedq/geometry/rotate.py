"""Yaw rotation of feature volumes about their vertical centre line.

Convention:
    Volumes are ``[N, C, Z, Y, X]`` in the reference frame R (z up). Yaw is in radians, counter-clockwise
    seen from above (from +z looking down): content at +x moves towards +y. Sampling is a local
    ``grid_sample`` with ``align_corners=False``.
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F
from torch import Tensor

from .grid import _desc

__all__ = ["rotate_yaw", "yaw_angles"]


def _yaw_theta(angles: Tensor, ny: int, nx: int) -> Tensor:
    """``[..., 2, 3]`` ``affine_grid`` matrices sampling at ``R(-t) p``: ``S^-1 R(-t) S``, ``S = diag(nx/2, ny/2)``."""
    c, s = torch.cos(angles), torch.sin(angles)
    zero = torch.zeros_like(c)
    return torch.stack((torch.stack((c, s * (ny / nx), zero), -1), torch.stack((-s * (nx / ny), c, zero), -1)), -2)


def rotate_yaw(volume: Tensor, yaw: Tensor) -> Tensor:
    """Rotate the content of volumes about the vertical axis through the volume centre.

    Output voxel ``p`` (x-y offset from the centre, in voxels) takes the input value at ``R(-yaw) p``,
    bilinearly interpolated within its z-slice (z is unchanged, so this equals trilinear sampling), zero
    outside the volume. All ``A`` angles are sampled in one ``grid_sample`` call without copying the input.

    Args:
        volume: ``[N, C, Z, Y, X]`` volumes.
        yaw: ``[N]`` or ``[N, A]`` angles in radians.

    Returns:
        ``[N, C, Z, Y, X]`` for ``yaw`` ``[N]``, ``[N, A, C, Z, Y, X]`` for ``yaw`` ``[N, A]``.
        Differentiable w.r.t. ``volume`` and ``yaw``.

    Convention:
        Counter-clockwise about +z seen from above: a point ``(x, y)`` goes to
        ``(x cos t - y sin t, x sin t + y cos t)``. The centre is the geometric centre of the volume
        (index ``(n - 1) / 2``, cell-centred, ``align_corners=False``). Angles are in voxel units, i.e. x
        and y voxels are assumed square; if ``X != Y`` the content may leave the volume.
    """
    if not isinstance(volume, Tensor) or volume.ndim != 5:
        raise ValueError(f"volume must have shape [N, C, Z, Y, X], got {_desc(volume)}")
    if not volume.is_floating_point():
        raise ValueError(f"volume must be a floating-point tensor, got {volume.dtype}")
    n, channels, nz, ny, nx = volume.shape
    if not isinstance(yaw, Tensor) or yaw.ndim not in (1, 2) or yaw.shape[0] != n:
        raise ValueError(f"yaw must have shape [N] or [N, A] with N={n}, got {_desc(yaw)}")
    single = yaw.ndim == 1
    if n == 0:
        return volume.clone() if single else volume.new_zeros(0, yaw.shape[1], *volume.shape[1:])
    angles = yaw.to(volume.dtype).reshape(n, -1)  # [N, A]
    n_angles = angles.shape[1]
    theta = _yaw_theta(angles, ny, nx)  # [N, A, 2, 3]
    coords = F.affine_grid(theta.reshape(n * n_angles, 2, 3), [n * n_angles, 1, ny, nx], align_corners=False)
    coords = coords.reshape(n, n_angles * ny, nx, 2)
    # z is unchanged, so fold (C, Z) into channels and rotate each slice in 2D; the A angles are stacked on H.
    slices = volume.reshape(n, channels * nz, ny, nx)
    out = F.grid_sample(slices, coords, mode="bilinear", padding_mode="zeros", align_corners=False)
    out = out.view(n, channels, nz, n_angles, ny, nx).permute(0, 3, 1, 2, 4, 5)
    return out[:, 0].contiguous() if single else out.contiguous()


def yaw_angles(n: int = 36, device: torch.device | str | None = None, dtype: torch.dtype | None = None) -> Tensor:
    """Evenly spaced yaw candidates ``0, 2 pi / n, ..., 2 pi (n - 1) / n``.

    Args:
        n: number of angles (positive int); 36 gives 10 degree steps.
        device: device of the result.
        dtype: floating dtype of the result (default: torch's default dtype).

    Returns:
        ``[n]`` angles in radians.

    Convention:
        Radians, counter-clockwise about +z seen from above.
    """
    if isinstance(n, bool) or not isinstance(n, int) or n < 1:
        raise ValueError(f"n must be a positive int, got {n!r}")
    dtype = dtype or torch.get_default_dtype()
    steps = torch.arange(n, device=device, dtype=torch.float64) * (2.0 * math.pi / n)
    return steps.to(dtype)
