"""Tests for threedq.geometry.crop."""

from __future__ import annotations

import math

import pytest
import torch
import torch.nn.functional as F

from threedq.geometry import VoxelGridSpec, box_mask, crop_boxes, occupancy_weighted, paste_boxes, sample_volume
from threedq.geometry.crop import _gather_crops, _sampled_crops

GRID = VoxelGridSpec((-1.0, -0.5, 0.0), (1.0, 0.5, 0.75), (8, 4, 3))  # 0.25 m voxels, volume (3, 4, 8)


def ramp(x: torch.Tensor, y: torch.Tensor, z: torch.Tensor) -> torch.Tensor:
    return 1.0 + 2.0 * x - 3.0 * y + 0.5 * z


def ramp_volume(grid: VoxelGridSpec) -> torch.Tensor:
    centres = grid.voxel_centres(dtype=torch.float64)
    return ramp(*centres.unbind(-1))[None, None]


def sample_points(box: torch.Tensor, size: tuple[int, int, int]) -> torch.Tensor:
    """[sz, sy, sx, 3] centres of the output cells of one box."""
    sz, sy, sx = size
    axes = [
        box[d] + (torch.arange(n, dtype=box.dtype) + 0.5) * (box[d + 3] - box[d]) / n
        for d, n in enumerate((sx, sy, sz))
    ]
    zz, yy, xx = torch.meshgrid(axes[2], axes[1], axes[0], indexing="ij")
    return torch.stack((xx, yy, zz), -1)


def trilinear_naive(volume: torch.Tensor, grid: VoxelGridSpec, point: torch.Tensor) -> torch.Tensor:
    """Trilinear interpolation [C] at one point, voxel values at centres, zero outside the grid."""
    idx = [(point[d].item() - grid.bounds_min[d]) / grid.voxel_size[d] - 0.5 for d in range(3)]  # (i, j, k)
    base = [math.floor(v) for v in idx]
    out = torch.zeros(volume.shape[0], dtype=volume.dtype)
    for di in (0, 1):
        for dj in (0, 1):
            for dk in (0, 1):
                i, j, k = base[0] + di, base[1] + dj, base[2] + dk
                if not (0 <= i < grid.resolution[0] and 0 <= j < grid.resolution[1] and 0 <= k < grid.resolution[2]):
                    continue
                w = 1.0
                for d, offset in enumerate((di, dj, dk)):
                    frac = idx[d] - base[d]
                    w *= frac if offset else 1.0 - frac
                out += w * volume[:, k, j, i]
    return out


def assert_matches_naive(out: torch.Tensor, volume: torch.Tensor, boxes: torch.Tensor, size: tuple[int, int, int]) -> None:
    """Every cell of ``[B, N, C, sz, sy, sx]`` crops against :func:`trilinear_naive` at its sample point."""
    for b in range(boxes.shape[0]):
        for n in range(boxes.shape[1]):
            points = sample_points(boxes[b, n], size)
            for idx in torch.cartesian_prod(*(torch.arange(s) for s in size)).tolist():
                expected = trilinear_naive(volume[b], GRID, points[tuple(idx)])
                torch.testing.assert_close(out[b, n, :, idx[0], idx[1], idx[2]], expected)


def random_boxes(batch: int, n: int, dtype: torch.dtype = torch.float64) -> torch.Tensor:
    lo = torch.tensor(GRID.bounds_min, dtype=dtype) - 0.2
    span = torch.tensor(GRID.bounds_max, dtype=dtype) - lo + 0.2
    a = lo + torch.rand(batch, n, 3, dtype=dtype) * span * 0.6
    b = a + (0.1 + torch.rand(batch, n, 3, dtype=dtype)) * span * 0.4
    return torch.cat((a, b), -1)


