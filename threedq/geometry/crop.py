"""Cropping axis-aligned boxes out of feature volumes.

Convention:
    Boxes are axis-aligned in the reference frame R (metres, z up): ``(xmin, ymin, zmin, xmax, ymax, zmax)``.
    Volumes are ``[B, C, Z, Y, X]`` on a cell-centred :class:`VoxelGridSpec`; sampling is a local ``grid_sample``
    with ``align_corners=False``.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor

from .grid import VoxelGridSpec, _check_grid, _desc

__all__ = ["box_mask", "crop_boxes", "occupancy_weighted", "paste_boxes", "sample_volume"]

def _check_boxes(boxes: Tensor) -> None:
    if not isinstance(boxes, Tensor) or boxes.ndim != 3 or boxes.shape[-1] != 6:
        raise ValueError(f"boxes must have shape [B, N, 6] (xmin, ymin, zmin, xmax, ymax, zmax), got {_desc(boxes)}")


def _check_volume(volume: Tensor, grid: VoxelGridSpec) -> None:
    _check_grid(grid)
    if volume.ndim != 5 or tuple(volume.shape[2:]) != grid.volume_shape:
        raise ValueError(f"volume must have shape [B, C, Z, Y, X] with (Z, Y, X) = {grid.volume_shape}, got "
                         f"{tuple(volume.shape)}")


def _as_size(size: int | tuple[int, int, int]) -> tuple[int, int, int]:
    sizes = (size,) * 3 if isinstance(size, int) else tuple(size)
    if len(sizes) != 3 or not all(isinstance(s, int) and not isinstance(s, bool) and s > 0 for s in sizes):
        raise ValueError(f"size must be a positive int or a tuple of 3 positive ints (sz, sy, sx), got {size!r}")
    return sizes  # type: ignore[return-value]


def _box_sample_points(boxes: Tensor, size: tuple[int, int, int]) -> Tensor:
    """Centres of the ``sz x sy x sx`` cells of each box: ``[B, N, sz, sy, sx, 3]`` (xyz) in R."""
    lo, hi = boxes[..., :3], boxes[..., 3:]
    sz, sy, sx = size
    axes = [(torch.arange(n, device=boxes.device, dtype=boxes.dtype) + 0.5) / n for n in (sx, sy, sz)]  # x, y, z
    fz, fy, fx = torch.meshgrid(axes[2], axes[1], axes[0], indexing="ij")
    frac = torch.stack((fx, fy, fz), dim=-1)  # [sz, sy, sx, 3]
    return lo[:, :, None, None, None, :] + frac * (hi - lo)[:, :, None, None, None, :]


def sample_volume(volume: Tensor, coords: Tensor) -> Tensor:
    """``F.grid_sample(volume, coords)`` (trilinear, zero padding, ``align_corners=False``), its points spread over
    the CPU's threads when the batch is smaller than their number (without autograd; bitwise the same values).

    Args:
        volume: ``[B, C, Z, Y, X]``.
        coords: ``[B, D, H, W, 3]`` normalised ``(x, y, z)`` in ``[-1, 1]``.

    Returns:
        ``[B, C, D, H, W]``, dtype of ``volume``.

    Convention: as ``F.grid_sample`` with ``align_corners=False``: ``-1`` and ``1`` are the outer faces of the
    first and last cells.
    """
    batch = volume.shape[0]
    threads = torch.get_num_threads()
    grad = torch.is_grad_enabled() and (volume.requires_grad or coords.requires_grad)
    if volume.device.type != "cpu" or batch >= threads or grad or volume.ndim != 5:
        return F.grid_sample(volume, coords, mode="bilinear", padding_mode="zeros", align_corners=False)
    k = -(-threads // batch)  # chunks per volume
    out_shape = coords.shape[1:4]
    n_points = out_shape[0] * out_shape[1] * out_shape[2]
    per = -(-n_points // k)
    pts = coords.reshape(batch, n_points, 3)
    if per * k != n_points:
        pts = F.pad(pts, (0, 0, 0, per * k - n_points))  # the padding samples the centre and is dropped below
    chunks = volume[:, None].expand(batch, k, *volume.shape[1:]).reshape(batch * k, *volume.shape[1:])
    out = F.grid_sample(chunks, pts.reshape(batch * k, per, 1, 1, 3), mode="bilinear", padding_mode="zeros",
                        align_corners=False)  # [B * k, C, per, 1, 1]
    channels = volume.shape[1]
    out = out.view(batch, k, channels, per).transpose(1, 2).reshape(batch, channels, k * per)[:, :, :n_points]
    return out.reshape(batch, channels, *out_shape)


def crop_boxes(volume: Tensor, boxes: Tensor, grid: VoxelGridSpec, size: int | tuple[int, int, int] = 16,
               mask: Tensor | None = None) -> Tensor:
    """Crop boxes out of a volume and resize each to a fixed size (trilinear, aspect not kept).

    Output cell ``(c, b, a)`` of a box samples the volume at the centre of that cell of the box, e.g.
    ``x = xmin + (a + 0.5) * (xmax - xmin) / sx``: ``F.grid_sample`` (trilinear, zero padding,
    ``align_corners=False``) at those points, or on a CPU without autograd its arithmetic as row gathers
    (:func:`_gather_crops`, bitwise the same values).

    Args:
        volume: ``[B, C, Z, Y, X]`` feature volume on ``grid``.
        boxes: ``[B, N, 6]`` boxes ``(xmin, ymin, zmin, xmax, ymax, zmax)`` in R.
        grid: the grid of ``volume``.
        size: output size, an int or ``(sz, sy, sx)`` in output-dimension (z, y, x) order.
        mask: ``[B, N]`` bool: return only these boxes' crops (the row gather samples no other box).

    Returns:
        ``[B, N, C, sz, sy, sx]`` crops, or with ``mask`` the ``[K, C, sz, sy, sx]`` crops of its ``K`` true boxes
        in ``(b, n)`` order (``crop_boxes(volume, boxes, grid, size)[mask]``, bitwise); zero where a sample falls
        outside the grid. The dtype of ``volume`` (float32 under CPU autocast, as ``grid_sample``). Differentiable
        w.r.t. ``volume``.

    Convention:
        Axis-aligned boxes in R; cell-centred voxels, ``align_corners=False``. Boxes are not validated:
        an inverted box (min > max) gives a mirrored crop.
    """
    _check_volume(volume, grid)
    _check_boxes(boxes)
    if boxes.shape[0] != volume.shape[0]:
        raise ValueError(f"boxes must have shape [B, N, 6] with B={volume.shape[0]}, got {tuple(boxes.shape)}")
    if mask is not None and (not isinstance(mask, Tensor) or mask.dtype != torch.bool or mask.shape != boxes.shape[:2]):
        got = (str(mask.dtype), tuple(mask.shape)) if isinstance(mask, Tensor) else type(mask).__name__
        raise ValueError(f"mask must be a bool tensor of shape [B, N] = {tuple(boxes.shape[:2])}, got {got}")
    sz, sy, sx = _as_size(size)
    batch, channels = volume.shape[:2]
    n_boxes = boxes.shape[1]
    boxes = boxes.to(volume.dtype)
    grad = torch.is_grad_enabled() and (volume.requires_grad or boxes.requires_grad)
    if volume.device.type == "cpu" and not grad and channels >= _GATHER_MIN_CHANNELS:
        if mask is None:
            flat, index = boxes.reshape(-1, 6), torch.arange(batch).repeat_interleave(n_boxes)
        else:
            flat, index = boxes[mask], mask.nonzero()[:, 0]
        cells = batch * (grid.volume_shape[0] + 2) * (grid.volume_shape[1] + 2) * (grid.volume_shape[2] + 2)
        if cells <= _GATHER_MAX_CELLS_PER_POINT * flat.shape[0] * sz * sy * sx:
            crops = _gather_crops(volume, flat, index, grid, (sz, sy, sx))
            if crops is not None:
                return crops if mask is not None else crops.view(batch, n_boxes, *crops.shape[1:])
    crops = _sampled_crops(volume, boxes, grid, (sz, sy, sx))
    return crops if mask is None else crops[mask]


def _sampled_crops(volume: Tensor, boxes: Tensor, grid: VoxelGridSpec, size: tuple[int, int, int]) -> Tensor:
    """:func:`crop_boxes` as one :func:`sample_volume` call: ``[B, N, C, sz, sy, sx]`` (``boxes`` ``[B, N, 6]`` in
    ``volume``'s dtype)."""
    batch, n_boxes = boxes.shape[:2]
    points = _box_sample_points(boxes, size)  # [B, N, sz, sy, sx, 3]
    coords = grid.world_to_normalized(points).reshape(batch, n_boxes * size[0], size[1], size[2], 3)
    crops = sample_volume(volume, coords)
    return crops.view(batch, crops.shape[1], n_boxes, *size).transpose(1, 2).contiguous()


#: :func:`_gather_crops` is used for volumes of at least this many channels whose table (the volume with its border)
#: has at most this many cells per sample point
_GATHER_MIN_CHANNELS = 16
_GATHER_MAX_CELLS_PER_POINT = 4
#: sample points per gather round of :func:`_gather_crops` (a float32 round of 32 channels: 2 MB)
_GATHER_CHUNK = 16384


def _gather_crops(volume: Tensor, boxes: Tensor, index: Tensor, grid: VoxelGridSpec,
                  size: tuple[int, int, int]) -> Tensor | None:
    """:func:`crop_boxes` without ``grid_sample``: bitwise its values, the channels gathered as rows.

    The operations of ATen's CPU ``grid_sample`` (5-D, trilinear, zero padding, ``align_corners=False``) in its
    order: per axis ``i = ((g + 1) * n - 1) / 2``, corner weights ``(wx * wy) * wz`` with ``w0 = (floor(i) + 1) - i``
    and ``w1 = i - floor(i)``, the eight corners added x fastest, then y, then z. The volume becomes a
    ``[B * (Z+2) * (Y+2) * (X+2), C]`` table of channel rows with a zero border; each corner is one ``index_select``.

    Args:
        volume: ``[B, C, Z, Y, X]``. boxes: ``[K, 6]`` in ``volume``'s dtype. index: ``[K]`` the volume of each box.
        grid: the grid of ``volume``. size: ``(sz, sy, sx)``.

    Returns:
        ``[K, C, sz, sy, sx]``, or None when a sample point is not finite (``grid_sample`` then decides).

    Convention: as :func:`crop_boxes`.
    """
    n_crops, channels = boxes.shape[0], volume.shape[1]
    sizes = (size[2], size[1], size[0])  # x, y, z
    if torch.is_autocast_enabled("cpu") and volume.dtype != torch.float64:
        compute = torch.float32  # CPU autocast runs grid_sample in float32 (the points are still made in bf16)
    else:
        compute = volume.dtype
    # each axis's sample positions, made by the operations of _box_sample_points and world_to_normalized
    lo, hi = boxes[:, :3], boxes[:, 3:]
    s_max = max(sizes)
    # [s_max, 3]; an axis with fewer cells is padded (not read)
    frac = torch.stack(
        [F.pad((torch.arange(n, dtype=boxes.dtype) + 0.5) / n, (0, s_max - n), value=0.5) for n in sizes], dim=-1
    )
    norm = grid.world_to_normalized(lo[:, None, :] + frac * (hi - lo)[:, None, :]).to(compute)  # [K, s_max, 3]
    if not bool(torch.isfinite(norm).all()):
        return None
    zyx = volume.shape[2:]
    pad = [n + 2 for n in zyx]  # (Z+2, Y+2, X+2)
    strides = (pad[1] * pad[2], pad[2], 1)  # z, y, x rows in the table
    idx, wts = [], []
    for axis, n in enumerate(sizes):  # x, y, z
        i = ((norm[:, :n, axis] + 1) * zyx[2 - axis] - 1) / 2
        f0 = torch.floor(i)
        # a corner outside the volume reads the zero border (index -1 or n, shifted by the border's 1)
        first = f0.clamp(-2, zyx[2 - axis]).long() + 1
        hi, stride = zyx[2 - axis] + 1, strides[2 - axis]
        idx.append([first.clamp(0, hi) * stride, (first + 1).clamp(0, hi) * stride])
        wts.append([(f0 + 1) - i, i - f0])
    table = volume.new_zeros(volume.shape[0], *pad, channels, dtype=compute)
    table[:, 1:-1, 1:-1, 1:-1] = volume.permute(0, 2, 3, 4, 1)
    table = table.view(-1, channels)
    base = (index.to(volume.device) * (pad[0] * pad[1] * pad[2]))[:, None, None, None]  # [K, 1, 1, 1]
    (x0, x1), (y0, y1), (z0, z1) = idx
    (wx0, wx1), (wy0, wy1), (wz0, wz1) = wts
    terms = []
    for zi, wz in ((z0, wz0), (z1, wz1)):  # grid_sample's corner order: x fastest, then y, then z
        for yi, wy in ((y0, wy0), (y1, wy1)):
            zy = base + zi[:, :, None, None] + yi[:, None, :, None]  # [K, sz, sy, 1]
            for xi, wx in ((x0, wx0), (x1, wx1)):
                rows = (zy + xi[:, None, None, :]).view(-1)
                w = ((wx[:, None, None, :] * wy[:, None, :, None]) * wz[:, :, None, None]).view(-1, 1)
                terms.append((rows, w))
    n_points = n_crops * size[0] * size[1] * size[2]
    out = torch.empty(n_points, channels, dtype=compute, device=volume.device)
    for start in range(0, n_points, _GATHER_CHUNK):
        end = min(n_points, start + _GATHER_CHUNK)
        acc = out[start:end]
        for k, (rows, w) in enumerate(terms):
            v = table.index_select(0, rows[start:end])
            if k == 0:
                torch.mul(v, w[start:end], out=acc)
            else:
                acc += v.mul_(w[start:end])  # two roundings, as grid_sample (not a fused multiply-add)
    return out.view(n_crops, *size, channels).permute(0, 4, 1, 2, 3).contiguous()


def box_mask(boxes: Tensor, grid: VoxelGridSpec) -> Tensor:
    """Voxels whose centre lies inside each box.

    Args:
        boxes: ``[B, N, 6]`` boxes ``(xmin, ymin, zmin, xmax, ymax, zmax)`` in R.
        grid: the voxel grid.

    Returns:
        ``[B, N, Z, Y, X]`` bool, true where ``min <= centre <= max`` on all three axes (closed box).

    Convention:
        Axis-aligned boxes in R; cell-centred voxels.
    """
    _check_grid(grid)
    _check_boxes(boxes)
    dtype = boxes.dtype if boxes.is_floating_point() else torch.get_default_dtype()
    boxes = boxes.to(dtype)
    centres = grid._axis_centres(boxes.device, dtype)
    mx, my, mz = [(c >= boxes[..., axis, None]) & (c <= boxes[..., axis + 3, None]) for axis, c in enumerate(centres)]
    return mz[:, :, :, None, None] & my[:, :, None, :, None] & mx[:, :, None, None, :]


def paste_boxes(volume: Tensor, crops: Tensor, boxes: Tensor, grid: VoxelGridSpec,
                mask: Tensor | None = None) -> Tensor:
    """Write crops back into a volume, each resized to fill its box: the inverse of :func:`crop_boxes`.

    Every voxel whose centre lies inside a box (:func:`box_mask`) takes the crop's value at the voxel's place in
    the box (a centre at fraction ``f`` of the box samples the crop at fraction ``f``, trilinear, border-clamped).
    Boxes are pasted in order (the later one wins); voxels outside every box keep ``volume``'s values.

    Args:
        volume: ``[B, C, Z, Y, X]`` volume on ``grid`` (not modified).
        crops: ``[B, N, C, sz, sy, sx]`` crops, e.g. prototypes rotated to each object's yaw.
        boxes: ``[B, N, 6]`` boxes ``(xmin, ymin, zmin, xmax, ymax, zmax)`` in R.
        grid: the grid of ``volume``.
        mask: ``[B, N]`` bool, which boxes to paste (default: all).

    Returns:
        ``[B, C, Z, Y, X]`` a new volume. Differentiable w.r.t. ``volume`` and ``crops``.

    Convention:
        Axis-aligned boxes in R; cell-centred voxels and crop cells, ``align_corners=False``.
    """
    _check_volume(volume, grid)
    _check_boxes(boxes)
    B, C = volume.shape[:2]
    N = boxes.shape[1]
    if boxes.shape[0] != B or crops.ndim != 6 or tuple(crops.shape[:3]) != (B, N, C):
        raise ValueError(f"crops must have shape [B, N, C, sz, sy, sx] = [{B}, {N}, {C}, ...] to match volume and "
                         f"boxes {tuple(boxes.shape)}, got {tuple(crops.shape)}")
    if mask is not None and tuple(mask.shape) != (B, N):
        raise ValueError(f"mask must have shape [B, N] = [{B}, {N}], got {tuple(mask.shape)}")
    boxes = boxes.to(volume.dtype)
    inside = box_mask(boxes, grid)  # [B, N, Z, Y, X]
    axes = grid._axis_centres(volume.device, volume.dtype)  # x, y, z centres
    out = volume.clone()
    for b in range(B):
        for n in range(N):
            if mask is not None and not bool(mask[b, n]):
                continue
            sel = inside[b, n]
            if not bool(sel.any()):
                continue
            lo, hi = boxes[b, n, :3], boxes[b, n, 3:]
            norm = [(2 * (c - lo[i]) / (hi[i] - lo[i]).clamp_min(1e-12) - 1) for i, c in enumerate(axes)]
            gz, gy, gx = torch.meshgrid(norm[2], norm[1], norm[0], indexing="ij")
            coords = torch.stack((gx, gy, gz), dim=-1)[None]  # [1, Z, Y, X, 3]
            vals = F.grid_sample(crops[b, n][None], coords, mode="bilinear", padding_mode="border", align_corners=False)
            out[b] = torch.where(sel[None], vals[0], out[b])
    return out


def occupancy_weighted(features: Tensor, occupancy: Tensor, floor: float = 0.2, dilation: int = 3) -> Tensor:
    """Crops whose voxels count by how near they are to observed surface: ``features * (floor + dilate(occ))``.

    Every voxel is weighted by ``floor`` plus the crop's input occupancy max-pooled over a ``dilation^3``
    neighbourhood (surface voxels and their neighbours count ``1 + floor``, empty space ``floor``).

    Args:
        features: ``[N, C, s, s, s]`` crops of the feature grid.
        occupancy: ``[N, 1, s, s, s]`` crops of the input occupancy (channel 0 of the raw ``cat[occ, occ * rgb]``
            crop) of the same boxes, in [0, 1].
        floor: weight of a voxel with no occupied voxel near it (>= 0; with 0 empty space is ignored).
        dilation: odd neighbourhood edge of the max-pool (1: the occupancy itself).

    Returns:
        ``[N, C, s, s, s]`` weighted crops (dtype of ``features``). Differentiable w.r.t. ``features``.

    Convention: crops ``[N, C, Z, Y, X]`` on the same cells; the weight does not change with yaw, so the weighted
    crops go through every rotation search as they are.
    """
    if features.ndim != 5 or occupancy.ndim != 5 or occupancy.shape[1] != 1:
        raise ValueError(f"features [N, C, s, s, s] and occupancy [N, 1, s, s, s] expected, got "
                         f"{tuple(features.shape)} and {tuple(occupancy.shape)}")
    if occupancy.shape[0] != features.shape[0] or occupancy.shape[2:] != features.shape[2:]:
        raise ValueError(f"occupancy {tuple(occupancy.shape)} does not match features {tuple(features.shape)}")
    if isinstance(dilation, bool) or not isinstance(dilation, int) or dilation < 1 or dilation % 2 == 0:
        raise ValueError(f"dilation: expected an odd int >= 1, got {dilation!r}")
    if not floor >= 0:
        raise ValueError(f"floor: expected >= 0, got {floor!r}")
    occ = occupancy.to(features.dtype)
    if dilation > 1:
        occ = F.max_pool3d(occ, dilation, stride=1, padding=dilation // 2)
    return features * (floor + occ)
