"""Geometry core: local implementations vs kornia, at the main job's sizes.

For every op of ``threedq.geometry`` that kornia could take over, times ``local`` (``_local_*`` below), ``kornia`` (the
``kornia.geometry`` function named in the table, swapped into the same body for composite ops) and ``threedq`` (what
``threedq.geometry`` ships) after checking that they agree (``max |diff|``); K has zero skew (kornia's pinhole
functions have none). 2 threads, forward only, two warm-up calls, then rounds of the three routes in a shuffled order.

    python benchmarks/bench_geometry_kornia.py            # about 2.5 minutes on 2 cores
    python benchmarks/bench_geometry_kornia.py --quick    # fewer rounds, no rotate3d

Convention:
    As ``threedq.geometry``: OpenCV cameras, ``a_T_b`` maps b to a, volumes ``[B, C, Z, Y, X]``, ``grid_sample``
    with ``align_corners=False``, z up, yaw counter-clockwise about +z seen from above, radians.
"""

from __future__ import annotations

import argparse
import math
import random
import statistics
import time
from collections.abc import Callable
from functools import partial

import kornia
import torch
import torch.nn.functional as F
from kornia.geometry import create_meshgrid
from kornia.geometry.camera.perspective import project_points as k_project_points
from kornia.geometry.conversions import axis_angle_to_rotation_matrix
from kornia.geometry.depth import depth_to_3d_v2, unproject_meshgrid
from kornia.geometry.linalg import inverse_transformation
from kornia.geometry.linalg import transform_points as k_transform_points
from kornia.geometry.transform import rotate as k_rotate
from kornia.geometry.transform import rotate3d as k_rotate3d
from kornia.geometry.transform import warp_affine3d
from _common import machine, table
from torch import Tensor

import threedq.geometry as G
from threedq.geometry.unproject import BEHIND_EPS, _voxelize


def _local_invert_rigid(a_T_b: Tensor) -> Tensor:
    rot_t = a_T_b[..., :3, :3].transpose(-1, -2)
    trans = -(rot_t @ a_T_b[..., :3, 3:4])
    out = torch.zeros_like(a_T_b)
    out[..., :3, :3] = rot_t
    out[..., :3, 3:4] = trans
    out[..., 3, 3] = 1.0
    return out


_kornia_invert_rigid = inverse_transformation
_kornia_transform_points = k_transform_points
_kornia_unproject_depth = depth_to_3d_v2


def _local_yaw_matrix(yaw: Tensor) -> Tensor:
    c, s = torch.cos(yaw), torch.sin(yaw)
    zero, one = torch.zeros_like(yaw), torch.ones_like(yaw)
    rows = ((c, -s, zero), (s, c, zero), (zero, zero, one))
    return torch.stack([torch.stack(r, dim=-1) for r in rows], dim=-2)


def _local_transform_points(a_T_b: Tensor, points: Tensor) -> Tensor:
    homog = torch.baddbmm(a_T_b[:, None, :, 3], points, a_T_b[:, :, :3].transpose(1, 2))
    w = homog[..., 3:]
    return homog[..., :3] / torch.where(w.abs() > 1e-8, w, torch.ones_like(w))


def _local_project(points_cam: Tensor, K: Tensor) -> tuple[Tensor, Tensor]:
    z = points_cam[..., 2]
    z_safe = torch.where(z.abs() > 1e-8, z, torch.full_like(z, 1e-8))
    xy = points_cam[..., :2] / z_safe[..., None]
    return xy @ K[:, :2, :2].transpose(-1, -2) + K[:, None, :2, 2], z


def _kornia_yaw_matrix(yaw: Tensor) -> Tensor:
    return axis_angle_to_rotation_matrix(torch.stack((0 * yaw, 0 * yaw, yaw), -1))


def _kornia_project(points_cam: Tensor, K: Tensor) -> tuple[Tensor, Tensor]:
    return k_project_points(points_cam, K[:, None]), points_cam[..., 2]


