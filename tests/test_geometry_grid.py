"""Tests for threedq.geometry.grid (VoxelGridSpec)."""

from __future__ import annotations

import dataclasses
import json

import pytest
import torch
import torch.nn.functional as F

from threedq.geometry import VoxelGridSpec


def make_grid() -> VoxelGridSpec:
    return VoxelGridSpec((-1.0, -2.0, 0.0), (1.0, 2.0, 1.5), (4, 8, 3))


class TestVoxelGridSpec:
    def test_smoke(self) -> None:
        grid = make_grid()
        assert grid.voxel_size == (0.5, 0.5, 0.5)
        assert grid.volume_shape == (3, 8, 4)
        assert grid.centre == (0.0, 0.0, 0.75)
        assert hash(grid) == hash(make_grid())

    def test_normalises_inputs(self) -> None:
        grid = VoxelGridSpec([-1, -1, -1], [1, 1, 1], [2, 2, 2])
        assert grid.bounds_min == (-1.0, -1.0, -1.0) and isinstance(grid.bounds_min, tuple)
        assert all(isinstance(v, float) for v in grid.bounds_max)
        assert grid.resolution == (2, 2, 2) and isinstance(grid.resolution, tuple)

    def test_frozen(self) -> None:
        with pytest.raises(dataclasses.FrozenInstanceError):
            make_grid().resolution = (1, 1, 1)  # type: ignore[misc]

    @pytest.mark.parametrize(
        ("kwargs", "field"),
        [
            ({"bounds_max": (1.0, 2.0, 0.0)}, "bounds_max"),  # zmax == zmin
            ({"bounds_min": (-1.0, -2.0)}, "bounds_min"),
            ({"bounds_min": (-1.0, float("nan"), 0.0)}, "bounds_min"),
            ({"bounds_max": "abc"}, "bounds_max"),
            ({"resolution": (4, 0, 3)}, "resolution"),
            ({"resolution": (4, 8, 3.0)}, "resolution"),
            ({"resolution": (4, 8)}, "resolution"),
            ({"resolution": (True, 8, 3)}, "resolution"),
        ],
    )
    def test_exception(self, kwargs: dict, field: str) -> None:
        args = {"bounds_min": (-1.0, -2.0, 0.0), "bounds_max": (1.0, 2.0, 1.5), "resolution": (4, 8, 3)}
        args.update(kwargs)
        with pytest.raises(ValueError, match=field):
            VoxelGridSpec(**args)

    def test_exception_points(self) -> None:
        grid = make_grid()
        with pytest.raises(ValueError, match=r"points must be a tensor of shape \[\.\.\., 3\]"):
            grid.world_to_normalized(torch.zeros(5, 2))
        with pytest.raises(ValueError, match="factor"):
            grid.scaled(3)
        with pytest.raises(ValueError, match="factor"):
            grid.scaled(0)
        with pytest.raises(ValueError, match="keys"):
            VoxelGridSpec.from_dict({"bounds_min": [0, 0, 0]})

    @pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
    def test_cardinality(self, dtype: torch.dtype) -> None:
        grid = make_grid()
        centres = grid.voxel_centres(dtype=dtype)
        assert centres.shape == (3, 8, 4, 3) and centres.dtype == dtype
        points = torch.rand(2, 5, 7, 3, dtype=dtype)
        assert grid.world_to_normalized(points).shape == (2, 5, 7, 3)
        assert grid.contains(points).shape == (2, 5, 7) and grid.contains(points).dtype == torch.bool

    def test_feature_voxel_centres(self) -> None:
        grid = make_grid()
        centres = grid.voxel_centres(dtype=torch.float64)
        # voxel (k, j, i) = (1, 5, 2): x = -1 + 2.5 * 0.5, y = -2 + 5.5 * 0.5, z = 0 + 1.5 * 0.5
        torch.testing.assert_close(centres[1, 5, 2], torch.tensor([0.25, 0.75, 0.75], dtype=torch.float64))
        index = (grid.world_to_normalized(centres) + 1) * torch.tensor(grid.resolution, dtype=torch.float64) / 2 - 0.5
        kk, jj, ii = torch.meshgrid(torch.arange(3), torch.arange(8), torch.arange(4), indexing="ij")
        torch.testing.assert_close(index, torch.stack((ii, jj, kk), -1).double())

    def test_feature_normalized(self) -> None:
        grid = make_grid()
        lo, hi = torch.tensor([grid.bounds_min]), torch.tensor([grid.bounds_max])
        torch.testing.assert_close(grid.world_to_normalized(lo), -torch.ones(1, 3))
        torch.testing.assert_close(grid.world_to_normalized(hi), torch.ones(1, 3))
        # Sampling a volume at its own voxel centres (align_corners=False) returns it exactly.
        volume = torch.rand(1, 2, *grid.volume_shape, dtype=torch.float64)
        coords = grid.world_to_normalized(grid.voxel_centres(dtype=torch.float64))[None]
        sampled = F.grid_sample(volume, coords, mode="bilinear", align_corners=False)
        torch.testing.assert_close(sampled, volume)

    def test_feature_contains(self) -> None:
        grid = make_grid()
        points = torch.tensor(
            [[-1.0, -2.0, 0.0], [0.999, 1.999, 1.499], [1.0, 0.0, 0.5], [0.0, 0.0, -0.01], [0.0, 0.0, 0.75]]
        )
        assert grid.contains(points).tolist() == [True, True, False, False, True]

    def test_feature_scaled(self) -> None:
        grid = VoxelGridSpec((-1.0, -1.0, 0.0), (1.0, 1.0, 2.0), (8, 4, 12))
        half = grid.half()
        assert half == grid.scaled(2)
        assert half.resolution == (4, 2, 6) and half.bounds_min == grid.bounds_min
        assert grid.scaled(4).resolution == (2, 1, 3)
        # coarse voxel centres are the means of the 2x2x2 fine centres they cover
        fine = grid.voxel_centres(dtype=torch.float64).permute(3, 0, 1, 2)[None]
        torch.testing.assert_close(
            F.avg_pool3d(fine, 2)[0].permute(1, 2, 3, 0), half.voxel_centres(dtype=torch.float64)
        )

    def test_feature_dict_round_trip(self) -> None:
        grid = make_grid()
        data = json.loads(json.dumps(grid.to_dict()))
        assert VoxelGridSpec.from_dict(data) == grid