class TestCropBoxes:
    def test_smoke(self) -> None:
        out = crop_boxes(torch.rand(1, 2, 3, 4, 8), random_boxes(1, 3, torch.float32), GRID)
        assert out.shape == (1, 3, 2, 16, 16, 16) and out.dtype == torch.float32

    def test_exception(self) -> None:
        volume, boxes = torch.rand(2, 2, 3, 4, 8), random_boxes(2, 3, torch.float32)
        with pytest.raises(
            ValueError, match=r"volume must have shape \[B, C, Z, Y, X\] with \(Z, Y, X\) = \(3, 4, 8\)"
        ):
            crop_boxes(volume[..., :4], boxes, GRID)
        with pytest.raises(ValueError, match=r"boxes must have shape \[B, N, 6\]"):
            crop_boxes(volume, boxes[..., :4], GRID)
        with pytest.raises(ValueError, match=r"boxes must have shape \[B, N, 6\] with B=2"):
            crop_boxes(volume, boxes[:1], GRID)
        with pytest.raises(ValueError, match="size"):
            crop_boxes(volume, boxes, GRID, size=0)
        with pytest.raises(ValueError, match="size"):
            crop_boxes(volume, boxes, GRID, size=(4, 4))
        with pytest.raises(ValueError, match="grid must be a VoxelGridSpec"):
            crop_boxes(volume, boxes, None)  # type: ignore[arg-type]

    @pytest.mark.parametrize("batch", [1, 2])
    @pytest.mark.parametrize("n_boxes", [0, 1, 5])
    @pytest.mark.parametrize("size", [4, (2, 3, 5)])
    def test_cardinality(self, batch: int, n_boxes: int, size: int | tuple[int, int, int]) -> None:
        out = crop_boxes(torch.rand(batch, 3, 3, 4, 8), random_boxes(batch, n_boxes, torch.float32), GRID, size=size)
        sz, sy, sx = (size,) * 3 if isinstance(size, int) else size
        assert out.shape == (batch, n_boxes, 3, sz, sy, sx)

    def test_feature_full_box_round_trip(self) -> None:
        torch.manual_seed(0)
        volume = torch.rand(2, 3, *GRID.volume_shape, dtype=torch.float64)
        boxes = torch.tensor(GRID.bounds_min + GRID.bounds_max, dtype=torch.float64).expand(2, 1, 6)
        out = crop_boxes(volume, boxes, GRID, size=GRID.volume_shape)
        torch.testing.assert_close(out[:, 0], volume)

    def test_feature_aligned_box_is_a_slice(self) -> None:
        # voxels i in [2, 6), j in [1, 3), k in [0, 2) cropped at their own resolution
        torch.manual_seed(1)
        volume = torch.rand(1, 2, *GRID.volume_shape, dtype=torch.float64)
        boxes = torch.tensor([[[-0.5, -0.25, 0.0, 0.5, 0.25, 0.5]]], dtype=torch.float64)
        out = crop_boxes(volume, boxes, GRID, size=(2, 2, 4))
        torch.testing.assert_close(out[:, 0], volume[:, :, 0:2, 1:3, 2:6])

    def test_feature_ramp(self) -> None:
        # trilinear interpolation reproduces a linear function exactly inside the hull of voxel centres
        boxes = torch.tensor(
            [[[-0.8, -0.3, 0.13, 0.7, 0.35, 0.6], [-0.2, -0.1, 0.2, 0.1, 0.3, 0.4], [0.5, 0.3, 0.5, 0.6, -0.3, 0.2]]],
            dtype=torch.float64,
        )
        size = (3, 5, 7)
        out = crop_boxes(ramp_volume(GRID), boxes, GRID, size=size)
        for n in range(3):
            expected = ramp(*sample_points(boxes[0, n], size).unbind(-1))
            torch.testing.assert_close(out[0, n, 0], expected)

    def test_feature_matches_naive(self) -> None:
        torch.manual_seed(2)
        volume = torch.rand(2, 3, *GRID.volume_shape, dtype=torch.float64)
        boxes = random_boxes(2, 3)
        assert_matches_naive(crop_boxes(volume, boxes, GRID, size=(2, 3, 3)), volume, boxes, (2, 3, 3))

    def test_feature_outside_is_zero(self) -> None:
        boxes = torch.tensor([[[2.0, 2.0, 2.0, 3.0, 3.0, 3.0]]])
        assert (crop_boxes(torch.rand(1, 2, 3, 4, 8) + 1.0, boxes, GRID, size=4) == 0).all()

    def test_gradcheck(self) -> None:
        torch.manual_seed(4)
        volume = torch.rand(1, 2, *GRID.volume_shape, dtype=torch.float64, requires_grad=True)
        boxes = random_boxes(1, 2)
        assert torch.autograd.gradcheck(lambda v: crop_boxes(v, boxes, GRID, size=3), (volume,))


