"""Tests for threedq.geometry.camera."""

from __future__ import annotations

import math

import pytest
import torch

from threedq.geometry import depth_to_points, invert_rigid, project, transform_points, unproject_depth, yaw_matrix


def random_rigid(batch: int, dtype: torch.dtype = torch.float64) -> torch.Tensor:
    """Random proper rigid transforms [B, 4, 4]."""
    q, r = torch.linalg.qr(torch.randn(batch, 3, 3, dtype=torch.float64))
    q = q * torch.sign(torch.diagonal(r, dim1=-2, dim2=-1))[:, None, :]
    q[:, :, 0] *= torch.sign(torch.linalg.det(q))[:, None]
    pose = torch.eye(4, dtype=torch.float64).repeat(batch, 1, 1)
    pose[:, :3, :3] = q
    pose[:, :3, 3] = torch.randn(batch, 3, dtype=torch.float64)
    return pose.to(dtype)


def make_K(batch: int, dtype: torch.dtype = torch.float64, skew: float = 0.0) -> torch.Tensor:
    K = torch.tensor([[50.0, skew, 31.5], [0.0, 45.0, 23.5], [0.0, 0.0, 1.0]], dtype=dtype)
    return K.repeat(batch, 1, 1)


class TestTransformPoints:
    def test_smoke(self) -> None:
        out = transform_points(torch.eye(4)[None], torch.rand(1, 5, 3))
        assert out.shape == (1, 5, 3)

    def test_exception(self) -> None:
        with pytest.raises(ValueError, match=r"points must have shape \[B, N, 3\]"):
            transform_points(torch.eye(4)[None], torch.rand(1, 5, 2))
        with pytest.raises(ValueError, match=r"a_T_b must have shape \[B, 4, 4\] with B=2"):
            transform_points(torch.eye(4)[None], torch.rand(2, 5, 3))
        with pytest.raises(ValueError, match="a_T_b"):
            transform_points(torch.eye(4), torch.rand(1, 5, 3))

    @pytest.mark.parametrize("batch", [1, 3])
    def test_cardinality(self, batch: int) -> None:
        assert transform_points(random_rigid(batch), torch.rand(batch, 7, 3, dtype=torch.float64)).shape == (
            batch,
            7,
            3,
        )

    def test_feature(self) -> None:
        # 90 deg about +z then translate by (1, 2, 3): (1, 0, 0) -> (0, 1, 0) + t, (0, 1, 0) -> (-1, 0, 0) + t
        a_T_b = torch.tensor([[[0.0, -1.0, 0.0, 1.0], [1.0, 0.0, 0.0, 2.0], [0.0, 0.0, 1.0, 3.0], [0, 0, 0, 1]]])
        points = torch.tensor([[[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 2.0]]])
        expected = torch.tensor([[[1.0, 3.0, 3.0], [0.0, 2.0, 3.0], [1.0, 2.0, 5.0]]])
        torch.testing.assert_close(transform_points(a_T_b, points), expected)

    @pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
    def test_feature_matches_naive(self, dtype: torch.dtype) -> None:
        # kornia-backed op against the per-point formula (x, y, z, w) = T (p, 1), divided by w unless |w| <= 1e-8
        torch.manual_seed(7)
        projective = random_rigid(2)
        projective[:, 3] = torch.tensor([[0.1, -0.2, 0.05, 1.0], [0.0, 0.0, 0.0, 1.0]], dtype=torch.float64)
        projective[1, 3, 3] = 0.0  # w = 0 for every point: left undivided
        transforms = torch.cat((random_rigid(2), projective)).to(dtype)
        points = torch.randn(4, 6, 3, dtype=dtype)
        out = transform_points(transforms, points)
        assert out.dtype == dtype
        expected = torch.zeros(4, 6, 3, dtype=torch.float64)
        for b in range(4):
            for n in range(6):
                x, y, z, w = (transforms[b].double() @ torch.cat((points[b, n].double(), torch.ones(1)))).tolist()
                scale = 1.0 / w if abs(w) > 1e-8 else 1.0
                expected[b, n] = torch.tensor([x * scale, y * scale, z * scale])
        torch.testing.assert_close(out, expected.to(dtype))

    def test_gradcheck(self) -> None:
        pose = random_rigid(2).requires_grad_()
        points = torch.rand(2, 4, 3, dtype=torch.float64, requires_grad=True)
        assert torch.autograd.gradcheck(transform_points, (pose, points))


