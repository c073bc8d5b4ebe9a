"""Axis-aligned, cell-centred voxel grid in the reference frame R.

Convention:
    Units are metres; R is right-handed with z up. A grid covers ``[bounds_min, bounds_max)`` with
    ``resolution = (nx, ny, nz)`` cells; volumes on it are tensors ``[B, C, Z, Y, X]``. Voxel
    ``(k, j, i)`` (z, y, x index) has its centre at ``x = xmin + (i + 0.5) * (xmax - xmin) / nx``
    (same for y, z), which is the ``align_corners=False`` convention of ``F.grid_sample``.
"""

from __future__ import annotations

import math
import numbers
from dataclasses import dataclass
from typing import Any

import torch
from torch import Tensor

__all__ = ["VoxelGridSpec"]


def _as_float_triple(name: str, value: Any) -> tuple[float, float, float]:
    try:
        out = tuple(float(v) for v in value)
    except (TypeError, ValueError) as err:
        raise ValueError(f"{name} must be a sequence of 3 numbers (x, y, z), got {value!r}") from err
    if len(out) != 3 or not all(math.isfinite(v) for v in out):
        raise ValueError(f"{name} must be 3 finite numbers (x, y, z), got {value!r}")
    return out  # type: ignore[return-value]


def _as_int_triple(name: str, value: Any) -> tuple[int, int, int]:
    try:
        items = tuple(value)
    except TypeError as err:
        raise ValueError(f"{name} must be a sequence of 3 positive ints (nx, ny, nz), got {value!r}") from err
    if len(items) != 3 or not all(isinstance(v, numbers.Integral) and not isinstance(v, bool) and v > 0 for v in items):
        raise ValueError(f"{name} must be 3 positive ints (nx, ny, nz), got {value!r}")
    return tuple(int(v) for v in items)  # type: ignore[return-value]