def _local_unproject_depth(depth: Tensor, K: Tensor) -> Tensor:
    height, width = depth.shape[-2:]
    uv = create_meshgrid(height, width, normalized_coordinates=False, device=depth.device, dtype=depth.dtype)
    u, v = uv[..., 0], uv[..., 1]
    fx, fy, skew = K[:, 0, 0, None, None], K[:, 1, 1, None, None], K[:, 0, 1, None, None]
    cx, cy = K[:, 0, 2, None, None], K[:, 1, 2, None, None]
    y = (v - cy) / fy
    x = (u - cx - skew * y) / fx
    return torch.stack((x, y, torch.ones_like(x)), dim=-1) * depth[..., None]


def _depth_to_points(depth: Tensor, K: Tensor, pose: Tensor, unproject: Callable, transform: Callable):
    valid = torch.isfinite(depth) & (depth > 0)
    clean = torch.where(valid, depth, torch.zeros_like(depth))
    return transform(pose, unproject(clean, K).flatten(1, 2)), valid.flatten(1)


_local_depth_to_points = partial(_depth_to_points, unproject=_local_unproject_depth, transform=_local_transform_points)
_kornia_depth_to_points = partial(_depth_to_points, unproject=depth_to_3d_v2, transform=k_transform_points)


def _unproject_rgb(rgb, K, pose, grid, invert: Callable, transform: Callable, project: Callable) -> Tensor:
    batch, channels, height, width = rgb.shape
    centres = grid.voxel_centres(device=rgb.device, dtype=rgb.dtype).reshape(1, -1, 3).expand(batch, -1, -1)
    uv, z = project(transform(invert(pose), centres), K)
    u, v = uv.unbind(-1)
    visible = (z > BEHIND_EPS) & (u >= -0.5) & (u <= width - 0.5) & (v >= -0.5) & (v <= height - 0.5)
    norm = torch.stack(((2.0 * u + 1.0) / width - 1.0, (2.0 * v + 1.0) / height - 1.0), dim=-1)
    norm = torch.where(visible[..., None], norm, torch.zeros_like(norm))
    sampled = F.grid_sample(rgb, norm[:, None], mode="bilinear", padding_mode="border", align_corners=False)
    return (sampled[:, :, 0] * visible[:, None].to(rgb.dtype)).view(batch, channels, *grid.volume_shape)


_local_unproject_rgb = partial(_unproject_rgb, invert=_local_invert_rigid, transform=_local_transform_points,
                               project=_local_project)
_kornia_unproject_rgb = partial(_unproject_rgb, invert=inverse_transformation, transform=k_transform_points,
                                project=_kornia_project)


def _local_occupancy_from_depth(depth, K, pose, grid):
    return _voxelize(*_local_depth_to_points(depth, K, pose), grid)


def _kornia_occupancy_from_depth(depth, K, pose, grid):
    return _voxelize(*_kornia_depth_to_points(depth, K, pose), grid)


def _free_space(depth, K, pose, grid, samples, rays_fn: Callable, occupancy: Callable) -> Tensor:
    margin = max(grid.voxel_size)
    batch = depth.shape[0]
    valid = torch.isfinite(depth) & (depth > margin)
    reach = torch.where(valid, depth - margin, torch.zeros_like(depth)).flatten(1)
    rays = rays_fn(depth, K).flatten(1, 2) @ pose[:, :3, :3].transpose(-1, -2)
    origin = pose[:, None, None, :3, 3]
    fractions = (torch.arange(samples, device=depth.device, dtype=depth.dtype) + 0.5) / samples
    steps = reach[:, :, None] * fractions
    points = torch.addcmul(origin, rays[:, :, None, :], steps[..., None]).reshape(batch, -1, 3)
    keep = valid.flatten(1)[:, :, None].expand(-1, -1, samples).reshape(batch, -1)
    return _voxelize(points, keep, grid) * (1.0 - occupancy(depth, K, pose, grid))


def _local_free_space_from_depth(depth, K, pose, grid, samples=32):
    rays = lambda d, k: _local_unproject_depth(torch.ones_like(d), k)
    return _free_space(depth, K, pose, grid, samples, rays, _local_occupancy_from_depth)


