"""Tests for threedq.geometry.frustum."""

from __future__ import annotations

import math
from collections.abc import Callable

import pytest
import torch

from threedq.geometry.frustum import frustum_depth_max, frustum_points, resample_to_frustum, scale_intrinsics
from threedq.geometry.grid import VoxelGridSpec
from threedq.nets import depth_max_pool

GRID = VoxelGridSpec((-1.0, -0.8, -0.6), (1.0, 0.8, 0.6), (6, 5, 4))  # volume_shape (4, 5, 6)


def voxel_index(points: torch.Tensor) -> torch.Tensor:
    """Continuous voxel indices ``(i, j, k)`` of points in R on :data:`GRID` (a voxel centre maps to its index)."""
    res = torch.tensor(GRID.resolution, dtype=points.dtype)
    return (GRID.world_to_normalized(points) + 1) * res / 2 - 0.5


def make_K(
    batch: int, fx: float = 6.0, fy: float = 5.0, cx: float = 1.7, cy: float = 1.2, skew: float = 0.0
) -> torch.Tensor:
    K = torch.tensor([[fx, skew, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]], dtype=torch.float64)
    return K.repeat(batch, 1, 1)


def look_at(eye: tuple[float, float, float], target: tuple[float, float, float] = (0.0, 0.0, 0.0)) -> torch.Tensor:
    """Camera-to-R pose [4, 4] (OpenCV axes) of a camera at ``eye`` looking at ``target``, R has z up."""
    eye_t = torch.tensor(eye, dtype=torch.float64)
    forward = torch.tensor(target, dtype=torch.float64) - eye_t
    forward = forward / forward.norm()
    right = torch.linalg.cross(forward, torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64))
    right = right / right.norm()
    down = torch.linalg.cross(forward, right)
    pose = torch.eye(4, dtype=torch.float64)
    pose[:3, :3] = torch.stack((right, down, forward), dim=1)
    pose[:3, 3] = eye_t
    return pose


def poses(batch: int) -> torch.Tensor:
    eyes = [(-2.5, 0.4, 0.9), (1.1, -2.2, 1.4), (0.3, 2.4, -0.5)]
    return torch.stack([look_at(eyes[b % len(eyes)]) for b in range(batch)])


def naive_point(K: torch.Tensor, pose: torch.Tensor, u: int, v: int, z: float) -> torch.Tensor:
    p_cam = z * (torch.linalg.inv(K) @ torch.tensor([u, v, 1.0], dtype=K.dtype))
    return pose[:3, :3] @ p_cam + pose[:3, 3]


def naive_trilinear(volume: torch.Tensor, grid: VoxelGridSpec, p: torch.Tensor) -> torch.Tensor:
    """Trilinear sample of volume [C, Z, Y, X] at point p (x, y, z) in R, zero outside (cell-centred grid)."""
    idx = [(p[a].item() - grid.bounds_min[a]) / grid.voxel_size[a] - 0.5 for a in range(3)]  # (i, j, k)
    base = [math.floor(c) for c in idx]
    frac = [c - b for c, b in zip(idx, base)]
    nx, ny, nz = grid.resolution
    out = torch.zeros(volume.shape[0], dtype=volume.dtype)
    for di in (0, 1):
        for dj in (0, 1):
            for dk in (0, 1):
                i, j, k = base[0] + di, base[1] + dj, base[2] + dk
                if not (0 <= i < nx and 0 <= j < ny and 0 <= k < nz):
                    continue
                wx = frac[0] if di else 1 - frac[0]
                wy = frac[1] if dj else 1 - frac[1]
                wz = frac[2] if dk else 1 - frac[2]
                w = wx * wy * wz
                out += w * volume[:, k, j, i]
    return out