def gathered(volume: torch.Tensor, boxes: torch.Tensor, grid: VoxelGridSpec, size: tuple[int, int, int]) -> torch.Tensor:
    """``_gather_crops`` on ``[B, N, 6]`` boxes, shaped as ``crop_boxes``' ``[B, N, C, sz, sy, sx]``."""
    batch, n = boxes.shape[:2]
    out = _gather_crops(volume, boxes.reshape(-1, 6).to(volume.dtype), torch.arange(batch).repeat_interleave(n), grid, size)
    assert out is not None
    return out.view(batch, n, *out.shape[1:])


def sampled(volume: torch.Tensor, boxes: torch.Tensor, grid: VoxelGridSpec, size: tuple[int, int, int]) -> torch.Tensor:
    return _sampled_crops(volume, boxes.to(volume.dtype), grid, size)


class TestCropBoxesImplementations:
    """The two implementations behind ``crop_boxes`` (``grid_sample`` and the row gather): each against the naive
    loop, a linear ramp and slices; the gather against ``grid_sample`` bitwise."""

    @pytest.mark.parametrize("impl", [sampled, gathered])
    def test_feature_matches_naive(self, impl) -> None:
        torch.manual_seed(12)
        volume = torch.rand(2, 3, *GRID.volume_shape, dtype=torch.float64)
        boxes = random_boxes(2, 3)
        assert_matches_naive(impl(volume, boxes, GRID, (2, 3, 4)), volume, boxes, (2, 3, 4))

    @pytest.mark.parametrize("impl", [sampled, gathered])
    def test_feature_ramp_and_slice(self, impl) -> None:
        boxes = torch.tensor([[[-0.8, -0.3, 0.13, 0.7, 0.35, 0.6], [0.5, 0.3, 0.5, 0.6, -0.3, 0.2]]], dtype=torch.float64)
        out = impl(ramp_volume(GRID), boxes, GRID, (3, 5, 7))
        for n in range(2):
            torch.testing.assert_close(out[0, n, 0], ramp(*sample_points(boxes[0, n], (3, 5, 7)).unbind(-1)))
        volume = torch.rand(1, 2, *GRID.volume_shape, dtype=torch.float64)
        aligned = torch.tensor([[[-0.5, -0.25, 0.0, 0.5, 0.25, 0.5]]], dtype=torch.float64)
        torch.testing.assert_close(impl(volume, aligned, GRID, (2, 2, 4))[:, 0], volume[:, :, 0:2, 1:3, 2:6])

    @pytest.mark.parametrize("impl", [sampled, gathered])
    def test_feature_outside_is_zero(self, impl) -> None:
        boxes = torch.tensor([[[2.0, 2.0, 2.0, 3.0, 3.0, 3.0], [-9.0, -9.0, -9.0, -8.0, -8.0, -8.0]]])
        assert (impl(torch.rand(1, 2, *GRID.volume_shape) + 1.0, boxes, GRID, (4, 4, 4)) == 0).all()

    @pytest.mark.parametrize("dtype", [torch.float32, torch.bfloat16, torch.float64])
    @pytest.mark.parametrize("threads", [1, 2, 3])
    def test_feature_gather_is_bitwise_grid_sample(self, dtype: torch.dtype, threads: int) -> None:
        g = torch.Generator().manual_seed(threads)
        volume = torch.randn(3, 5, *GRID.volume_shape, generator=g).to(dtype)
        boxes = torch.cat([random_boxes(3, 4, torch.float32),  # partly outside, an inverted box, one far outside
                           torch.tensor([[[0.6, 0.4, 0.7, -0.6, -0.4, 0.1], [5.0, 5.0, 5.0, 9.0, 9.0, 9.0]]]).expand(3, 2, 6)], 1)
        was = torch.get_num_threads()
        torch.set_num_threads(threads)
        try:
            for size in ((16, 16, 16), (3, 5, 7)):
                ref = sampled(volume, boxes, GRID, size)
                assert torch.equal(gathered(volume, boxes, GRID, size), ref)
        finally:
            torch.set_num_threads(was)

    def test_feature_gather_under_autocast_is_grid_sample_under_autocast(self) -> None:
        volume = torch.randn(2, 4, *GRID.volume_shape).bfloat16()
        boxes = random_boxes(2, 3, torch.float32)
        with torch.autocast("cpu", dtype=torch.bfloat16):
            ref, out = sampled(volume, boxes, GRID, (6, 6, 6)), gathered(volume, boxes, GRID, (6, 6, 6))
        assert ref.dtype == out.dtype == torch.float32
        assert torch.equal(out, ref)

    def test_feature_gather_not_finite_defers(self) -> None:
        boxes = torch.tensor([[[float("nan"), 0.0, 0.0, 0.5, 0.2, 0.3]]])
        assert _gather_crops(torch.rand(1, 2, *GRID.volume_shape), boxes[0], torch.zeros(1, dtype=torch.long), GRID,
                             (2, 2, 2)) is None

    @pytest.mark.parametrize("channels", [4, 32])  # the grid_sample path and the gather
    def test_crop_boxes_is_grid_sample_and_mask_selects(self, channels: int) -> None:
        torch.manual_seed(13)
        volume = torch.randn(3, channels, *GRID.volume_shape)
        boxes = random_boxes(3, 3, torch.float32)
        ref = sampled(volume, boxes, GRID, (16, 16, 16))
        assert torch.equal(crop_boxes(volume, boxes, GRID), ref)
        mask = torch.tensor([[True, False, True], [False, False, False], [False, True, True]])
        out = crop_boxes(volume, boxes, GRID, mask=mask)
        assert out.shape == (4, channels, 16, 16, 16) and torch.equal(out, ref[mask])
        empty = crop_boxes(volume, boxes, GRID, 4, mask=torch.zeros(3, 3, dtype=torch.bool))
        assert empty.shape == (0, channels, 4, 4, 4)

    def test_crop_boxes_mask_exception(self) -> None:
        volume, boxes = torch.rand(2, 2, *GRID.volume_shape), random_boxes(2, 3, torch.float32)
        with pytest.raises(ValueError, match=r"mask must be a bool tensor of shape \[B, N\] = \(2, 3\)"):
            crop_boxes(volume, boxes, GRID, mask=torch.ones(2, 2, dtype=torch.bool))
        with pytest.raises(ValueError, match="mask must be a bool tensor"):
            crop_boxes(volume, boxes, GRID, mask=torch.ones(2, 3))

    def test_crop_boxes_with_grad_is_differentiable_with_many_channels(self) -> None:
        volume = torch.rand(1, 16, *GRID.volume_shape, dtype=torch.float64, requires_grad=True)
        boxes = random_boxes(1, 2)
        out = crop_boxes(volume, boxes, GRID, size=3)
        assert out.requires_grad
        assert torch.autograd.gradcheck(lambda v: crop_boxes(v, boxes, GRID, size=2), (volume,))


