"""Tests for threedq.geometry.unproject (gather unprojection, occupancy, free space)."""

from __future__ import annotations

import math

import pytest
import torch

from threedq.geometry import (
    VoxelGridSpec,
    free_space_from_depth,
    occupancy_from_depth,
    unproject_rgb,
    unproject_rgbd_occupied,
    yaw_matrix,
)

# Camera axes (OpenCV) expressed in R, as columns of the camera-to-R rotation.
LOOK_DOWN = torch.tensor([[1.0, 0.0, 0.0], [0.0, -1.0, 0.0], [0.0, 0.0, -1.0]])  # z_cam = -z_R
LOOK_ALONG_X = torch.tensor([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])  # z_cam = +x_R


def pose(
    rotation: torch.Tensor, position: tuple[float, float, float], dtype: torch.dtype = torch.float32
) -> torch.Tensor:
    """R_T_cam [1, 4, 4] for a camera at ``position`` (in R) with camera-to-R ``rotation``."""
    out = torch.eye(4, dtype=dtype)
    out[:3, :3] = rotation.to(dtype)
    out[:3, 3] = torch.tensor(position, dtype=dtype)
    return out[None]


def intrinsics(f: float, cx: float, cy: float, skew: float = 0.0, dtype: torch.dtype = torch.float32) -> torch.Tensor:
    return torch.tensor([[[f, skew, cx], [0.0, f, cy], [0.0, 0.0, 1.0]]], dtype=dtype)


def unproject_rgb_naive(rgb: torch.Tensor, K: torch.Tensor, R_T_cam: torch.Tensor, grid: VoxelGridSpec) -> torch.Tensor:
    """Per-voxel Python loop: project each voxel centre, zero if behind/outside, else bilinear (border clamp)."""
    batch, channels, height, width = rgb.shape
    nz, ny, nx = grid.volume_shape
    out = torch.zeros(batch, channels, nz, ny, nx, dtype=rgb.dtype)
    (x0, y0, z0), (sx, sy, sz) = grid.bounds_min, grid.voxel_size
    for b in range(batch):
        rot, trans = R_T_cam[b, :3, :3], R_T_cam[b, :3, 3]
        fx, skew, cx = K[b, 0].tolist()
        fy, cy = K[b, 1, 1].item(), K[b, 1, 2].item()
        for k in range(nz):
            for j in range(ny):
                for i in range(nx):
                    centre = torch.tensor(
                        [x0 + (i + 0.5) * sx, y0 + (j + 0.5) * sy, z0 + (k + 0.5) * sz], dtype=rgb.dtype
                    )
                    x, y, z = (rot.T @ (centre - trans)).tolist()
                    if z <= 1e-4:
                        continue
                    u, v = (fx * x + skew * y) / z + cx, fy * y / z + cy
                    if not (-0.5 <= u <= width - 0.5 and -0.5 <= v <= height - 0.5):
                        continue
                    u, v = min(max(u, 0.0), width - 1.0), min(max(v, 0.0), height - 1.0)
                    u0, v0 = math.floor(u), math.floor(v)
                    u1, v1 = min(u0 + 1, width - 1), min(v0 + 1, height - 1)
                    a, c = u - u0, v - v0
                    out[b, :, k, j, i] = (
                        (1 - a) * (1 - c) * rgb[b, :, v0, u0]
                        + a * (1 - c) * rgb[b, :, v0, u1]
                        + (1 - a) * c * rgb[b, :, v1, u0]
                        + a * c * rgb[b, :, v1, u1]
                    )
    return out


def tiny_scene(dtype: torch.dtype = torch.float64) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, VoxelGridSpec]:
    """A 6x5x4 grid seen by two 7x9 cameras.

    Camera 0 is inside the grid looking along +x (slightly yawed): some voxels are behind it, some project
    outside the image, some inside. Camera 1 looks down from above.
    """
    grid = VoxelGridSpec((-1.0, -1.0, 0.0), (1.0, 1.0, 1.0), (6, 5, 4))
    rotation = yaw_matrix(torch.tensor(0.2, dtype=torch.float64)) @ LOOK_ALONG_X.double()
    R_T_cam = torch.cat((pose(rotation, (-0.3, 0.1, 0.45), dtype), pose(LOOK_DOWN, (0.1, -0.2, 2.0), dtype)))
    K = torch.cat((intrinsics(3.0, 4.2, 2.9, skew=0.4, dtype=dtype), intrinsics(4.0, 3.7, 3.1, dtype=dtype)))
    rgb = torch.rand(2, 3, 7, 9, dtype=dtype)
    return rgb, K, R_T_cam, grid