class TestScaleIntrinsics:
    def test_smoke(self) -> None:
        assert scale_intrinsics(torch.eye(3), 0.5, 0.5).shape == (3, 3)

    def test_exception(self) -> None:
        with pytest.raises(ValueError, match=r"K must have shape \[\.\.\., 3, 3\]"):
            scale_intrinsics(torch.eye(4), 0.5, 0.5)
        with pytest.raises(ValueError, match="positive"):
            scale_intrinsics(torch.eye(3), 0.0, 0.5)

    @pytest.mark.parametrize("shape", [(), (1,), (2, 3)])
    def test_cardinality(self, shape: tuple[int, ...]) -> None:
        K = make_K(1)[0].expand(*shape, 3, 3)
        assert scale_intrinsics(K, 2.0, 0.25).shape == (*shape, 3, 3)

    def test_feature(self) -> None:
        K = torch.tensor([[[100.0, 2.0, 127.5], [0.0, 90.0, 63.5], [0.0, 0.0, 1.0]]])
        expected = torch.tensor([[[50.0, 1.0, 63.5], [0.0, 22.5, 15.5], [0.0, 0.0, 1.0]]])
        torch.testing.assert_close(scale_intrinsics(K, 0.5, 0.25), expected)

    def test_round_trip(self) -> None:
        torch.manual_seed(0)
        K = make_K(1, fx=200.0, fy=180.0, cx=130.2, cy=118.7, skew=1.5)[0]
        size_hw = (256, 320)
        K_half = scale_intrinsics(K, 0.5, 0.25)
        size_half = (size_hw[0] * 0.25, size_hw[1] * 0.5)
        points = torch.randn(50, 3, dtype=torch.float64) + torch.tensor([0.0, 0.0, 4.0], dtype=torch.float64)

        def relative(K_: torch.Tensor, hw: tuple[float, float]) -> torch.Tensor:
            uvw = points @ K_.T
            uv = uvw[:, :2] / uvw[:, 2:]
            return (uv + 0.5) / torch.tensor([hw[1], hw[0]], dtype=torch.float64)

        torch.testing.assert_close(relative(K_half, size_half), relative(K, size_hw))
        torch.testing.assert_close(scale_intrinsics(K_half, 2.0, 4.0), K)

    def test_pixel_centres(self) -> None:
        # Full-res pixels 0 and 1 (centres u = 0, 1) merge into half-res pixel 0: its centre is at u = 0.5 full-res.
        K = make_K(1)[0]
        K_half = scale_intrinsics(K, 0.5, 0.5)
        p = torch.linalg.inv(K) @ torch.tensor([0.5, 0.5, 1.0], dtype=torch.float64)
        uvw = K_half @ p
        torch.testing.assert_close(uvw[:2] / uvw[2], torch.zeros(2, dtype=torch.float64))


class TestFrustumPoints:
    def test_feature(self) -> None:
        K = make_K(2)
        pose = poses(2)
        pts = frustum_points(K, pose, (3, 4), (1.0, 3.0), 4)
        assert pts.shape == (2, 4, 3, 4, 3) and pts.dtype == torch.float64
        depths = [1.25, 1.75, 2.25, 2.75]
        for b in range(2):
            for d, z in enumerate(depths):
                for v in range(3):
                    for u in range(4):
                        torch.testing.assert_close(pts[b, d, v, u], naive_point(K[b], pose[b], u, v, z))

    def test_skew(self) -> None:
        K = make_K(1, skew=0.7)
        pts = frustum_points(K, poses(1), (2, 3), (0.5, 1.5), 1)
        torch.testing.assert_close(pts[0, 0, 1, 2], naive_point(K[0], poses(1)[0], 2, 1, 1.0))


def gradcheck_small(op: Callable[[torch.Tensor, VoxelGridSpec, torch.Tensor, torch.Tensor], torch.Tensor]) -> bool:
    """float64 gradcheck of ``op(volume, grid, K, pose)`` w.r.t. the volume: 2 cameras on a 3 x 4 x 2 grid."""
    torch.manual_seed(0)
    grid = VoxelGridSpec((-1.0, -1.0, -1.0), (1.0, 1.0, 1.0), (3, 4, 2))
    volume = torch.rand(2, 2, *grid.volume_shape, dtype=torch.float64, requires_grad=True)
    K, pose = make_K(2, fx=2.0, fy=2.0, cx=1.0, cy=0.5), poses(2)
    return torch.autograd.gradcheck(lambda vol: op(vol, grid, K, pose), (volume,))