class TestPasteBoxes:
    def test_smoke(self) -> None:
        out = paste_boxes(torch.zeros(1, 2, *GRID.volume_shape), torch.ones(1, 1, 2, 3, 3, 3),
                          torch.tensor([[[-0.5, -0.25, 0.0, 0.5, 0.25, 0.5]]]), GRID)
        assert out.shape == (1, 2, *GRID.volume_shape)

    def test_exception(self) -> None:
        vol = torch.zeros(1, 2, *GRID.volume_shape)
        box = torch.tensor([[[-0.5, -0.25, 0.0, 0.5, 0.25, 0.5]]])
        with pytest.raises(ValueError, match=r"crops must have shape"):
            paste_boxes(vol, torch.ones(1, 1, 3, 2, 2, 2), box, GRID)
        with pytest.raises(ValueError, match=r"volume must have shape"):
            paste_boxes(torch.zeros(1, 2, 3, 3, 3), torch.ones(1, 1, 2, 2, 2, 2), box, GRID)
        with pytest.raises(ValueError, match=r"mask must have shape"):
            paste_boxes(vol, torch.ones(1, 1, 2, 2, 2, 2), box, GRID, mask=torch.ones(2, 1, dtype=torch.bool))

    def test_feature_aligned_round_trip(self) -> None:
        # crop a voxel-aligned box at its own resolution, paste it into another volume: the slice comes back exactly
        torch.manual_seed(5)
        volume = torch.rand(1, 2, *GRID.volume_shape, dtype=torch.float64)
        boxes = torch.tensor([[[-0.5, -0.25, 0.0, 0.5, 0.25, 0.5]]], dtype=torch.float64)
        crop = crop_boxes(volume, boxes, GRID, size=(2, 2, 4))
        base = torch.zeros_like(volume)
        out = paste_boxes(base, crop, boxes, GRID)
        torch.testing.assert_close(out[:, :, 0:2, 1:3, 2:6], volume[:, :, 0:2, 1:3, 2:6])
        inside = box_mask(boxes, GRID)[0, 0]
        assert (out[0][:, ~inside] == 0).all()

    def test_feature_ramp(self) -> None:
        # a crop holding a linear function of its fractional coordinates is reproduced at every voxel of the box
        size = (4, 5, 6)
        box = torch.tensor([-0.8, -0.3, 0.1, 0.7, 0.45, 0.6], dtype=torch.float64)
        fr = [(torch.arange(n, dtype=torch.float64) + 0.5) / n for n in size]  # fractions along z, y, x
        fz, fy, fx = torch.meshgrid(*fr, indexing="ij")
        crop = (1 + 2 * fx - 3 * fy + 0.5 * fz)[None, None, None]
        out = paste_boxes(torch.full((1, 1, *GRID.volume_shape), -7.0, dtype=torch.float64), crop, box.expand(1, 1, 6),
                          GRID)
        centres = GRID.voxel_centres(dtype=torch.float64)  # [Z, Y, X, 3]
        f = (centres - box[:3]) / (box[3:] - box[:3])
        # within the hull of the crop's cell centres the interpolation is exact; outside it clamps to the border
        lo = torch.tensor([0.5 / size[2], 0.5 / size[1], 0.5 / size[0]], dtype=torch.float64)
        fc = torch.maximum(torch.minimum(f, 1 - lo), lo)
        expected = 1 + 2 * fc[..., 0] - 3 * fc[..., 1] + 0.5 * fc[..., 2]
        inside = box_mask(box.expand(1, 1, 6), GRID)[0, 0]
        assert inside.sum() > 10
        torch.testing.assert_close(out[0, 0][inside], expected[inside])
        assert (out[0, 0][~inside] == -7).all()

    def test_feature_mask_and_order(self) -> None:
        vol = torch.zeros(1, 1, *GRID.volume_shape)
        boxes = torch.tensor([[[-1.0, -0.5, 0.0, 0.0, 0.5, 0.75], [-0.5, -0.5, 0.0, 0.5, 0.5, 0.75]]])
        crops = torch.stack([torch.full((1, 2, 2, 2), 1.0), torch.full((1, 2, 2, 2), 2.0)])[None]
        out = paste_boxes(vol, crops, boxes, GRID)
        both = box_mask(boxes, GRID)[0]
        assert (out[0, 0][both[1]] == 2).all() and (out[0, 0][both[0] & ~both[1]] == 1).all()
        out = paste_boxes(vol, crops, boxes, GRID, mask=torch.tensor([[True, False]]))
        assert (out[0, 0][both[0]] == 1).all() and (out[0, 0][~both[0]] == 0).all()

    def test_gradcheck(self) -> None:
        torch.manual_seed(6)
        vol = torch.rand(1, 1, *GRID.volume_shape, dtype=torch.float64, requires_grad=True)
        crop = torch.rand(1, 1, 1, 2, 3, 3, dtype=torch.float64, requires_grad=True)
        box = torch.tensor([[[-0.7, -0.4, 0.05, 0.6, 0.3, 0.6]]], dtype=torch.float64)
        assert torch.autograd.gradcheck(lambda v, c: paste_boxes(v, c, box, GRID), (vol, crop))


