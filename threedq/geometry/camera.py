"""Rigid transforms and the pinhole camera model.

Convention:
    Cameras use OpenCV axes (x right, y down, z forward). ``a_T_b`` ``[4, 4]`` maps points in frame b to
    frame a; a view's pose is ``R_T_cam``. ``K`` ``[3, 3]`` has pixel centres at integer coordinates:
    pixel (row v, col u) is centred at ``(u, v)``, and its skew ``K[0, 1]`` is honoured. Depth is metric
    z-depth, 0 = invalid. Yaw is a counter-clockwise rotation about +z (seen from above), in radians.
    Point transforms, rigid inversion and yaw matrices are kornia's; projection and back-projection are local ops
    (kornia's pinhole functions drop the skew).
"""

from __future__ import annotations

import torch
from kornia.geometry import create_meshgrid
from kornia.geometry.conversions import axis_angle_to_rotation_matrix
from kornia.geometry.linalg import inverse_transformation
from kornia.geometry.linalg import transform_points as _kornia_transform_points
from torch import Tensor

__all__ = ["depth_to_points", "invert_rigid", "project", "transform_points", "unproject_depth", "yaw_matrix"]

_PROJECT_EPS = 1e-8


def _shape_error(name: str, expected: str, tensor: Tensor) -> ValueError:
    return ValueError(f"{name} must have shape {expected}, got {tuple(tensor.shape)}")


def _check_intrinsics(K: Tensor, batch: int) -> None:
    if K.ndim != 3 or K.shape != (batch, 3, 3):
        raise _shape_error("K", f"[B, 3, 3] with B={batch}", K)


def _check_pose(name: str, pose: Tensor, batch: int) -> None:
    if pose.ndim != 3 or pose.shape != (batch, 4, 4):
        raise _shape_error(name, f"[B, 4, 4] with B={batch}", pose)


def _check_view(K: Tensor, R_T_cam: Tensor, batch: int) -> None:
    _check_intrinsics(K, batch)
    _check_pose("R_T_cam", R_T_cam, batch)


def _check_depth(depth: Tensor) -> None:
    if depth.ndim != 3:
        raise _shape_error("depth", "[B, H, W]", depth)


def _pixel_rays(K: Tensor, u: Tensor, v: Tensor) -> Tensor:
    """``[B, H, W, 3]`` camera-frame rays at z = 1 through pixels ``(u, v)`` (broadcast with ``[B, 1, 1]``, skew
    honoured)."""
    fx, fy, skew = K[:, 0, 0, None, None], K[:, 1, 1, None, None], K[:, 0, 1, None, None]
    cx, cy = K[:, 0, 2, None, None], K[:, 1, 2, None, None]
    y = (v - cy) / fy
    x = (u - cx - skew * y) / fx
    return torch.stack((x, y.expand_as(x), torch.ones_like(x)), dim=-1)


def transform_points(a_T_b: Tensor, points: Tensor) -> Tensor:
    """Apply rigid (or any homogeneous) transforms to point sets (``kornia.geometry.linalg.transform_points``).

    Args:
        a_T_b: ``[B, 4, 4]`` transforms from frame b to frame a.
        points: ``[B, N, 3]`` points in frame b.

    Returns:
        ``[B, N, 3]`` points in frame a.

    Convention:
        ``a_T_b`` maps points in frame b to frame a: ``p_a = R p_b + t``. A projective last row divides by
        ``w = a_T_b[3] . (p_b, 1)``, except where ``|w| <= 1e-8`` (left undivided, kornia's rule).
    """
    if points.ndim != 3 or points.shape[-1] != 3:
        raise _shape_error("points", "[B, N, 3]", points)
    _check_pose("a_T_b", a_T_b, points.shape[0])
    return _kornia_transform_points(a_T_b, points)


def invert_rigid(a_T_b: Tensor) -> Tensor:
    """Invert rigid transforms using the rotation's transpose (``kornia.geometry.linalg.inverse_transformation``).

    Args:
        a_T_b: ``[..., 4, 4]`` rigid transforms (rotation + translation, last row ``0 0 0 1``).

    Returns:
        ``[..., 4, 4]`` transforms ``b_T_a`` (dtype and device of ``a_T_b``).

    Convention:
        ``b_T_a = [[R^T, -R^T t], [0, 1]]``; not valid for non-rigid matrices (no general inverse is taken).
    """
    if a_T_b.ndim < 2 or a_T_b.shape[-2:] != (4, 4):
        raise _shape_error("a_T_b", "[..., 4, 4]", a_T_b)
    if a_T_b.ndim <= 3:
        return inverse_transformation(a_T_b)
    return inverse_transformation(a_T_b.reshape(-1, 4, 4)).reshape(a_T_b.shape)