class TestResampleToFrustum:
    def test_smoke(self) -> None:
        volume = torch.rand(1, 3, *GRID.volume_shape)
        out = resample_to_frustum(volume, GRID, make_K(1).float(), poses(1).float(), (3, 4), (1.0, 4.0), 8)
        assert out.shape == (1, 3, 8, 3, 4) and out.dtype == torch.float32

    def test_exception(self) -> None:
        volume = torch.rand(1, 3, *GRID.volume_shape)
        K, pose = make_K(1), poses(1)
        with pytest.raises(ValueError, match="does not match grid.volume_shape"):
            fine = VoxelGridSpec(GRID.bounds_min, GRID.bounds_max, (12, 10, 8))  # volume lives on fine.half()
            resample_to_frustum(volume, fine, K, pose, (3, 4), (1.0, 4.0), 8)
        with pytest.raises(ValueError, match=r"volume must have shape \[B, C, Z, Y, X\]"):
            resample_to_frustum(volume[0], GRID, K, pose, (3, 4), (1.0, 4.0), 8)
        with pytest.raises(ValueError, match=r"K must have shape \[B, 3, 3\] with B=1"):
            resample_to_frustum(volume, GRID, make_K(2), pose, (3, 4), (1.0, 4.0), 8)
        with pytest.raises(ValueError, match=r"R_T_cam must have shape \[B, 4, 4\]"):
            resample_to_frustum(volume, GRID, K, pose[:, :3], (3, 4), (1.0, 4.0), 8)
        with pytest.raises(ValueError, match="depth_range"):
            resample_to_frustum(volume, GRID, K, pose, (3, 4), (4.0, 1.0), 8)
        with pytest.raises(ValueError, match="depth_range"):
            resample_to_frustum(volume, GRID, K, pose, (3, 4), (0.0, 1.0), 8)
        with pytest.raises(ValueError, match="num_planes"):
            resample_to_frustum(volume, GRID, K, pose, (3, 4), (1.0, 4.0), 0)
        with pytest.raises(ValueError, match="image_size"):
            resample_to_frustum(volume, GRID, K, pose, (3, 0), (1.0, 4.0), 8)
        with pytest.raises(ValueError, match="VoxelGridSpec"):
            resample_to_frustum(volume, (4, 5, 6), K, pose, (3, 4), (1.0, 4.0), 8)  # type: ignore[arg-type]

    @pytest.mark.parametrize("batch", [1, 2, 3])
    @pytest.mark.parametrize("size_dhw", [(1, 1, 1), (4, 3, 5), (8, 6, 2)])
    def test_cardinality(self, batch: int, size_dhw: tuple[int, int, int]) -> None:
        d, h, w = size_dhw
        volume = torch.rand(batch, 2, *GRID.volume_shape, dtype=torch.float64)
        out = resample_to_frustum(volume, GRID, make_K(batch), poses(batch), (h, w), (1.0, 4.0), d)
        assert out.shape == (batch, 2, d, h, w)

    def test_matches_naive_loop(self) -> None:
        torch.manual_seed(0)
        batch, channels, (h, w), depth = 2, 2, (3, 4), 5
        volume = torch.randn(batch, channels, *GRID.volume_shape, dtype=torch.float64)
        K, pose = make_K(batch), poses(batch)
        near, far = 1.5, 4.0
        out = resample_to_frustum(volume, GRID, K, pose, (h, w), (near, far), depth)
        expected = torch.zeros_like(out)
        for b in range(batch):
            for d in range(depth):
                z = near + (d + 0.5) * (far - near) / depth
                for v in range(h):
                    for u in range(w):
                        p = naive_point(K[b], pose[b], u, v, z)
                        expected[b, :, d, v, u] = naive_trilinear(volume[b], GRID, p)
        assert (expected != 0).float().mean() > 0.5  # most samples hit the grid
        torch.testing.assert_close(out, expected)

    def test_linear_field(self) -> None:
        # Trilinear interpolation reproduces a linear function exactly between voxel centres.
        coeffs = torch.tensor([0.7, -1.3, 2.1], dtype=torch.float64)
        offset = 0.4
        centres = GRID.voxel_centres(dtype=torch.float64)  # [Z, Y, X, 3]
        volume = (centres @ coeffs + offset)[None, None]
        K, pose = make_K(2), poses(2)
        out = resample_to_frustum(volume.expand(2, 1, -1, -1, -1), GRID, K, pose, (6, 8), (1.0, 4.0), 16)
        points = frustum_points(K, pose, (6, 8), (1.0, 4.0), 16)
        index = voxel_index(points)
        upper = torch.tensor([n - 1 for n in GRID.resolution], dtype=torch.float64)
        inside = ((index >= 0) & (index <= upper)).all(dim=-1)
        assert inside.sum() > 50
        expected = points @ coeffs + offset
        torch.testing.assert_close(out[:, 0][inside], expected[inside])
        # Far outside the grid the samples are zero.
        outside = ((index < -1) | (index > upper + 1)).any(dim=-1)
        assert outside.any() and (out[:, 0][outside] == 0).all()

    def test_half_resolution_consistency(self) -> None:
        # With a linear field, a half-res sample equals the mean of the 2x2 full-res samples it covers.
        coeffs = torch.tensor([0.3, 0.5, -0.9], dtype=torch.float64)
        big = VoxelGridSpec((-4.0, -4.0, -4.0), (4.0, 4.0, 4.0), (8, 8, 8))
        volume = (big.voxel_centres(dtype=torch.float64) @ coeffs)[None, None]
        K, pose = make_K(1, fx=3.0, fy=3.0, cx=1.5, cy=1.5), look_at((-2.0, 0.1, 0.2))[None]
        full = resample_to_frustum(volume, big, K, pose, (4, 4), (0.5, 2.5), 4)
        half = resample_to_frustum(volume, big, scale_intrinsics(K, 0.5, 0.5), pose, (2, 2), (0.5, 2.5), 4)
        pooled = torch.nn.functional.avg_pool3d(full, kernel_size=(1, 2, 2))
        torch.testing.assert_close(half, pooled)

    def test_gradcheck(self) -> None:
        assert gradcheck_small(lambda vol, grid, K, T: resample_to_frustum(vol, grid, K, T, (2, 3), (1.5, 3.5), 3))

    def test_low_precision_volume(self) -> None:
        torch.manual_seed(0)
        volume = torch.rand(1, 4, *GRID.volume_shape)
        K, pose = make_K(1).float(), poses(1).float()
        ref = resample_to_frustum(volume, GRID, K, pose, (6, 8), (1.0, 4.0), 8)
        out = resample_to_frustum(volume.bfloat16(), GRID, K, pose, (6, 8), (1.0, 4.0), 8)
        assert out.dtype == torch.bfloat16
        torch.testing.assert_close(out.float(), ref, rtol=0, atol=2e-2)

    def test_channels_last_volume(self) -> None:
        volume = torch.rand(2, 3, *GRID.volume_shape)
        K, pose = make_K(2).float(), poses(2).float()
        ref = resample_to_frustum(volume, GRID, K, pose, (3, 4), (1.0, 4.0), 4)
        out = resample_to_frustum(volume.to(memory_format=torch.channels_last_3d), GRID, K, pose, (3, 4), (1.0, 4.0), 4)
        torch.testing.assert_close(out, ref)