class TestUnprojectRgb:
    def test_smoke(self) -> None:
        rgb, K, R_T_cam, grid = tiny_scene(torch.float32)
        out = unproject_rgb(rgb, K, R_T_cam, grid)
        assert out.shape == (2, 3, 4, 5, 6) and out.dtype == torch.float32

    def test_exception(self) -> None:
        rgb, K, R_T_cam, grid = tiny_scene()
        with pytest.raises(ValueError, match=r"rgb must have shape \[B, C, H, W\]"):
            unproject_rgb(rgb[0], K, R_T_cam, grid)
        with pytest.raises(ValueError, match="floating-point"):
            unproject_rgb((rgb * 255).to(torch.uint8), K, R_T_cam, grid)
        with pytest.raises(ValueError, match=r"K must have shape \[B, 3, 3\] with B=2"):
            unproject_rgb(rgb, K[:1], R_T_cam, grid)
        with pytest.raises(ValueError, match=r"R_T_cam must have shape \[B, 4, 4\]"):
            unproject_rgb(rgb, K, R_T_cam[:, :3], grid)
        with pytest.raises(ValueError, match="grid must be a VoxelGridSpec"):
            unproject_rgb(rgb, K, R_T_cam, (6, 5, 4))  # type: ignore[arg-type]

    @pytest.mark.parametrize("batch", [1, 3])
    @pytest.mark.parametrize("channels", [1, 3, 8])
    def test_cardinality(self, batch: int, channels: int) -> None:
        grid = VoxelGridSpec((-1.0, -1.0, -1.0), (1.0, 1.0, 1.0), (4, 3, 2))
        out = unproject_rgb(
            torch.rand(batch, channels, 5, 6),
            intrinsics(4.0, 2.5, 2.0).expand(batch, -1, -1),
            pose(LOOK_DOWN, (0.0, 0.0, 3.0)).expand(batch, -1, -1),
            grid,
        )
        assert out.shape == (batch, channels, 2, 3, 4)

    def test_feature_matches_naive(self) -> None:
        torch.manual_seed(0)
        rgb, K, R_T_cam, grid = tiny_scene()
        fast = unproject_rgb(rgb, K, R_T_cam, grid)
        naive = unproject_rgb_naive(rgb, K, R_T_cam, grid)
        torch.testing.assert_close(fast, naive)
        # the scene exercises all cases: visible voxels and zeroed ones (behind / outside the image)
        zero = (naive == 0).all(dim=1)
        assert zero[0].any() and (~zero[0]).any() and (~zero[1]).any()

    def test_feature_behind_camera_is_zero(self) -> None:
        # camera at x = 0 looking along +x with a huge field of view: every voxel with x < 0 is behind it
        grid = VoxelGridSpec((-1.0, -1.0, -1.0), (1.0, 1.0, 1.0), (4, 4, 4))
        out = unproject_rgb(
            torch.rand(1, 3, 8, 8) + 0.5, intrinsics(0.5, 3.5, 3.5), pose(LOOK_ALONG_X, (0.0, 0.0, 0.0)), grid
        )
        assert (out[..., :2] == 0).all()
        assert (out[..., 2:] > 0).all()

    def test_feature_constant_image(self) -> None:
        # a constant image is reproduced exactly in the visible frustum, including the half-pixel rim
        grid = VoxelGridSpec((-1.0, -1.0, 0.0), (1.0, 1.0, 1.0), (8, 8, 4))
        out = unproject_rgb(
            torch.full((1, 3, 6, 6), 0.7), intrinsics(2.0, 2.5, 2.5), pose(LOOK_DOWN, (0.0, 0.0, 2.0)), grid
        )
        assert all(v == 0.0 or abs(v - 0.7) < 1e-6 for v in out.unique().tolist())
        assert (out[:, :, :, 3:5, 3:5] > 0.69).all()  # the centre column is always seen

    def test_gradcheck(self) -> None:
        torch.manual_seed(5)
        rgb, K, R_T_cam, grid = tiny_scene()
        rgb = rgb[:, :, :4, :5].contiguous().requires_grad_()
        small = VoxelGridSpec((-1.0, -1.0, 0.0), (1.0, 1.0, 1.0), (3, 2, 2))
        assert torch.autograd.gradcheck(lambda x: unproject_rgb(x, K, R_T_cam, small), (rgb,))