class TestInvertRigid:
    def test_smoke(self) -> None:
        torch.testing.assert_close(invert_rigid(torch.eye(4)), torch.eye(4))

    def test_exception(self) -> None:
        with pytest.raises(ValueError, match=r"a_T_b must have shape \[\.\.\., 4, 4\]"):
            invert_rigid(torch.eye(3))

    @pytest.mark.parametrize("shape", [(), (1,), (2, 3)])
    def test_cardinality(self, shape: tuple[int, ...]) -> None:
        pose = random_rigid(math.prod(shape)).reshape(*shape, 4, 4)
        assert invert_rigid(pose).shape == (*shape, 4, 4)

    @pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
    def test_feature(self, dtype: torch.dtype) -> None:
        torch.manual_seed(0)
        pose = random_rigid(5, dtype)
        torch.testing.assert_close(invert_rigid(pose), torch.linalg.inv(pose))
        torch.testing.assert_close(invert_rigid(pose) @ pose, torch.eye(4, dtype=dtype).expand(5, 4, 4))

    @pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
    @pytest.mark.parametrize("shape", [(), (0,), (5,), (2, 3)])
    def test_feature_matches_local_formula(self, dtype: torch.dtype, shape: tuple[int, ...]) -> None:
        # kornia's inverse_transformation against the previous local formula [[R^T, -R^T t], [0, 0, 0, 1]], per matrix
        torch.manual_seed(9)
        pose = random_rigid(max(math.prod(shape), 1), dtype)[: math.prod(shape)].reshape(*shape, 4, 4)
        out = invert_rigid(pose)
        assert out.shape == pose.shape and out.dtype == dtype and out.device == pose.device
        flat, expected = pose.reshape(-1, 4, 4), torch.zeros(math.prod(shape), 4, 4, dtype=dtype)
        for i, matrix in enumerate(flat):
            rot_t = matrix[:3, :3].T
            expected[i, :3, :3] = rot_t
            expected[i, :3, 3] = -(rot_t @ matrix[:3, 3])
            expected[i, 3, 3] = 1.0
        torch.testing.assert_close(out, expected.reshape(*shape, 4, 4))

    def test_gradcheck(self) -> None:
        assert torch.autograd.gradcheck(invert_rigid, (random_rigid(2).requires_grad_(),))
        pose = random_rigid(6).reshape(2, 3, 4, 4).requires_grad_()
        assert torch.autograd.gradcheck(invert_rigid, (pose,))


class TestProject:
    def test_smoke(self) -> None:
        uv, z = project(torch.tensor([[[0.0, 0.0, 2.0]]]), make_K(1, torch.float32))
        torch.testing.assert_close(uv, torch.tensor([[[31.5, 23.5]]]))
        torch.testing.assert_close(z, torch.tensor([[2.0]]))

    def test_exception(self) -> None:
        with pytest.raises(ValueError, match=r"points_cam must have shape \[B, N, 3\]"):
            project(torch.rand(1, 4), make_K(1))
        with pytest.raises(ValueError, match=r"K must have shape \[B, 3, 3\] with B=2"):
            project(torch.rand(2, 4, 3), make_K(1))

    @pytest.mark.parametrize("batch", [1, 2, 4])
    def test_cardinality(self, batch: int) -> None:
        uv, z = project(torch.rand(batch, 6, 3, dtype=torch.float64), make_K(batch))
        assert uv.shape == (batch, 6, 2) and z.shape == (batch, 6)

    def test_feature(self) -> None:
        # u = (fx x + s y) / z + cx, v = fy y / z + cy
        points = torch.tensor([[[1.0, -2.0, 4.0]]], dtype=torch.float64)
        uv, _ = project(points, make_K(1, skew=2.0))
        torch.testing.assert_close(
            uv, torch.tensor([[[(50.0 - 4.0) / 4.0 + 31.5, -90.0 / 4.0 + 23.5]]], dtype=torch.float64)
        )

    def test_feature_zero_depth_is_finite(self) -> None:
        uv, z = project(torch.tensor([[[1.0, 1.0, 0.0], [1.0, 1.0, -1e-12]]]), make_K(1, torch.float32))
        assert torch.isfinite(uv).all()

    @pytest.mark.parametrize("skew", [0.0, 1.5])
    def test_feature_round_trip(self, skew: float) -> None:
        torch.manual_seed(1)
        K = make_K(2, skew=skew)
        # pixels + depth -> points -> pixels + depth
        depth = torch.rand(2, 5, 6, dtype=torch.float64) + 1.0
        points = unproject_depth(depth, K).flatten(1, 2)
        uv, z = project(points, K)
        vv, uu = torch.meshgrid(torch.arange(5.0), torch.arange(6.0), indexing="ij")
        pixels = torch.stack((uu, vv), -1).reshape(1, -1, 2).double().expand(2, -1, -1)
        torch.testing.assert_close(uv, pixels)
        torch.testing.assert_close(z, depth.flatten(1))
        # points -> pixels + depth -> points (K^-1 [u, v, 1] * z)
        points = torch.randn(2, 40, 3, dtype=torch.float64)
        points[..., 2] = points[..., 2].abs() + 0.5
        uv, z = project(points, K)
        homog = torch.cat((uv, torch.ones_like(z)[..., None]), -1)
        rays = torch.linalg.solve(K[:, None], homog[..., None])[..., 0]
        torch.testing.assert_close(rays * z[..., None], points)

    def test_gradcheck(self) -> None:
        points = torch.rand(1, 4, 3, dtype=torch.float64) + torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64)
        assert torch.autograd.gradcheck(project, (points.requires_grad_(), make_K(1).requires_grad_()))