class TestFrustumDepthMax:
    """``frustum_depth_max`` against the two steps it fuses: ``depth_max_pool(resample_to_frustum(...))``."""

    @staticmethod
    def both(volume: torch.Tensor, grid: VoxelGridSpec, K: torch.Tensor, pose: torch.Tensor, hw: tuple[int, int],
             depth_range: tuple[float, float], planes: int, pool: int) -> tuple[torch.Tensor, torch.Tensor]:
        ref = depth_max_pool(resample_to_frustum(volume, grid, K, pose, hw, depth_range, planes), pool)
        return ref, frustum_depth_max(volume, grid, K, pose, hw, depth_range, planes, pool)

    def test_smoke(self) -> None:
        volume = torch.rand(1, 3, *GRID.volume_shape)
        out = frustum_depth_max(volume, GRID, make_K(1).float(), poses(1).float(), (3, 4), (1.0, 4.0), 8, 4)
        assert out.shape == (1, 3, 2, 3, 4) and out.dtype == torch.float32

    def test_exception(self) -> None:
        volume = torch.rand(1, 3, *GRID.volume_shape)
        K, pose = make_K(1), poses(1)
        for pool in (3, 0, 2.5, True):
            with pytest.raises(ValueError, match="pool must be a positive int dividing num_planes=8"):
                frustum_depth_max(volume, GRID, K, pose, (3, 4), (1.0, 4.0), 8, pool)  # type: ignore[arg-type]
        with pytest.raises(ValueError, match="does not match grid.volume_shape"):
            frustum_depth_max(volume[:, :, :2], GRID, K, pose, (3, 4), (1.0, 4.0), 8, 4)
        with pytest.raises(ValueError, match=r"K must have shape \[B, 3, 3\] with B=1"):
            frustum_depth_max(volume, GRID, make_K(2), pose, (3, 4), (1.0, 4.0), 8, 4)
        with pytest.raises(ValueError, match="floating"):
            frustum_depth_max(volume.long(), GRID, K, pose, (3, 4), (1.0, 4.0), 8, 4)

    @pytest.mark.parametrize(("batch", "hw", "planes", "pool"),
                             [(1, (1, 1), 1, 1), (2, (3, 5), 8, 4), (3, (6, 2), 6, 2), (2, (4, 4), 4, 4)])
    def test_shapes(self, batch: int, hw: tuple[int, int], planes: int, pool: int) -> None:
        volume = torch.rand(batch, 2, *GRID.volume_shape, dtype=torch.float64)
        out = frustum_depth_max(volume, GRID, make_K(batch), poses(batch), hw, (1.0, 4.0), planes, pool)
        assert out.shape == (batch, 2, planes // pool, *hw)

    @pytest.mark.parametrize("memory_format", [torch.contiguous_format, torch.channels_last_3d])
    @pytest.mark.parametrize(("depth_range", "planes", "pool"), [((1.0, 4.0), 16, 8), ((0.5, 6.0), 24, 4),
                                                                 ((1.0, 4.0), 16, 1), ((2.0, 2.6), 8, 8)])
    def test_bitwise_two_steps(self, depth_range: tuple[float, float], planes: int, pool: int,
                               memory_format: torch.memory_format) -> None:
        # values and the volume's gradient bit for bit: the same samples, summed into the gradient in the same order
        torch.manual_seed(0)
        batch = 3
        volume = torch.randn(batch, 5, *GRID.volume_shape).contiguous(memory_format=memory_format)
        volume[:, :, :, :2] = 0.0  # exact zeros inside the grid tie with the zeros outside it
        K, pose = make_K(batch, fx=4.0, fy=3.5, cx=4.5, cy=3.0).float(), poses(batch).float()
        a, b = volume.clone().requires_grad_(True), volume.clone().requires_grad_(True)
        ref = self.both(a, GRID, K, pose, (7, 9), depth_range, planes, pool)[0]
        out = self.both(b, GRID, K, pose, (7, 9), depth_range, planes, pool)[1]
        some = frustum_points(K, pose, (7, 9), depth_range, planes)
        index = voxel_index(some)
        upper = torch.tensor([n - 1 for n in GRID.resolution], dtype=some.dtype)
        inside = ((index >= -0.5) & (index <= upper + 0.5)).all(-1)
        assert 0 < inside.float().mean() < 1  # windows of both kinds
        assert torch.equal(ref, out)
        grad = torch.randn_like(ref)
        ref.backward(grad)
        out.backward(grad)
        assert torch.equal(a.grad, b.grad) and a.grad.abs().sum() > 0

    def test_views_outside_the_grid(self) -> None:
        # a camera looking away from the grid samples nothing: zeros, and a zero gradient, as the two steps give
        K = make_K(2).float()
        away = torch.stack([look_at((3.0, 0.0, 0.0), (6.0, 0.0, 0.0)), look_at((-2.5, 0.4, 0.9))]).float()
        for pose in (away, away[:1]):
            volume = torch.rand(pose.shape[0], 2, *GRID.volume_shape, requires_grad=True)
            ref, out = self.both(volume, GRID, K[: pose.shape[0]], pose, (3, 4), (1.0, 4.0), 8, 4)
            assert torch.equal(ref, out) and not out[0].any()
            (grad,) = torch.autograd.grad(out.sum(), volume)
            (grad_ref,) = torch.autograd.grad(ref.sum(), volume)
            assert torch.equal(grad, grad_ref) and not grad[0].any()

    def test_low_precision_volume(self) -> None:
        torch.manual_seed(0)
        volume = torch.rand(2, 4, *GRID.volume_shape).bfloat16()
        ref, out = self.both(volume, GRID, make_K(2).float(), poses(2).float(), (6, 8), (1.0, 4.0), 8, 4)
        assert out.dtype == torch.bfloat16 and torch.equal(ref, out)

    def test_gradcheck(self) -> None:
        assert gradcheck_small(lambda vol, grid, K, T: frustum_depth_max(vol, grid, K, T, (2, 3), (1.5, 3.5), 4, 2))