@dataclass(frozen=True)
class VoxelGridSpec:
    """Bounds and resolution of an axis-aligned voxel grid in the reference frame R.

    Args:
        bounds_min: ``(xmin, ymin, zmin)`` in metres.
        bounds_max: ``(xmax, ymax, zmax)`` in metres, each strictly greater than its minimum.
        resolution: ``(nx, ny, nz)`` number of voxels per axis (positive ints).

    Convention:
        R is right-handed, z up, metres. Volumes are ``[B, C, Z, Y, X]`` = ``[B, C, nz, ny, nx]``; voxel
        ``(k, j, i)`` has its centre at ``bounds_min + (index + 0.5) * voxel_size`` (cell-centred,
        ``align_corners=False``). The grid covers the half-open box ``[bounds_min, bounds_max)``.
    """

    bounds_min: tuple[float, float, float]
    bounds_max: tuple[float, float, float]
    resolution: tuple[int, int, int]

    def __post_init__(self) -> None:
        bmin = _as_float_triple("bounds_min", self.bounds_min)
        bmax = _as_float_triple("bounds_max", self.bounds_max)
        res = _as_int_triple("resolution", self.resolution)
        for axis, lo, hi in zip("xyz", bmin, bmax, strict=True):
            if not hi > lo:
                raise ValueError(f"bounds_max must exceed bounds_min on every axis; on {axis}: min={lo}, max={hi}")
        object.__setattr__(self, "bounds_min", bmin)
        object.__setattr__(self, "bounds_max", bmax)
        object.__setattr__(self, "resolution", res)

    @property
    def voxel_size(self) -> tuple[float, float, float]:
        """Edge lengths ``(sx, sy, sz)`` of one voxel in metres."""
        (x0, y0, z0), (x1, y1, z1), (nx, ny, nz) = self.bounds_min, self.bounds_max, self.resolution
        return ((x1 - x0) / nx, (y1 - y0) / ny, (z1 - z0) / nz)

    @property
    def volume_shape(self) -> tuple[int, int, int]:
        """Spatial shape ``(nz, ny, nx)`` of a volume tensor ``[B, C, Z, Y, X]`` on this grid."""
        nx, ny, nz = self.resolution
        return (nz, ny, nx)

    @property
    def centre(self) -> tuple[float, float, float]:
        """Centre ``(x, y, z)`` of the grid's box in metres."""
        (x0, y0, z0), (x1, y1, z1) = self.bounds_min, self.bounds_max
        return (0.5 * (x0 + x1), 0.5 * (y0 + y1), 0.5 * (z0 + z1))

    def _bounds(self, like: Tensor) -> tuple[Tensor, Tensor]:
        dtype = like.dtype if like.is_floating_point() else torch.get_default_dtype()
        lo = torch.tensor(self.bounds_min, device=like.device, dtype=dtype)
        hi = torch.tensor(self.bounds_max, device=like.device, dtype=dtype)
        return lo, hi

    def voxel_centres(self, device: torch.device | str | None = None, dtype: torch.dtype | None = None) -> Tensor:
        """``[Z, Y, X, 3]`` coordinates of every voxel centre: ``[k, j, i]`` holds the ``(x, y, z)`` centre of voxel
        ``(k, j, i)`` (dtype default: torch's default dtype).

        Convention: cell-centred, centre = ``bounds_min + (index + 0.5) * voxel_size``, xyz order in the last dim.
        """
        x, y, z = self._axis_centres(device, dtype or torch.get_default_dtype())
        zz, yy, xx = torch.meshgrid(z, y, x, indexing="ij")
        return torch.stack((xx, yy, zz), dim=-1)

    def _axis_centres(self, device: torch.device | str | None, dtype: torch.dtype) -> list[Tensor]:
        """The voxel centres along x ``[nx]``, y ``[ny]`` and z ``[nz]``."""
        axes = zip(self.bounds_min, self.resolution, self.voxel_size, strict=True)
        return [lo + (torch.arange(n, device=device, dtype=dtype) + 0.5) * size for lo, n, size in axes]

    def world_to_normalized(self, points: Tensor) -> Tensor:
        """Map points ``[..., 3]`` ``(x, y, z)`` in R to ``grid_sample`` coordinates ``[..., 3]``, ``-1``/``+1`` at
        ``bounds_min``/``bounds_max``.

        Convention:
            ``n = 2 * (p - min) / (max - min) - 1``, valid for ``align_corners=False`` only.
        """
        _check_points(points)
        lo, hi = self._bounds(points)
        return 2.0 * (points - lo) / (hi - lo) - 1.0

    def contains(self, points: Tensor) -> Tensor:
        """``[...]`` bool: whether points ``[..., 3]`` ``(x, y, z)`` in R lie inside the grid.

        Convention: half-open box ``bounds_min <= p < bounds_max``, the region whose points get a voxel
        ``floor((p - bounds_min) / voxel_size)`` in range.
        """
        _check_points(points)
        lo, hi = self._bounds(points)
        return ((points >= lo) & (points < hi)).all(dim=-1)

    def scaled(self, factor: int) -> VoxelGridSpec:
        """The same bounds at ``resolution // factor`` (``factor`` a positive int dividing every entry).

        Convention: bounds are unchanged, so coarse voxel centres are the means of the fine ones they cover.
        """
        if isinstance(factor, bool) or not isinstance(factor, numbers.Integral) or factor < 1:
            raise ValueError(f"factor must be a positive int, got {factor!r}")
        if any(n % factor for n in self.resolution):
            raise ValueError(f"factor {factor} does not divide resolution {self.resolution}")
        return VoxelGridSpec(self.bounds_min, self.bounds_max, tuple(n // int(factor) for n in self.resolution))

    def half(self) -> VoxelGridSpec:
        """The same bounds at half resolution (the encoder's output grid); see :meth:`scaled`."""
        return self.scaled(2)

    def to_dict(self) -> dict[str, list[float] | list[int]]:
        """JSON-friendly dict ``{"bounds_min": [...], "bounds_max": [...], "resolution": [...]}``."""
        return {key: list(getattr(self, key)) for key in ("bounds_min", "bounds_max", "resolution")}

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> VoxelGridSpec:
        """Inverse of :meth:`to_dict`; raises ValueError on missing or unknown keys."""
        keys = {"bounds_min", "bounds_max", "resolution"}
        if set(data) != keys:
            raise ValueError(f"VoxelGridSpec dict must have exactly the keys {sorted(keys)}, got {sorted(data)}")
        return cls(data["bounds_min"], data["bounds_max"], data["resolution"])


def _desc(x: object) -> object:
    """What a bad argument was, for an error message: its shape, or its type's name."""
    return tuple(x.shape) if isinstance(x, Tensor) else type(x).__name__


def _check_points(points: Tensor) -> None:
    if not isinstance(points, Tensor) or points.ndim < 1 or points.shape[-1] != 3:
        raise ValueError(f"points must be a tensor of shape [..., 3], got {_desc(points)}")


def _check_grid(grid: object) -> None:
    if not isinstance(grid, VoxelGridSpec):
        raise ValueError(f"grid must be a VoxelGridSpec, got {type(grid).__name__}")