def _kornia_free_space_from_depth(depth, K, pose, grid, samples=32):
    rays = lambda d, k: unproject_meshgrid(d.shape[-2], d.shape[-1], k, device=d.device, dtype=d.dtype)
    return _free_space(depth, K, pose, grid, samples, rays, _kornia_occupancy_from_depth)


def _frustum(volume, grid, K, pose, size, depth_range, planes, rays_fn: Callable, transform: Callable) -> Tensor:
    near, far = depth_range
    rays = rays_fn(K, size)  # [B, H, W, 3], z = 1
    z = near + (torch.arange(planes, dtype=K.dtype) + 0.5) * ((far - near) / planes)
    cam = z[None, :, None, None, None] * rays[:, None]  # [B, D, H, W, 3]
    points = transform(pose, cam.flatten(1, 3)).view(*cam.shape)
    return F.grid_sample(volume, grid.world_to_normalized(points), mode="bilinear", padding_mode="zeros",
                         align_corners=False)


def _local_rays(K, size):
    height, width = size
    u, v = torch.arange(width, dtype=K.dtype), torch.arange(height, dtype=K.dtype)
    fx, fy, skew = K[:, 0, 0, None, None], K[:, 1, 1, None, None], K[:, 0, 1, None, None]
    cx, cy = K[:, 0, 2, None, None], K[:, 1, 2, None, None]
    y = (v[None, :, None] - cy) / fy
    x = (u[None, None, :] - cx - skew * y) / fx
    return torch.stack((x, y.expand_as(x), torch.ones_like(x)), dim=-1)


def _local_resample_to_frustum(volume, grid, K, pose, size, depth_range, planes):
    rays_R = _local_rays(K, size) @ pose[:, None, :3, :3].transpose(-1, -2)
    near, far = depth_range
    z = near + (torch.arange(planes, dtype=K.dtype) + 0.5) * ((far - near) / planes)
    points = z[None, :, None, None, None] * rays_R[:, None] + pose[:, None, None, None, :3, 3]
    return F.grid_sample(volume, grid.world_to_normalized(points), mode="bilinear", padding_mode="zeros",
                         align_corners=False)


def _kornia_resample_to_frustum(volume, grid, K, pose, size, depth_range, planes):
    rays = lambda k, s: unproject_meshgrid(s[0], s[1], k, dtype=k.dtype)
    return _frustum(volume, grid, K, pose, size, depth_range, planes, rays, k_transform_points)


def _local_rotate_yaw(volume: Tensor, yaw: Tensor) -> Tensor:
    n, channels, nz, ny, nx = volume.shape
    angles = yaw.to(volume.dtype).reshape(n, -1)
    n_angles = angles.shape[1]
    c, s = torch.cos(angles), torch.sin(angles)
    zero = torch.zeros_like(c)
    theta = torch.stack((torch.stack((c, s * (ny / nx), zero), dim=-1), torch.stack((-s * (nx / ny), c, zero), dim=-1)),
                        dim=-2)
    coords = F.affine_grid(theta.reshape(n * n_angles, 2, 3), [n * n_angles, 1, ny, nx], align_corners=False)
    coords = coords.reshape(n, n_angles * ny, nx, 2)
    slices = volume.reshape(n, channels * nz, ny, nx)
    out = F.grid_sample(slices, coords, mode="bilinear", padding_mode="zeros", align_corners=False)
    return out.view(n, channels, nz, n_angles, ny, nx).permute(0, 3, 1, 2, 4, 5).contiguous()


def _kornia_rotate_yaw(volume: Tensor, yaw: Tensor) -> Tensor:
    """kornia 2D ``rotate`` of the (C, Z)-folded slices, one call per angle; its positive angle is counter-clockwise
    as displayed (y down), hence ``-degrees(yaw)``."""
    n, channels, nz, ny, nx = volume.shape
    slices = volume.reshape(n, channels * nz, ny, nx)
    outs = [k_rotate(slices, torch.rad2deg(-yaw[:, a]), align_corners=False) for a in range(yaw.shape[1])]
    return torch.stack(outs, 1).view(n, yaw.shape[1], channels, nz, ny, nx)