def project(points_cam: Tensor, K: Tensor) -> tuple[Tensor, Tensor]:
    """Project camera-frame points to pixels.

    Args:
        points_cam: ``[B, N, 3]`` points in the camera frame.
        K: ``[B, 3, 3]`` pinhole intrinsics (skew is honoured).

    Returns:
        ``uv`` ``[B, N, 2]`` pixel coordinates (u = column, v = row) and ``z`` ``[B, N]`` camera depth.

    Convention:
        OpenCV camera axes; pixel centres at integer coordinates. Where ``|z| <= 1e-8`` the division uses
        ``1e-8`` instead so ``uv`` stays finite; such ``uv`` are meaningless and callers must mask by ``z``
        (points behind the camera, ``z <= 0``, also get meaningless ``uv``).
    """
    if points_cam.ndim != 3 or points_cam.shape[-1] != 3:
        raise _shape_error("points_cam", "[B, N, 3]", points_cam)
    _check_intrinsics(K, points_cam.shape[0])
    z = points_cam[..., 2]
    z_safe = torch.where(z.abs() > _PROJECT_EPS, z, torch.full_like(z, _PROJECT_EPS))
    xy = points_cam[..., :2] / z_safe[..., None]
    uv = xy @ K[:, :2, :2].transpose(-1, -2) + K[:, None, :2, 2]
    return uv, z


def unproject_depth(depth: Tensor, K: Tensor) -> Tensor:
    """Back-project every pixel of a depth map to a camera-frame point.

    Args:
        depth: ``[B, H, W]`` metric z-depth.
        K: ``[B, 3, 3]`` pinhole intrinsics (skew is honoured).

    Returns:
        ``[B, H, W, 3]`` camera-frame points; pixel (v, u) gives ``z * K^-1 (u, v, 1)`` with ``z = depth[v, u]``.

    Convention:
        Pixel centres at integer coordinates; OpenCV camera axes; depth is z-depth, not ray length.
    """
    _check_depth(depth)
    _check_intrinsics(K, depth.shape[0])
    height, width = depth.shape[-2:]
    uv = create_meshgrid(height, width, normalized_coordinates=False, device=depth.device, dtype=depth.dtype)
    return _pixel_rays(K, uv[..., 0], uv[..., 1]) * depth[..., None]


def depth_to_points(depth: Tensor, K: Tensor, R_T_cam: Tensor) -> tuple[Tensor, Tensor]:
    """Back-project a depth map into the reference frame R.

    Args:
        depth: ``[B, H, W]`` metric z-depth, 0 (or non-finite) = invalid.
        K: ``[B, 3, 3]`` pinhole intrinsics.
        R_T_cam: ``[B, 4, 4]`` camera-to-R poses.

    Returns:
        ``points_R`` ``[B, H*W, 3]`` (row-major pixel order) and ``valid`` ``[B, H*W]`` bool
        (``depth > 0`` and finite). Invalid pixels are back-projected at depth 0 (the camera centre).

    Convention:
        OpenCV camera axes, integer pixel centres, z-depth; ``R_T_cam`` maps camera points to R.
    """
    _check_depth(depth)
    _check_pose("R_T_cam", R_T_cam, depth.shape[0])
    valid = torch.isfinite(depth) & (depth > 0)
    clean = torch.where(valid, depth, torch.zeros_like(depth))
    points_cam = unproject_depth(clean, K).flatten(1, 2)
    return transform_points(R_T_cam, points_cam), valid.flatten(1)


def yaw_matrix(yaw: Tensor) -> Tensor:
    """Rotation matrices about +z (``kornia.geometry.conversions.axis_angle_to_rotation_matrix``).

    Args:
        yaw: ``[...]`` angles in radians (integer angles are cast to the default float dtype).

    Returns:
        ``[..., 3, 3]`` rotations mapping ``(x, y, z)`` to ``(x cos t - y sin t, x sin t + y cos t, z)``.

    Convention:
        Counter-clockwise seen from above (from +z looking down), right-handed, radians.
    """
    if not isinstance(yaw, Tensor):
        raise ValueError(f"yaw must be a tensor of angles, got {type(yaw).__name__}")
    if not yaw.is_floating_point():
        yaw = yaw.to(torch.get_default_dtype())
    zero = torch.zeros_like(yaw)
    return axis_angle_to_rotation_matrix(torch.stack((zero, zero, yaw), dim=-1))