class TestUnprojectDepth:
    def test_smoke(self) -> None:
        assert unproject_depth(torch.ones(1, 3, 4), make_K(1, torch.float32)).shape == (1, 3, 4, 3)

    def test_exception(self) -> None:
        with pytest.raises(ValueError, match=r"depth must have shape \[B, H, W\]"):
            unproject_depth(torch.ones(3, 4), make_K(1))
        with pytest.raises(ValueError, match=r"K must have shape \[B, 3, 3\] with B=2"):
            unproject_depth(torch.ones(2, 3, 4), make_K(1))

    @pytest.mark.parametrize("batch", [1, 3])
    def test_cardinality(self, batch: int) -> None:
        assert unproject_depth(torch.ones(batch, 2, 5, dtype=torch.float64), make_K(batch)).shape == (batch, 2, 5, 3)

    def test_feature(self) -> None:
        # K = identity with principal point (1, 0): pixel (v, u) at depth d -> ((u - 1) d, v d, d)
        K = torch.tensor([[[1.0, 0.0, 1.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]]])
        depth = torch.tensor([[[2.0, 2.0, 2.0], [3.0, 3.0, 3.0]]])
        expected = torch.tensor(
            [
                [
                    [[-2.0, 0.0, 2.0], [0.0, 0.0, 2.0], [2.0, 0.0, 2.0]],
                    [[-3.0, 3.0, 3.0], [0.0, 3.0, 3.0], [3.0, 3.0, 3.0]],
                ]
            ]
        )
        torch.testing.assert_close(unproject_depth(depth, K), expected)

    def test_gradcheck(self) -> None:
        depth = torch.rand(1, 2, 3, dtype=torch.float64, requires_grad=True)
        assert torch.autograd.gradcheck(unproject_depth, (depth, make_K(1).requires_grad_()))


class TestDepthToPoints:
    def test_smoke(self) -> None:
        points, valid = depth_to_points(torch.ones(1, 2, 3), make_K(1, torch.float32), torch.eye(4)[None])
        assert points.shape == (1, 6, 3) and valid.all()

    def test_exception(self) -> None:
        with pytest.raises(ValueError, match=r"R_T_cam must have shape \[B, 4, 4\]"):
            depth_to_points(torch.ones(1, 2, 3), make_K(1), torch.eye(4))

    @pytest.mark.parametrize("batch", [1, 2])
    def test_cardinality(self, batch: int) -> None:
        points, valid = depth_to_points(
            torch.ones(batch, 4, 5, dtype=torch.float64), make_K(batch), random_rigid(batch)
        )
        assert points.shape == (batch, 20, 3) and valid.shape == (batch, 20) and valid.dtype == torch.bool

    def test_feature(self) -> None:
        torch.manual_seed(2)
        depth = torch.rand(2, 4, 5, dtype=torch.float64) + 0.5
        depth[0, 1, 2] = 0.0
        depth[1, 3, 4] = float("nan")
        depth[1, 0, 0] = float("inf")
        depth[1, 2, 2] = -1.0
        pose, K = random_rigid(2), make_K(2)
        points, valid = depth_to_points(depth, K, pose)
        assert valid.sum() == 40 - 4
        assert not valid[0, 1 * 5 + 2] and not valid[1, 3 * 5 + 4] and not valid[1, 0] and not valid[1, 12]
        assert torch.isfinite(points).all()
        expected = transform_points(pose, unproject_depth(torch.nan_to_num(depth, 0.0, 0.0, 0.0), K).flatten(1, 2))
        torch.testing.assert_close(points[valid], expected[valid])
        # points go back to their pixels
        uv, z = project(transform_points(invert_rigid(pose), points), K)
        torch.testing.assert_close(z[valid], depth.flatten(1)[valid])