def _kornia_rotate_yaw_3d(volume: Tensor, yaw: Tensor) -> Tensor:
    """kornia ``rotate3d`` about +z, one call per angle; exact only with ``align_corners=True`` (its 3D normalisation
    is corner-aligned whatever the flag)."""
    outs = []
    for a in range(yaw.shape[1]):
        roll = torch.rad2deg(yaw[:, a])
        zero = torch.zeros_like(roll)
        outs.append(k_rotate3d(volume, zero, zero, roll, align_corners=True))
    return torch.stack(outs, 1)


def _local_crop_boxes(volume: Tensor, boxes: Tensor, grid: G.VoxelGridSpec, size: int) -> Tensor:
    sz = sy = sx = size
    batch, channels = volume.shape[:2]
    n_boxes = boxes.shape[1]
    lo, hi = boxes[..., :3], boxes[..., 3:]
    axes = [(torch.arange(n, dtype=boxes.dtype) + 0.5) / n for n in (sx, sy, sz)]
    fz, fy, fx = torch.meshgrid(axes[2], axes[1], axes[0], indexing="ij")
    frac = torch.stack((fx, fy, fz), dim=-1)
    points = lo[:, :, None, None, None, :] + frac * (hi - lo)[:, :, None, None, None, :]
    coords = grid.world_to_normalized(points).reshape(batch, n_boxes * sz, sy, sx, 3)
    crops = F.grid_sample(volume, coords, mode="bilinear", padding_mode="zeros", align_corners=False)
    return crops.view(batch, channels, n_boxes, sz, sy, sx).transpose(1, 2).contiguous()


def _kornia_crop_boxes(volume: Tensor, boxes: Tensor, grid: G.VoxelGridSpec, size: int) -> Tensor:
    """kornia ``warp_affine3d`` (what ``crop_by_transform_mat3d`` calls), one batch element per box: the voxel-index
    affine map with ``align_corners=True`` samples our cell-centred points."""
    batch, channels = volume.shape[:2]
    n_boxes = boxes.shape[1]
    bmin = torch.tensor(grid.bounds_min, dtype=volume.dtype)
    voxel = torch.tensor(grid.voxel_size, dtype=volume.dtype)
    scale = (boxes[..., 3:] - boxes[..., :3]) / size / voxel  # input voxels per output cell, (x, y, z)
    offset = (boxes[..., :3] - bmin) / voxel + 0.5 * scale - 0.5  # input index of output cell 0
    src_to_dst = torch.zeros(batch, n_boxes, 3, 4, dtype=volume.dtype)
    src_to_dst[..., [0, 1, 2], [0, 1, 2]] = 1.0 / scale
    src_to_dst[..., 3] = -offset / scale
    src = volume[:, None].expand(batch, n_boxes, *volume.shape[1:]).reshape(batch * n_boxes, *volume.shape[1:])
    out = warp_affine3d(src, src_to_dst.reshape(-1, 3, 4), (size, size, size), align_corners=True)
    return out.view(batch, n_boxes, channels, size, size, size)


def _look_at(eye: tuple[float, float, float], target=(0.0, 0.0, 0.3)) -> Tensor:
    eye_t = torch.tensor(eye)
    fwd = torch.tensor(target) - eye_t
    fwd = fwd / fwd.norm()
    right = torch.linalg.cross(fwd, torch.tensor([0.0, 0.0, 1.0]))
    right = right / right.norm()
    pose = torch.eye(4)
    pose[:3, :3] = torch.stack((right, torch.linalg.cross(fwd, right), fwd), dim=1)
    pose[:3, 3] = eye_t
    return pose


def _views(n: int, size: int = 128) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """``n`` cameras 3 m around the grid (zero skew), an RGB+1 image and a depth map that hits the grid."""
    torch.manual_seed(0)
    angles = torch.linspace(0.3, 5.5, n).tolist()
    poses = torch.stack([_look_at((3.0 * math.cos(a), 3.0 * math.sin(a), 1.6)) for a in angles])
    K = torch.tensor([[110.0, 0.0, (size - 1) / 2], [0.0, 110.0, (size - 1) / 2], [0.0, 0.0, 1.0]]).repeat(n, 1, 1)
    rgb = torch.cat((torch.rand(n, 3, size, size), torch.ones(n, 1, size, size)), 1)
    depth = 2.6 + 0.8 * torch.rand(n, size, size)
    depth[:, ::9, ::7] = 0.0
    return rgb, depth, K, poses