class TestBoxMask:
    def test_smoke(self) -> None:
        assert box_mask(random_boxes(1, 2), GRID).shape == (1, 2, 3, 4, 8)

    def test_exception(self) -> None:
        with pytest.raises(ValueError, match=r"boxes must have shape \[B, N, 6\]"):
            box_mask(torch.rand(2, 6), GRID)

    @pytest.mark.parametrize("batch", [1, 3])
    @pytest.mark.parametrize("n_boxes", [0, 4])
    def test_cardinality(self, batch: int, n_boxes: int) -> None:
        mask = box_mask(random_boxes(batch, n_boxes), GRID)
        assert mask.shape == (batch, n_boxes, 3, 4, 8) and mask.dtype == torch.bool

    def test_feature(self) -> None:
        # centres x in {-0.875, ..., 0.875}, y in {-0.375, ..., 0.375}, z in {0.125, 0.375, 0.625}
        boxes = torch.tensor([[[-0.5, -0.25, 0.0, 0.5, 0.25, 0.5], [0.6, -1.0, 0.3, 0.9, 0.0, 0.4]]])
        mask = box_mask(boxes, GRID)
        expected = torch.zeros(1, 2, 3, 4, 8, dtype=torch.bool)
        expected[0, 0, 0:2, 1:3, 2:6] = True
        expected[0, 1, 1, 0:2, 6:8] = True
        assert torch.equal(mask, expected)
        torch.manual_seed(3)
        boxes = random_boxes(2, 5)
        centres = GRID.voxel_centres(dtype=torch.float64)
        brute = ((centres >= boxes[:, :, None, None, None, :3]) & (centres <= boxes[:, :, None, None, None, 3:])).all(
            -1
        )
        assert torch.equal(box_mask(boxes, GRID), brute)


