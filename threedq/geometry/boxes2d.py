"""2D object boxes from projected 3D boxes, and bilinear crops / RoI average pooling inside them.

:func:`project_boxes_2d` gives the image region of a projected 3D box, :func:`crop_boxes_2d` resamples it to a fixed
``size x size`` grid (aspect not kept) and :func:`roi_average_pool` averages a feature map inside it (RoIAlign-style
bilinear samples).

Convention:
    Pixel coordinates ``(u, v)``: u = column (x right), v = row (y down), pixel centres at integer
    coordinates, pixel ``i`` covering ``[i - 0.5, i + 0.5]`` (the convention of
    :func:`threedq.geometry.camera.project`). A 2D box is ``(u0, v0, u1, v1)`` with ``u0 <= u1``, ``v0 <= v1``,
    the continuous region it covers. A feature map of ``h x w`` cells over an ``H x W`` image has cell ``j``
    covering image pixels ``[j W / w - 0.5, (j + 1) W / w - 0.5]`` (each cell a uniform block of pixels).
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor

from threedq.boxes import box_corners
from threedq.geometry.camera import invert_rigid, project, transform_points

__all__ = ["crop_boxes_2d", "project_boxes_2d", "roi_average_pool"]

#: Camera depth (metres) below which a box corner counts as behind the camera.
_MIN_DEPTH = 1e-3


def project_boxes_2d(boxes: Tensor, K: Tensor, R_T_cam: Tensor, image_size: tuple[int, int]) -> tuple[Tensor, Tensor]:
    """The image rectangle of each oriented 3D box: the hull of its 8 projected corners, clipped to the image.

    Args:
        boxes: ``[B, M, 7]`` ``(cx, cy, cz, sx, sy, sz, yaw)`` in frame R (:func:`threedq.boxes.box_corners`).
        K: ``[B, 3, 3]`` intrinsics.
        R_T_cam: ``[B, 4, 4]`` camera-to-R poses.
        image_size: ``(H, W)``.

    Returns:
        ``boxes2d`` ``[B, M, 4]`` ``(u0, v0, u1, v1)`` clipped to ``[-0.5, W - 0.5] x [-0.5, H - 0.5]``, and
        ``valid`` ``[B, M]`` bool: every corner in front of the camera and a clipped box of positive area.

    Convention: see the module docstring; OpenCV camera axes (z forward, y down).
    """
    if boxes.ndim != 3 or boxes.shape[-1] != 7:
        raise ValueError(f"boxes must have shape [B, M, 7], got {tuple(boxes.shape)}")
    B, M = boxes.shape[:2]
    if K.shape != (B, 3, 3) or R_T_cam.shape != (B, 4, 4):
        raise ValueError(f"K and R_T_cam must be [B, 3, 3] and [B, 4, 4] with B={B}, got {tuple(K.shape)} and "
                         f"{tuple(R_T_cam.shape)}")
    H, W = image_size
    corners = box_corners(boxes).reshape(B, M * 8, 3)
    cam = transform_points(invert_rigid(R_T_cam), corners)
    uv, z = project(cam, K)
    uv, z = uv.view(B, M, 8, 2), z.view(B, M, 8)
    lo, hi = (torch.stack([e[..., 0].clamp(-0.5, W - 0.5), e[..., 1].clamp(-0.5, H - 0.5)], dim=-1)
              for e in (uv.amin(dim=2), uv.amax(dim=2)))
    out = torch.cat([lo, hi], dim=-1)
    valid = (z > _MIN_DEPTH).all(dim=2) & (hi > lo).all(dim=-1)
    return out, valid


def _check_boxes2d(images: Tensor, boxes2d: Tensor) -> None:
    if images.ndim != 4:
        raise ValueError(f"images must have shape [B, C, H, W], got {tuple(images.shape)}")
    if boxes2d.ndim != 3 or boxes2d.shape[-1] != 4 or boxes2d.shape[0] != images.shape[0]:
        raise ValueError(f"boxes2d must have shape [B, M, 4] with B={images.shape[0]}, got {tuple(boxes2d.shape)}")


def crop_boxes_2d(images: Tensor, boxes2d: Tensor, size: int = 32) -> Tensor:
    """Resample the region of each 2D box to ``size x size`` (bilinear, zeros outside the image).

    Output pixel ``(i, j)`` samples the image at ``u = u0 + (j + 0.5) (u1 - u0) / size``, ``v = v0 + (i + 0.5)
    (v1 - v0) / size`` (cell centres of a ``size x size`` grid over the box).

    Args:
        images: ``[B, C, H, W]``.
        boxes2d: ``[B, M, 4]`` ``(u0, v0, u1, v1)`` pixel coordinates.
        size: output side.

    Returns:
        ``[B, M, C, size, size]``. Differentiable w.r.t. ``images`` and ``boxes2d``.

    Convention: see the module docstring (pixel centres at integers, ``align_corners=False``).
    """
    _check_boxes2d(images, boxes2d)
    if isinstance(size, bool) or not isinstance(size, int) or size < 1:
        raise ValueError(f"size must be a positive int, got {size!r}")
    B, C, H, W = images.shape
    M = boxes2d.shape[1]
    t = (torch.arange(size, device=images.device, dtype=images.dtype) + 0.5) / size  # [s]
    u = boxes2d[..., 0:1] + t * (boxes2d[..., 2:3] - boxes2d[..., 0:1])  # [B, M, s]
    v = boxes2d[..., 1:2] + t * (boxes2d[..., 3:4] - boxes2d[..., 1:2])
    gx = (2.0 * u + 1.0) / W - 1.0  # align_corners=False: pixel i at (2 i + 1) / W - 1
    gy = (2.0 * v + 1.0) / H - 1.0
    grid = torch.stack(torch.broadcast_tensors(gx[:, :, None, :], gy[:, :, :, None]), dim=-1)  # [B, M, s, s, 2]
    grid = grid.reshape(B, M * size, size, 2).to(images.dtype)
    out = F.grid_sample(images, grid, mode="bilinear", padding_mode="zeros", align_corners=False)  # [B, C, M*s, s]
    return out.view(B, C, M, size, size).permute(0, 2, 1, 3, 4)


def roi_average_pool(features: Tensor, boxes2d: Tensor, image_size: tuple[int, int], samples: int = 4) -> Tensor:
    """Average of a feature map inside each image box (RoIAlign average: ``samples^2`` bilinear samples).

    The box is mapped from image pixels to the ``h x w`` feature map (``x_f = (u + 0.5) w / W - 0.5``) and
    sampled at the centres of a ``samples x samples`` grid of cells over it; the result is their mean.

    Args:
        features: ``[B, C, h, w]`` (e.g. ResNet-18's last stage, stride 32).
        boxes2d: ``[B, M, 4]`` image-pixel boxes ``(u0, v0, u1, v1)``.
        image_size: ``(H, W)`` of the image the boxes live in.
        samples: sample points per box side.

    Returns:
        ``[B, M, C]`` pooled features. Differentiable w.r.t. ``features``.

    Convention: see the module docstring.
    """
    _check_boxes2d(features, boxes2d)
    H, W = image_size
    h, w = features.shape[-2:]
    scale = boxes2d.new_tensor([w / W, h / H, w / W, h / H])
    fboxes = (boxes2d + 0.5) * scale - 0.5
    return crop_boxes_2d(features, fboxes, samples).mean(dim=(-2, -1))