def _max_diff(a, b) -> float:
    if isinstance(a, tuple):
        return max(_max_diff(x, y) for x, y in zip(a, b, strict=True))
    return float((a.double() - b.double()).abs().max()) if a.numel() else 0.0


def _time(fns: list[Callable[[], object]], rounds: int, warmup: int, inner: int) -> list[float]:
    """Median ms per call of each fn over ``rounds`` rounds, each running every fn (``inner`` calls), shuffled."""
    for fn in fns:
        for _ in range(warmup):
            fn()
    samples: list[list[float]] = [[] for _ in fns]
    order = list(range(len(fns)))
    rng = random.Random(0)
    for _ in range(rounds):
        rng.shuffle(order)
        for i in order:
            start = time.perf_counter()
            for _ in range(inner):
                fns[i]()
            samples[i].append((time.perf_counter() - start) * 1e3 / inner)
    return [statistics.median(s) for s in samples]


def _fmt(ms: float) -> str:
    return f"{ms:.4f}" if ms < 0.1 else f"{ms:.2f}" if ms < 100 else f"{ms:.0f}"


#: op -> (the kornia function(s) of its kornia route, the route ``threedq.geometry`` ships)
KORNIA = {
    "invert_rigid": ("linalg.inverse_transformation", "kornia"),
    "yaw_matrix": ("conversions.axis_angle_to_rotation_matrix", "kornia"),
    "transform_points": ("linalg.transform_points", "kornia"),
    "project": ("camera.perspective.project_points (no skew)", "local"),
    "unproject_depth": ("depth.depth_to_3d_v2 (no skew)", "local"),
    "depth_to_points": ("depth_to_3d_v2 + transform_points", "local"),
    "unproject_rgb": ("inverse_transformation + transform_points + project_points", "mixed"),
    "occupancy_from_depth": ("depth_to_3d_v2 + transform_points", "local"),
    "free_space_from_depth": ("unproject_meshgrid + depth_to_3d_v2 + transform_points", "local"),
    "resample_to_frustum": ("unproject_meshgrid + transform_points", "local"),
    "crop_boxes": ("transform.warp_affine3d", "local"),
    "rotate_yaw": ("transform.rotate (2D, folded slices)", "local"),
}