class TestYawMatrix:
    def test_smoke(self) -> None:
        torch.testing.assert_close(yaw_matrix(torch.tensor(0.0)), torch.eye(3))

    def test_exception(self) -> None:
        with pytest.raises(ValueError, match="yaw must be a tensor"):
            yaw_matrix(0.5)  # type: ignore[arg-type]

    @pytest.mark.parametrize("shape", [(), (4,), (2, 3)])
    def test_cardinality(self, shape: tuple[int, ...]) -> None:
        assert yaw_matrix(torch.rand(shape)).shape == (*shape, 3, 3)

    def test_feature(self) -> None:
        # +x goes to +y (counter-clockwise seen from above), z unchanged
        rot = yaw_matrix(torch.tensor(math.pi / 2, dtype=torch.float64))
        torch.testing.assert_close(
            rot @ torch.tensor([1.0, 0.0, 0.0], dtype=torch.float64), torch.tensor([0.0, 1.0, 0.0], dtype=torch.float64)
        )
        torch.testing.assert_close(
            rot @ torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64), torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64)
        )
        t = torch.tensor([0.3, -1.2], dtype=torch.float64)
        x, y = 2.0, -0.5
        out = yaw_matrix(t) @ torch.tensor([x, y, 1.0], dtype=torch.float64)
        expected = torch.stack((x * t.cos() - y * t.sin(), x * t.sin() + y * t.cos(), torch.ones_like(t)), -1)
        torch.testing.assert_close(out, expected)
        assert torch.allclose(torch.linalg.det(yaw_matrix(t)), torch.ones(2, dtype=torch.float64))

    @pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
    def test_feature_matches_local_formula(self, dtype: torch.dtype) -> None:
        # kornia's axis_angle_to_rotation_matrix about +z against the previous local formula, values and gradients,
        # on both of its branches (Rodrigues, and the Taylor series for |t| < 1e-3)
        angles = [0.0, 1e-7, -2e-4, 9e-4, 1.1e-3, 0.3, -1.2, math.pi / 2, -math.pi, 3.0, 7.5, -40.0]
        yaw = torch.tensor(angles, dtype=dtype).reshape(3, 4).requires_grad_()
        out = yaw_matrix(yaw)

        def local(t: torch.Tensor) -> torch.Tensor:
            c, s, zero, one = torch.cos(t), torch.sin(t), torch.zeros_like(t), torch.ones_like(t)
            rows = (torch.stack((c, -s, zero), -1), torch.stack((s, c, zero), -1), torch.stack((zero, zero, one), -1))
            return torch.stack(rows, dim=-2)

        expected = local(yaw)
        assert out.dtype == dtype and out.shape == (3, 4, 3, 3)
        torch.testing.assert_close(out, expected)
        weights = torch.randn(3, 4, 3, 3, dtype=dtype)
        (grad,) = torch.autograd.grad((out * weights).sum(), yaw)
        (expected_grad,) = torch.autograd.grad((expected * weights).sum(), yaw)
        torch.testing.assert_close(grad, expected_grad)
        torch.testing.assert_close(yaw_matrix(torch.tensor([0, 2])), local(torch.tensor([0.0, 2.0])))  # int angles

    def test_gradcheck(self) -> None:
        assert torch.autograd.gradcheck(yaw_matrix, (torch.rand(3, dtype=torch.float64, requires_grad=True),))
        small = torch.tensor([0.0, 3e-4, -5e-4], dtype=torch.float64, requires_grad=True)  # Taylor branch
        assert torch.autograd.gradcheck(yaw_matrix, (small,))