def plane_scene(depth_value: float = 0.85) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, VoxelGridSpec]:
    """A camera inside the grid at z = 0.95 looking straight down at a plane (constant z-depth)."""
    grid = VoxelGridSpec((-1.0, -1.0, -1.0), (1.0, 1.0, 1.0), (8, 8, 8))  # 0.25 m voxels
    K = intrinsics(24.0, 31.5, 31.5)  # 64 x 64, covers |x|, |y| <= 1.1 at depth 0.85
    depth = torch.full((1, 64, 64), depth_value)
    return depth, K, pose(LOOK_DOWN, (0.0, 0.0, 0.95)), grid


class TestOccupancyFromDepth:
    def test_smoke(self) -> None:
        depth, K, R_T_cam, grid = plane_scene()
        occ = occupancy_from_depth(depth, K, R_T_cam, grid)
        assert occ.shape == (1, 1, 8, 8, 8) and occ.dtype == torch.float32

    def test_exception(self) -> None:
        depth, K, R_T_cam, grid = plane_scene()
        with pytest.raises(ValueError, match=r"depth must be a float tensor of shape \[B, H, W\]"):
            occupancy_from_depth(depth[0], K, R_T_cam, grid)
        with pytest.raises(ValueError, match="R_T_cam"):
            occupancy_from_depth(depth, K, R_T_cam[0], grid)

    @pytest.mark.parametrize("batch", [1, 2])
    def test_cardinality(self, batch: int) -> None:
        depth, K, R_T_cam, grid = plane_scene()
        occ = occupancy_from_depth(
            depth.expand(batch, -1, -1), K.expand(batch, -1, -1), R_T_cam.expand(batch, -1, -1), grid.half()
        )
        assert occ.shape == (batch, 1, 4, 4, 4)

    def test_feature_plane(self) -> None:
        # plane at z = 0.95 - 0.85 = 0.1 -> voxel k = floor((0.1 + 1) / 0.25) = 4; invalid pixels are ignored
        # (a depth-0 point would be the camera centre, inside voxel k = 7)
        depth, K, R_T_cam, grid = plane_scene()
        depth[0, ::7, ::5] = 0.0
        depth[0, 3, 3] = float("nan")
        occ = occupancy_from_depth(depth, K, R_T_cam, grid)
        expected = torch.zeros(1, 1, 8, 8, 8)
        expected[:, :, 4] = 1.0
        torch.testing.assert_close(occ, expected)

    def test_feature_outside_dropped_and_batched(self) -> None:
        depth, K, R_T_cam, grid = plane_scene()
        far = torch.full_like(depth, 5.0)  # plane at z = -4.05: outside the grid
        occ = occupancy_from_depth(torch.cat((far, depth)), K.expand(2, -1, -1), R_T_cam.expand(2, -1, -1), grid)
        assert occ[0].sum() == 0 and occ[1, 0, 4].sum() == 64 and occ[1].sum() == 64

    def test_feature_boundary_is_half_open(self) -> None:
        # a point exactly on the boundary z = 0 between voxels 3 and 4 belongs to voxel 4
        depth, K, R_T_cam, grid = plane_scene(0.95)
        occ = occupancy_from_depth(depth, K, R_T_cam, grid)
        assert occ[0, 0, 4].sum() == 64 and occ.sum() == 64


def ray_scene() -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, VoxelGridSpec]:
    """One pixel whose ray runs along +x through the centre line of an 8x3x3 grid (0.25 m voxels)."""
    grid = VoxelGridSpec((-1.0, -0.375, -0.375), (1.0, 0.375, 0.375), (8, 3, 3))
    K = intrinsics(1.0, 0.0, 0.0)  # 1 x 1 image, its pixel centre on the optical axis
    depth = torch.tensor([[[1.8]]])  # camera at x = -1.2 -> surface at x = 0.6, voxel i = 6
    return depth, K, pose(LOOK_ALONG_X, (-1.2, 0.0, 0.0)), grid