def _rows(quick: bool) -> list[tuple]:
    """The benchmark rows: ``(op, shape, kornia function, ships, (local, kornia, threedq), inner, rounds)``."""
    rounds, big_rounds = (5, 3) if quick else (21, 7)

    def row(op: str, shape: str, *args: object, inner: int = 1, n: int = rounds, k3d: bool = False) -> tuple:
        kornia = _kornia_rotate_yaw_3d if k3d else globals()[f"_kornia_{op}"]
        fns = tuple((lambda f=f: f(*args)) for f in (globals()[f"_local_{op}"], kornia, getattr(G, op)))
        kname, ships = ("transform.rotate3d (align_corners=True)", "local") if k3d else KORNIA[op]
        return op, shape, kname, ships, fns, inner, n

    grid = G.VoxelGridSpec((-1.28, -1.28, -0.32), (1.28, 1.28, 0.96), (64, 64, 32))
    fgrid = grid.half()
    rgb, depth, K, poses = _views(4)
    centres = grid.voxel_centres().reshape(1, -1, 3).expand(4, -1, -1)
    cam_T_R = G.invert_rigid(poses)
    points_cam = G.transform_points(cam_T_R, centres)
    yaw36 = G.yaw_angles(36)
    feats2 = torch.randn(2, 32, *fgrid.volume_shape)
    feats4 = torch.randn(4, 32, *fgrid.volume_shape)
    raw4 = torch.rand(4, 4, *grid.volume_shape)
    centre = torch.rand(4, 3, 3) * torch.tensor([1.6, 1.6, 0.4]) + torch.tensor([-0.8, -0.8, 0.0])
    boxes = torch.cat((centre - 0.25, centre + 0.25), -1)
    # a self-labelling batch: 8 pool scenes, 15 candidate boxes each (objects of 0.3-0.9 m)
    feats8 = torch.randn(8, 32, *fgrid.volume_shape)
    centre15 = torch.rand(8, 15, 3) * torch.tensor([2.4, 2.4, 0.8]) + torch.tensor([-1.2, -1.2, -0.3])
    half15 = (torch.rand(8, 15, 3) * 0.6 + 0.3) / 2
    boxes15 = torch.cat((centre15 - half15, centre15 + half15), -1)
    frustum_args = (G.scale_intrinsics(K[:2], 0.5, 0.5), poses[:2], (64, 64), (1.2, 5.2), 32)
    n_crops = 10 if quick else 50
    crops = torch.randn(n_crops, 32, 16, 16, 16)
    yaws = yaw36[None].expand(n_crops, -1).contiguous()
    ds, ks = depth[:, ::2, ::2], K * torch.tensor([0.5, 0.5, 1.0])[:, None]
    crops_shape = f"[{n_crops}, 32, 16, 16, 16]"
    rows = [
        row("invert_rigid", "[4, 4, 4]", poses, inner=200),
        row("yaw_matrix", "[36]", yaw36, inner=200),
        row("transform_points", "[4, 131072, 3]", cam_T_R, centres),
        row("project", "[4, 131072, 3]", points_cam, K),
        row("unproject_depth", "[4, 128, 128]", depth, K),
        row("depth_to_points", "[4, 128, 128]", depth, K, poses),
        row("unproject_rgb", "[4, 4, 128, 128] -> 64x64x32", rgb, K, poses, grid),
        row("occupancy_from_depth", "[4, 128, 128] -> 64x64x32", depth, K, poses, grid),
        row("free_space_from_depth", "[4, 64, 64] x 32 -> 32x32x16", ds, ks, poses, fgrid),
        row("resample_to_frustum", "[2, 32, 16, 32, 32] -> 32x64x64", feats2, fgrid, *frustum_args),
        row("crop_boxes", "[4, 32, 16, 32, 32], 3 boxes, 16^3", feats4, boxes, fgrid, 16),
        row("crop_boxes", "[8, 32, 16, 32, 32], 15 boxes, 16^3", feats8, boxes15, fgrid, 16),
        row("crop_boxes", "[1, 32, 16, 32, 32], 15 boxes, 16^3 (one scene)", feats8[:1], boxes15[:1], fgrid, 16),
        row("crop_boxes", "[4, 4, 32, 64, 64], 3 boxes, 16^3", raw4, boxes, grid, 16),
        row("rotate_yaw", f"36 x {crops_shape}", crops, yaws, n=big_rounds),
        row("rotate_yaw", f"1 x {crops_shape}", crops, yaws[:, 3:4]),
    ]
    if not quick:
        rows.append(row("rotate_yaw", f"36 x {crops_shape}", crops, yaws, n=big_rounds, k3d=True))
    return rows


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--quick", action="store_true", help="fewer rounds, rotate_yaw on 10 crops, no rotate3d")
    args = parser.parse_args()
    torch.set_num_threads(2)
    rows = _rows(args.quick)
    print(f"threedq.geometry vs kornia {kornia.__version__}, {machine()}\n")
    print(table(["op", "shape", "local ms", "kornia ms", "threedq ms", "kornia / local", "max abs diff",
                 "kornia function", "ships"]))
    with torch.no_grad():
        for op, shape, kname, ships, (local_fn, kornia_fn, ours_fn), inner, n_rounds in rows:
            diff = max(_max_diff(local_fn(), kornia_fn()), _max_diff(local_fn(), ours_fn()))
            t_local, t_kornia, t_ours = _time([local_fn, kornia_fn, ours_fn], n_rounds, 2, inner)
            print(f"| {op} | {shape} | {_fmt(t_local)} | {_fmt(t_kornia)} | {_fmt(t_ours)} | "
                  f"{t_kornia / t_local:.2f}x | {diff:.1e} | {kname} | {ships} |", flush=True)


if __name__ == "__main__":
    main()