class TestOccupancyWeighted:
    def _naive(self, f: torch.Tensor, occ: torch.Tensor, floor: float, dilation: int) -> torch.Tensor:
        """Loop over voxels: weight = floor + max of the occupancy within +-dilation//2 (clipped at the border)."""
        out = torch.empty_like(f)
        r = dilation // 2
        N, _, Z, Y, X = f.shape
        for n in range(N):
            for z in range(Z):
                for y in range(Y):
                    for x in range(X):
                        nb = occ[n, 0, max(z - r, 0):z + r + 1, max(y - r, 0):y + r + 1, max(x - r, 0):x + r + 1]
                        out[n, :, z, y, x] = f[n, :, z, y, x] * (floor + nb.max())
        return out

    def test_smoke_and_shapes(self) -> None:
        f, occ = torch.randn(3, 5, 4, 4, 4), (torch.rand(3, 1, 4, 4, 4) > 0.7).float()
        out = occupancy_weighted(f, occ)
        assert out.shape == f.shape and out.dtype == f.dtype

    @pytest.mark.parametrize("dilation", [1, 3, 5])
    def test_against_naive_loop(self, dilation: int) -> None:
        g = torch.Generator().manual_seed(0)
        f = torch.randn(2, 3, 5, 4, 6, generator=g, dtype=torch.float64)
        occ = (torch.rand(2, 1, 5, 4, 6, generator=g, dtype=torch.float64) > 0.8).double()
        torch.testing.assert_close(occupancy_weighted(f, occ, 0.2, dilation), self._naive(f, occ, 0.2, dilation))

    def test_hand_computed(self) -> None:
        # one occupied voxel in the corner of a 3^3 crop: with dilation 3 the 2^3 voxels around it weigh 1 + floor
        f = torch.ones(1, 1, 3, 3, 3)
        occ = torch.zeros(1, 1, 3, 3, 3)
        occ[0, 0, 0, 0, 0] = 1.0
        out = occupancy_weighted(f, occ, floor=0.5, dilation=3)
        assert out[0, 0, :2, :2, :2].eq(1.5).all() and out[0, 0, 2].eq(0.5).all() and out.sum() == 8 * 1.5 + 19 * 0.5
        # floor 0, dilation 1: empty voxels vanish, so only the surface counts in a cosine
        assert occupancy_weighted(f, occ, floor=0.0, dilation=1).sum() == 1.0

    def test_yaw_invariant_weight_commutes_with_rotation(self) -> None:
        # the weight of a rotated crop is the rotated weight (90-degree turns are exact on the grid)
        g = torch.Generator().manual_seed(1)
        f, occ = torch.randn(2, 4, 4, 6, 6, generator=g), (torch.rand(2, 1, 4, 6, 6, generator=g) > 0.6).float()
        rot = lambda t: torch.rot90(t, 1, dims=(3, 4))  # noqa: E731 - a quarter turn about z
        torch.testing.assert_close(occupancy_weighted(rot(f), rot(occ)), rot(occupancy_weighted(f, occ)))

    @pytest.mark.parametrize(
        "f_shape, occ_shape, kwargs",
        [((2, 3, 4, 4, 4), (2, 3, 4, 4, 4), {}), ((2, 3, 4, 4, 4), (1, 1, 4, 4, 4), {}),
         ((2, 3, 4, 4), (2, 1, 4, 4), {}), ((2, 3, 4, 4, 4), (2, 1, 4, 4, 4), {"dilation": 2}),
         ((2, 3, 4, 4, 4), (2, 1, 4, 4, 4), {"floor": -0.1})],
    )
    def test_exception(self, f_shape: tuple, occ_shape: tuple, kwargs: dict) -> None:
        with pytest.raises(ValueError):
            occupancy_weighted(torch.zeros(f_shape), torch.zeros(occ_shape), **kwargs)

    def test_gradcheck(self) -> None:
        f = torch.randn(1, 2, 3, 3, 3, dtype=torch.float64, requires_grad=True)
        occ = (torch.rand(1, 1, 3, 3, 3, dtype=torch.float64) > 0.5).double()
        assert torch.autograd.gradcheck(lambda t: occupancy_weighted(t, occ), (f,))