class TestVoxelize:
    """The scatter behind the occupancy and free-space labels, against a per-point loop of the same float32 ops."""

    @staticmethod
    def _naive(points: torch.Tensor, keep: torch.Tensor, grid: VoxelGridSpec) -> torch.Tensor:
        lo = torch.tensor(grid.bounds_min, dtype=points.dtype)
        size = torch.tensor(grid.voxel_size, dtype=points.dtype)
        nx, ny, nz = grid.resolution
        out = torch.zeros(points.shape[0], 1, nz, ny, nx, dtype=points.dtype)
        for b in range(points.shape[0]):
            for n in range(points.shape[1]):
                if not bool(keep[b, n]):
                    continue
                cell = [float(torch.floor((points[b, n, a] - lo[a]) / size[a])) for a in range(3)]
                if all(math.isfinite(c) and 0 <= c < r for c, r in zip(cell, grid.resolution)):
                    i, j, k = (int(c) for c in cell)
                    out[b, 0, k, j, i] = 1.0
        return out

    def test_feature_matches_naive(self) -> None:
        from threedq.geometry.unproject import _voxelize

        grid = VoxelGridSpec((-1.28, -1.28, -0.32), (1.28, 1.28, 0.96), (16, 16, 8))
        g = torch.Generator().manual_seed(0)
        points = torch.rand(2, 600, 3, generator=g) * 3.2 - 1.6  # inside and outside the grid
        lo, hi = torch.tensor(grid.bounds_min), torch.tensor(grid.bounds_max)
        points[:, :40] = lo  # on the lower faces: inside
        points[:, 40:80] = hi  # on the upper faces: outside (half-open)
        points[:, 80:120] = lo + torch.tensor(grid.voxel_size) * torch.randint(0, 8, (40, 3), generator=g)  # cell edges
        points[0, 120] = float("nan")
        points[0, 121, 1] = float("inf")
        points[1, 122, 2] = -float("inf")
        points[1, 123] = 1e30
        keep = torch.rand(2, 600, generator=g) > 0.2
        keep[:, 120:124] = True
        got = _voxelize(points, keep, grid)
        assert got.shape == (2, 1, 8, 16, 16) and got.dtype == points.dtype
        assert torch.equal(got, self._naive(points, keep, grid))
        assert got.sum() > 0 and not torch.equal(got[0], got[1])

    def test_empty(self) -> None:
        from threedq.geometry.unproject import _voxelize

        grid = VoxelGridSpec((0.0, 0.0, 0.0), (1.0, 1.0, 1.0), (4, 4, 4))
        assert torch.equal(_voxelize(torch.zeros(3, 0, 3), torch.zeros(3, 0, dtype=torch.bool), grid),
                           torch.zeros(3, 1, 4, 4, 4))


