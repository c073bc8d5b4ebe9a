"""Tests for threedq.geometry.rotate."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
import torch.nn.functional as F
from scipy import ndimage

from threedq.geometry import rotate_yaw, yaw_angles


def rotate_yaw_scipy(volume: torch.Tensor, yaw: float) -> torch.Tensor:
    """Reference: scipy.ndimage.affine_transform per z-slice (order 1, zero padding beyond the grid)."""
    _, _, _, ny, nx = volume.shape
    c, s = math.cos(yaw), math.sin(yaw)
    # output (y, x) index samples input at centre + R(-yaw) (p - centre); R(-yaw) in (y, x) order:
    matrix = np.array([[c, -s], [s, c]])
    centre = np.array([(ny - 1) / 2, (nx - 1) / 2])
    offset = centre - matrix @ centre
    out = np.zeros(volume.shape)
    arr = volume.numpy()
    for idx in np.ndindex(*volume.shape[:3]):
        out[idx] = ndimage.affine_transform(arr[idx], matrix, offset, order=1, mode="grid-constant", cval=0.0)
    return torch.from_numpy(out).to(volume.dtype)


def smooth_volume(channels: int, size: int, radius: float, dtype: torch.dtype = torch.float64) -> torch.Tensor:
    """Random smooth content (blurred noise) inside a vertical cylinder of ``radius`` voxels, zero outside."""
    noise = torch.randn(1, channels, size, size, size, dtype=dtype)
    for _ in range(2):
        noise = F.avg_pool3d(noise, 3, stride=1, padding=1)
    centre = (size - 1) / 2
    yy, xx = torch.meshgrid(torch.arange(size, dtype=dtype), torch.arange(size, dtype=dtype), indexing="ij")
    inside = ((xx - centre) ** 2 + (yy - centre) ** 2) <= radius**2
    return noise * inside


def gaussian_blobs(size: int, dtype: torch.dtype = torch.float64) -> torch.Tensor:
    """[1, 2, size, size, size] smooth volume (wide Gaussians well inside the grid)."""
    coords = torch.arange(size, dtype=dtype) - (size - 1) / 2
    zz, yy, xx = torch.meshgrid(coords, coords, coords, indexing="ij")
    a = torch.exp(-((xx - 2.0) ** 2 + (yy + 1.0) ** 2 + zz**2) / (2 * 2.5**2))
    b = torch.exp(-((xx + 1.5) ** 2 + (yy - 2.5) ** 2 + (zz - 1.0) ** 2) / (2 * 3.0**2))
    return torch.stack((a, b))[None]


class TestRotateYaw:
    def test_smoke(self) -> None:
        out = rotate_yaw(torch.rand(2, 3, 4, 6, 6), torch.rand(2))
        assert out.shape == (2, 3, 4, 6, 6) and out.dtype == torch.float32

    def test_exception(self) -> None:
        volume = torch.rand(2, 3, 4, 6, 6)
        with pytest.raises(ValueError, match=r"volume must have shape \[N, C, Z, Y, X\]"):
            rotate_yaw(volume[0], torch.rand(2))
        with pytest.raises(ValueError, match="floating-point"):
            rotate_yaw(volume.long(), torch.rand(2))
        with pytest.raises(ValueError, match=r"yaw must have shape \[N\] or \[N, A\] with N=2"):
            rotate_yaw(volume, torch.rand(3))
        with pytest.raises(ValueError, match=r"yaw must have shape \[N\] or \[N, A\]"):
            rotate_yaw(volume, torch.rand(2, 3, 1))
        with pytest.raises(ValueError, match="yaw"):
            rotate_yaw(volume, 0.5)  # type: ignore[arg-type]

    @pytest.mark.parametrize("n", [1, 3])
    @pytest.mark.parametrize("n_angles", [None, 1, 4])
    def test_cardinality(self, n: int, n_angles: int | None) -> None:
        volume = torch.rand(n, 2, 3, 5, 7)
        yaw = torch.rand(n) if n_angles is None else torch.rand(n, n_angles)
        expected = (n, 2, 3, 5, 7) if n_angles is None else (n, n_angles, 2, 3, 5, 7)
        assert rotate_yaw(volume, yaw).shape == expected

    def test_feature_zero_is_identity(self) -> None:
        volume = torch.rand(2, 3, 4, 6, 5, dtype=torch.float64)
        torch.testing.assert_close(rotate_yaw(volume, torch.zeros(2, dtype=torch.float64)), volume)

    @pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
    def test_feature_four_quarter_turns(self, dtype: torch.dtype) -> None:
        torch.manual_seed(0)
        volume = torch.zeros(2, 3, 4, 10, 10, dtype=dtype)
        volume[..., 1:-1, 1:-1] = torch.rand(2, 3, 4, 8, 8, dtype=dtype)
        quarter = torch.full((2,), math.pi / 2, dtype=dtype)
        out = volume
        for _ in range(4):
            out = rotate_yaw(out, quarter)
        torch.testing.assert_close(out, volume)
        # one quarter turn is the exact index permutation: out[y, x] = in[x, n - 1 - y] (square grid)
        torch.testing.assert_close(rotate_yaw(volume, quarter), torch.rot90(volume, k=1, dims=(-1, -2)))

    @pytest.mark.parametrize(
        ("shape", "source", "target"),
        [
            # square 8 x 8, centre (3.5, 3.5): (x, y) = (6, 3) is offset (+2.5, -0.5) -> (+0.5, +2.5) = (4, 6)
            ((8, 8), (6, 3), (4, 6)),
            # odd square 9 x 9, centre (4, 4): content on +x moves to +y, (3, 0) -> (0, 3)
            ((9, 9), (7, 4), (4, 7)),
            # non-square 8 (x) x 6 (y), centre (3.5, 2.5): (5, 2) offset (1.5, -0.5) -> (0.5, 1.5) = (4, 4)
            ((6, 8), (5, 2), (4, 4)),
        ],
    )
    def test_feature_quarter_turn_moves_blob(
        self, shape: tuple[int, int], source: tuple[int, int], target: tuple[int, int]
    ) -> None:
        ny, nx = shape
        volume = torch.zeros(1, 1, 2, ny, nx, dtype=torch.float64)
        volume[..., source[1], source[0]] = 1.0
        out = rotate_yaw(volume, torch.tensor([math.pi / 2], dtype=torch.float64))
        expected = torch.zeros_like(volume)
        expected[..., target[1], target[0]] = 1.0
        torch.testing.assert_close(out, expected)

    def test_feature_matches_scipy(self) -> None:
        torch.manual_seed(1)
        volume = torch.rand(2, 2, 3, 7, 9, dtype=torch.float64)
        yaw = torch.tensor([[0.3, -2.0, 4.0], [1.1, 0.0, math.pi / 3]], dtype=torch.float64)
        for vol in (volume, volume[..., :7]):  # non-square (angles in voxel units) and square
            out = rotate_yaw(vol, yaw)
            for n in range(2):
                for a in range(3):
                    torch.testing.assert_close(out[n, a], rotate_yaw_scipy(vol[n : n + 1], yaw[n, a].item())[0])

    def test_feature_batched_angles_match_single(self) -> None:
        torch.manual_seed(2)
        volume = torch.rand(3, 2, 2, 6, 6)
        yaw = torch.rand(3, 4) * 6.0
        batched = rotate_yaw(volume, yaw)
        for a in range(4):
            torch.testing.assert_close(batched[:, a], rotate_yaw(volume, yaw[:, a]))

    def test_feature_angle_recovery(self) -> None:
        torch.manual_seed(3)
        volume = smooth_volume(channels=4, size=16, radius=7.0)
        true_step = int(torch.randint(1, 36, ()).item())
        rotated = rotate_yaw(volume, yaw_angles(36, dtype=torch.float64)[true_step : true_step + 1])
        # rotate back by every candidate and pick the best cosine
        candidates = rotate_yaw(rotated, -yaw_angles(36, dtype=torch.float64)[None])[0]  # [36, C, Z, Y, X]
        cosine = F.cosine_similarity(candidates.flatten(1), volume.flatten(1), dim=1)
        assert int(cosine.argmax()) == true_step
        assert cosine.max() > 0.9

    def test_feature_there_and_back(self) -> None:
        volume = gaussian_blobs(20)
        t = torch.tensor([0.7], dtype=torch.float64)
        back = rotate_yaw(rotate_yaw(volume, t), -t)
        # two bilinear resamplings smooth the peaks a little (~5% at a sigma = 2.5 voxel peak)
        assert (back - volume).abs().max() < 0.08
        assert (back - volume).norm() / volume.norm() < 0.05
        # a half turn maps the centre of mass to its mirror image through the volume centre (no half-voxel drift)
        rotated = rotate_yaw(volume, torch.tensor([math.pi], dtype=torch.float64))
        coords = torch.arange(20, dtype=torch.float64) - 9.5
        com_x = (rotated.sum(dim=(2, 3)) * coords).sum(-1) / rotated.sum(dim=(2, 3, 4))
        com_x_in = (volume.sum(dim=(2, 3)) * coords).sum(-1) / volume.sum(dim=(2, 3, 4))
        torch.testing.assert_close(com_x, -com_x_in)

    def test_gradcheck(self) -> None:
        torch.manual_seed(4)
        volume = torch.rand(2, 1, 2, 4, 4, dtype=torch.float64, requires_grad=True)
        yaw = (torch.rand(2, 2, dtype=torch.float64) * 6.0).requires_grad_()
        assert torch.autograd.gradcheck(rotate_yaw, (volume, yaw))


class TestYawAngles:
    def test_smoke(self) -> None:
        angles = yaw_angles()
        assert angles.shape == (36,) and angles.dtype == torch.get_default_dtype()

    def test_exception(self) -> None:
        with pytest.raises(ValueError, match="n must be a positive int"):
            yaw_angles(0)
        with pytest.raises(ValueError, match="n must be a positive int"):
            yaw_angles(4.0)  # type: ignore[arg-type]

    @pytest.mark.parametrize("n", [1, 4, 36])
    def test_cardinality(self, n: int) -> None:
        assert yaw_angles(n, dtype=torch.float64).shape == (n,)

    def test_feature(self) -> None:
        torch.testing.assert_close(
            yaw_angles(4, dtype=torch.float64),
            torch.tensor([0.0, math.pi / 2, math.pi, 3 * math.pi / 2], dtype=torch.float64),
        )
        torch.testing.assert_close(
            torch.rad2deg(yaw_angles(36, dtype=torch.float64))[1:3], torch.tensor([10.0, 20.0], dtype=torch.float64)
        )