class TestSampleVolume:
    """``sample_volume`` against one ``F.grid_sample`` call: bitwise, at any thread count and batch size."""

    @staticmethod
    def reference(volume: torch.Tensor, coords: torch.Tensor) -> torch.Tensor:
        return F.grid_sample(volume, coords, mode="bilinear", padding_mode="zeros", align_corners=False)

    @staticmethod
    def data(batch: int, dtype: torch.dtype = torch.float32) -> tuple[torch.Tensor, torch.Tensor]:
        g = torch.Generator().manual_seed(batch)
        volume = torch.randn(batch, 3, 5, 6, 7, generator=g).to(dtype)
        coords = (torch.rand(batch, 7, 3, 5, 3, generator=g) * 2.4 - 1.2).to(dtype)  # some outside: zero padding
        return volume, coords

    def test_smoke(self) -> None:
        volume, coords = self.data(1)
        assert sample_volume(volume, coords).shape == (1, 3, 7, 3, 5)

    def test_exception(self) -> None:
        with pytest.raises(RuntimeError):
            sample_volume(torch.zeros(2, 1, 2, 2, 2), torch.zeros(3, 1, 1, 1, 3))  # batch sizes differ

    @pytest.mark.parametrize("threads", [1, 2, 3, 4])
    @pytest.mark.parametrize("batch", [1, 2, 3])
    @pytest.mark.parametrize("dtype", [torch.float32, torch.float64, torch.bfloat16])
    def test_feature_bitwise_grid_sample(self, threads: int, batch: int, dtype: torch.dtype) -> None:
        volume, coords = self.data(batch, dtype)  # 105 points: not a multiple of any chunk count above 1
        was = torch.get_num_threads()
        torch.set_num_threads(threads)
        try:
            out = sample_volume(volume, coords)
        finally:
            torch.set_num_threads(was)
        assert out.dtype == dtype
        assert torch.equal(out, self.reference(volume, coords))

    def test_feature_crop_boxes_same_on_one_and_many_threads(self) -> None:
        volume = torch.randn(1, 4, *GRID.volume_shape)
        boxes = random_boxes(1, 5, torch.float32)
        was = torch.get_num_threads()
        try:
            torch.set_num_threads(1)
            one = crop_boxes(volume, boxes, GRID, 8)
            torch.set_num_threads(4)
            many = crop_boxes(volume, boxes, GRID, 8)
        finally:
            torch.set_num_threads(was)
        assert torch.equal(one, many)

    def test_gradcheck(self) -> None:
        volume, coords = self.data(1, torch.float64)
        volume.requires_grad_(True)
        assert torch.autograd.gradcheck(lambda v: sample_volume(v, coords), (volume,))