class TestFreeSpaceFromDepth:
    def test_smoke(self) -> None:
        depth, K, R_T_cam, grid = ray_scene()
        free = free_space_from_depth(depth, K, R_T_cam, grid)
        assert free.shape == (1, 1, 3, 3, 8) and free.dtype == torch.float32

    def test_exception(self) -> None:
        depth, K, R_T_cam, grid = ray_scene()
        with pytest.raises(ValueError, match="samples_per_ray"):
            free_space_from_depth(depth, K, R_T_cam, grid, samples_per_ray=0)
        with pytest.raises(ValueError, match="margin"):
            free_space_from_depth(depth, K, R_T_cam, grid, margin=-0.1)
        with pytest.raises(ValueError, match=r"K must have shape \[B, 3, 3\]"):
            free_space_from_depth(depth, K[0], R_T_cam, grid)

    @pytest.mark.parametrize("batch", [1, 3])
    def test_cardinality(self, batch: int) -> None:
        depth, K, R_T_cam, grid = plane_scene()
        free = free_space_from_depth(
            depth.expand(batch, -1, -1), K.expand(batch, -1, -1), R_T_cam.expand(batch, -1, -1), grid, samples_per_ray=4
        )
        assert free.shape == (batch, 1, 8, 8, 8)

    @pytest.mark.parametrize("margin", [None, 0.0, 0.1])
    def test_feature_single_ray(self, margin: float | None) -> None:
        # voxels 0..5 along the ray are free; the surface voxel 6 is not (occupied); voxel 7 (behind) is not
        depth, K, R_T_cam, grid = ray_scene()
        free = free_space_from_depth(depth, K, R_T_cam, grid, margin=margin)
        expected = torch.zeros(1, 1, 3, 3, 8)
        expected[0, 0, 1, 1, :6] = 1.0
        torch.testing.assert_close(free, expected)

    def test_feature_margin_and_invalid(self) -> None:
        depth, K, R_T_cam, grid = ray_scene()
        # a one-metre margin stops the samples at x = -0.4: voxels 0..2 only
        free = free_space_from_depth(depth, K, R_T_cam, grid, margin=1.0)
        assert free[0, 0, 1, 1].tolist() == [1, 1, 1, 0, 0, 0, 0, 0] and free.sum() == 3
        assert free_space_from_depth(torch.zeros_like(depth), K, R_T_cam, grid).sum() == 0

    def test_feature_plane(self) -> None:
        # looking down at the plane in voxel k = 4 from k = 7 with the default margin (0.25): the samples
        # reach z ~ 0.36 (k = 5, where the frustum spans |x|, |y| <= 0.77 > 0.75); only slabs 5..7 can be free, the
        # plane and below are not, and nothing free is occupied
        depth, K, R_T_cam, grid = plane_scene()
        free = free_space_from_depth(depth, K, R_T_cam, grid)
        occ = occupancy_from_depth(depth, K, R_T_cam, grid)
        assert (free * occ).sum() == 0
        assert free[0, 0, :5].sum() == 0
        assert (free[0, 0, 5] == 1).all()
        assert (free[0, 0, 7, 3:5, 3:5] == 1).all()
        # deterministic
        torch.testing.assert_close(free, free_space_from_depth(depth, K, R_T_cam, grid))


def dense_rgbd(rgb: torch.Tensor, depth: torch.Tensor, K: torch.Tensor, R_T_cam: torch.Tensor,
               grid: VoxelGridSpec) -> torch.Tensor:
    """``cat[occ, occ * unproject_rgb(rgb)]`` over the whole grid: the reference of the sparse gather."""
    occ = occupancy_from_depth(depth.to(rgb.dtype), K, R_T_cam, grid)
    return torch.cat((occ, occ * unproject_rgb(rgb, K, R_T_cam, grid)), dim=1)


class TestUnprojectRgbdOccupied:
    """The sparse gather against the dense one (one body, two implementations)."""

    def test_exception(self) -> None:
        depth, K, R_T_cam, grid = plane_scene()
        with pytest.raises(ValueError, match=r"rgb must have shape \[B, 3, H, W\]"):
            unproject_rgbd_occupied(torch.rand(1, 1, 64, 64), depth, K, R_T_cam, grid)

    @pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
    def test_feature_equals_dense(self, dtype: torch.dtype) -> None:
        torch.manual_seed(7)
        depth, K, R_T_cam, grid = plane_scene()
        B = 2
        rgb = torch.rand(B, 3, 64, 64, dtype=dtype)
        depth = torch.stack([depth[0], depth[0] * 0.9]).to(dtype)
        depth[1, :10] = 0  # invalid pixels
        args = (rgb, depth, K.expand(B, -1, -1).to(dtype), R_T_cam.expand(B, -1, -1).to(dtype), grid)
        dense, sparse = dense_rgbd(*args), unproject_rgbd_occupied(*args)
        assert sparse.shape == dense.shape and sparse.dtype == dense.dtype
        assert (dense[:, 0] > 0).sum() > 10
        torch.testing.assert_close(sparse, dense, rtol=0, atol=1e-6 if dtype == torch.float32 else 1e-12)

    def test_empty_depth(self) -> None:
        depth, K, R_T_cam, grid = plane_scene()
        out = unproject_rgbd_occupied(torch.rand(1, 3, 64, 64), torch.zeros_like(depth), K, R_T_cam, grid)
        assert (out == 0).all()
