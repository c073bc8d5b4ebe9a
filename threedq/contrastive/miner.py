"""3D correspondence mining (paper supplement): object-level rotation-max retrieval, patch matching over yaws and
positions, and spatial-consistency verification by context patches.

:func:`mine_correspondences`, for every query crop: retrieves the ``top_k`` targets of highest rotation-max cosine
(:func:`retrieve_targets`); matches one query patch against every target rotated by each of ``num_angles`` yaws, at
each position of a centred ``grid^3`` grid of patches (:func:`match_patch`, :func:`patch_grid`); verifies each match
by the context patches at Manhattan distance ``context_distance`` (:func:`verify_match`); keeps the ``keep`` best
pairs with score ``>= min_score``.

Convention:
    Crops are ``[N, C, Z, Y, X]`` (z up); a single crop is ``[C, Z, Y, X]``. A patch position is the
    ``(z, y, x)`` voxel index of its first corner: patch ``pos`` covers voxels
    ``[z:z + patch, y:y + patch, x:x + patch]``; its vector is those voxels' features flattened (``C * patch^3``)
    and L2-normalised. Yaw index ``b`` means ``2 pi b / A`` radians counter-clockwise seen from above, applied
    with ``threedq.geometry.rotate_yaw`` (rotation about the vertical centre line, ``align_corners=False``).
    In :func:`match_patch`, :func:`verify_match` and :func:`mine_correspondences` the yaw rotates the TARGET:
    ``rotate_yaw(target, 2 pi b / A)`` is aligned with the query around the matched patch (the "aligned
    target"), so the query rotated by ``-b`` steps aligns with the target; this is the opposite sign of the
    object-level ``angle`` of :func:`retrieve_targets` / ``all_pairs_rotation_max`` (query rotated onto target),
    i.e. ``b ~ -angle mod A`` for a consistent pair. Positions in the aligned target map to the unrotated
    target crop with :func:`rotate_patch_positions` (``yaw = -2 pi b / A``).
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Sequence

import torch
import torch.nn.functional as F
from torch import Tensor

from threedq.geometry.grid import _desc
from threedq.geometry.rotate import _yaw_theta, rotate_yaw, yaw_angles
from threedq.quantization.rotation_search import _check_crops, all_pairs_rotation_max

__all__ = ["calibrate_context_cosine", "context_offsets", "match_patch", "mine_correspondences", "patch_grid",
           "retrieve_targets", "rotate_patch_positions", "salient_positions", "verify_match"]

#: Floats of scratch one vectorised chunk may use (~64 MiB in float32).
_CHUNK_FLOATS = 1 << 24
#: Pairs whose crops :func:`mine_correspondences` gathers at once for verification.
_VERIFY_PAIRS = 256
#: A position of a rotated target is usable when at least this fraction of every voxel of the patch comes from
#: inside the unrotated crop (``rotate_yaw`` pads with zeros).
_MIN_COVERAGE = 0.5
#: The keys of :func:`mine_correspondences`' result, in order; the first six hold long tensors.
_LONG_KEYS = ("query_index", "target_index", "query_pos", "target_pos", "target_pos_aligned", "yaw")
_KEYS = (*_LONG_KEYS, "match_cosine", "score", "retrieval_sim")


def _check_int(name: str, v: object, minimum: int = 1) -> int:
    if isinstance(v, bool) or not isinstance(v, int) or v < minimum:
        raise ValueError(f"{name} must be an int >= {minimum}, got {v!r}")
    return v


def _check_ints(**values: object) -> None:
    for name, v in values.items():
        _check_int(name, v)


def _check_unit(name: str, v: object, lo: float) -> None:
    if isinstance(v, bool) or not isinstance(v, (int, float)) or not lo <= v <= 1.0:
        raise ValueError(f"{name} must be a number in [{lo:g}, 1], got {v!r}")


def _check_volume(x: object, name: str, ndim: int) -> Tensor:
    _check_crops(x, name, ndim)
    return x if x.dtype in (torch.float32, torch.float64) else x.float()


def _check_pos(pos: object, name: str, size: Sequence[int], patch: int, device: torch.device) -> Tensor:
    """A ``(z, y, x)`` patch position as a long ``[3]`` tensor, checked to lie inside a volume of ``size``."""
    if isinstance(pos, Tensor):
        if pos.shape != (3,) or pos.is_floating_point() or pos.dtype == torch.bool:
            raise ValueError(f"{name} must be 3 ints (z, y, x), got a tensor of shape {_desc(pos)} and {pos.dtype}")
        vals = [int(v) for v in pos.tolist()]
    else:
        ints = isinstance(pos, Sequence) and all(isinstance(v, int) and not isinstance(v, bool) for v in pos)
        if not ints or len(pos) != 3:
            raise ValueError(f"{name} must be 3 ints (z, y, x), got {pos!r}")
        vals = list(pos)
    if any(v < 0 or v + patch > n for v, n in zip(vals, size)):
        raise ValueError(f"{name}={tuple(vals)}: a {patch}^3 patch there leaves the volume of size {tuple(size)}")
    return torch.tensor(vals, dtype=torch.long, device=device)


def _inside(starts: Tensor, size: Sequence[int], patch: int) -> Tensor:
    hi = torch.tensor([n - patch for n in size], device=starts.device)
    return ((starts >= 0) & (starts <= hi)).all(dim=-1)


def patch_grid(size: int, grid: int = 4, patch: int = 2) -> list[int]:
    """First voxel of each of ``grid`` patches along an axis of ``size`` voxels, stride ``size // grid``, centred.

    The offset is ``(size - patch - stride * (grid - 1)) // 2`` (``size=16, grid=4, patch=2``: ``[1, 5, 9, 13]``).

    Raises:
        ValueError: if the grid does not fit (``stride < 1`` or a patch would leave the axis).
    """
    _check_ints(size=size, grid=grid, patch=patch)
    stride = size // grid
    offset = (size - patch - stride * (grid - 1)) // 2 if stride >= 1 else -1
    if stride < 1 or offset < 0:
        raise ValueError(f"a grid of {grid} patches of {patch} voxels does not fit an axis of {size} voxels")
    return [offset + i * stride for i in range(grid)]


def rotate_patch_positions(positions: Tensor, yaw: Tensor | float, size: Sequence[int], patch: int = 2, *,
                           round: bool = True) -> Tensor:
    """Where patches of a crop land in ``rotate_yaw(crop, yaw)``.

    The patch centre ``pos + (patch - 1) / 2`` is rotated about the crop centre ``((Y - 1) / 2, (X - 1) / 2)``
    as ``rotate_yaw`` moves content (z unchanged). The inverse map is ``-yaw``: a position ``p`` in the target
    aligned by yaw index ``b`` (:func:`match_patch`) is ``rotate_patch_positions(p, -2 pi b / A, size)`` in the
    unrotated target.

    Args:
        positions: ``[..., 3]`` patch positions ``(z, y, x)`` (int or float).
        yaw: radians, a float or a tensor broadcastable to ``positions.shape[:-1]``.
        size: ``(Z, Y, X)`` of the crop.
        patch: patch edge in voxels.
        round: round to the nearest voxel (long result) or return float positions.

    Returns:
        ``[..., 3]`` long (``round=True``) or float positions in the rotated crop; not clamped to the crop.

    Convention:
        Counter-clockwise seen from above, as ``threedq.geometry.rotate_yaw``.
    """
    if not isinstance(positions, Tensor) or positions.ndim < 1 or positions.shape[-1] != 3:
        raise ValueError(f"positions must have shape [..., 3], got {_desc(positions)}")
    if len(size) != 3:
        raise ValueError(f"size must be (Z, Y, X), got {size!r}")
    _check_int("patch", patch)
    dtype = torch.float64
    pos = positions.to(dtype)
    t = torch.as_tensor(yaw, dtype=dtype, device=positions.device)
    half = (patch - 1) / 2.0
    cy, cx = (size[1] - 1) / 2.0, (size[2] - 1) / 2.0
    y, x = pos[..., 1] + half - cy, pos[..., 2] + half - cx
    c, s = torch.cos(t), torch.sin(t)
    out = torch.stack((pos[..., 0] + half, x * s + y * c + cy, x * c - y * s + cx), dim=-1) - half
    if round:
        return torch.round(out).long()
    return out.to(positions.dtype if positions.is_floating_point() else torch.get_default_dtype())


def context_offsets(context_distance: int = 6, device: torch.device | str | None = None) -> Tensor:
    """All integer offsets ``(dz, dy, dx)`` with ``|dz| + |dy| + |dx| == context_distance``: ``[D, 3]`` long.

    ``D = 4 d^2 + 2`` (146 for ``d = 6``), in lexicographic order.
    """
    d = _check_int("context_distance", context_distance)
    rng = range(-d, d + 1)
    offs = [o for o in itertools.product(rng, rng, rng) if abs(o[0]) + abs(o[1]) + abs(o[2]) == d]
    return torch.tensor(offs, dtype=torch.long, device=device)


def _patch_voxels(patch: int, device: torch.device) -> Tensor:
    """``[patch^3, 3]`` voxel offsets of a patch, z-major (the order of ``crop[:, z:z+p, y:y+p, x:x+p]``)."""
    r = torch.arange(patch, device=device)
    return torch.stack(torch.meshgrid(r, r, r, indexing="ij"), dim=-1).reshape(-1, 3)


def _gather_patches(volumes: Tensor, starts: Tensor, patch: int) -> Tensor:
    """Flattened patches ``[P, ..., patch^3 * C]`` (voxel-major, then channel) at ``starts`` ``[P, ..., 3]``.

    ``volumes`` is ``[P, C, Z, Y, X]``; ``starts`` must already lie inside (callers clamp and mask).
    """
    p_count, channels, nz, ny, nx = volumes.shape
    flat = volumes.permute(0, 2, 3, 4, 1).reshape(p_count * nz * ny * nx, channels)
    vox = starts[..., None, :] + _patch_voxels(patch, starts.device)  # [P, ..., p^3, 3]
    idx = (vox[..., 0] * ny + vox[..., 1]) * nx + vox[..., 2]
    base = torch.arange(p_count, device=starts.device).view(-1, *([1] * (idx.ndim - 1))) * (nz * ny * nx)
    out = flat.index_select(0, (idx + base).reshape(-1))
    return out.view(*idx.shape[:-1], patch**3 * channels)


def _rotated_grid_patches(targets: Tensor, angles: Tensor, starts: Sequence[list[int]], patch: int) -> Tensor:
    """Patches of every yaw-rotated target at every grid position: ``[K, A, G, C * patch^3]``, not normalised.

    ``angles``: ``[A]`` yaws shared by every target, or ``[K, A]`` yaws of each target.

    Equal to cutting the patches out of ``rotate_yaw(targets, angles)`` (the same sampling grid is used) but
    only the voxel rows/columns/slices that some grid patch covers are interpolated. Flattening order per patch:
    channel-major ``[C, pz, py, px]``, like ``crop[:, z:z+p, y:y+p, x:x+p].reshape(-1)``.
    """
    k, channels, _, ny, nx = targets.shape
    n_angles = angles.shape[-1]
    r = torch.arange(patch, device=targets.device)
    zs, ys, xs = ((torch.tensor(s, device=targets.device)[:, None] + r).reshape(-1) for s in starts)  # [G_i * p]
    flat = angles.reshape(-1)
    coords = F.affine_grid(_yaw_theta(flat, ny, nx), [flat.numel(), 1, ny, nx], align_corners=False)  # [A', Y, X, 2]
    coords = coords[:, ys][:, :, xs]  # [A', Ly, Lx, 2]
    ly, lx, lz = ys.numel(), xs.numel(), zs.numel()
    slices = targets[:, :, zs].reshape(k, channels * lz, ny, nx)
    if angles.dim() == 1:
        grid = coords.reshape(1, n_angles * ly, lx, 2).expand(k, -1, -1, -1)
    else:
        grid = coords.reshape(k, n_angles * ly, lx, 2)
    out = F.grid_sample(slices, grid, mode="bilinear", padding_mode="zeros", align_corners=False)
    gz, gy, gx = (len(s) for s in starts)
    out = out.view(k, channels, gz, patch, n_angles, gy, patch, gx, patch)
    out = out.permute(0, 4, 2, 5, 7, 1, 3, 6, 8)  # [K, A, Gz, Gy, Gx, C, pz, py, px]
    return out.reshape(k, n_angles, gz * gy * gx, channels * patch**3)


@torch.no_grad()
def retrieve_targets(query_crops: Tensor, target_crops: Tensor, top_k: int = 30, num_angles: int = 36,
                     exclude: Tensor | None = None, *, method: str = "fast") -> tuple[Tensor, Tensor, Tensor]:
    """The ``top_k`` targets of highest rotation-max cosine for every query (object-level retrieval).

    Args:
        query_crops: ``[N, C, S, S, S]`` feature crops.
        target_crops: ``[M, C, S, S, S]`` feature crops (same ``C, S``).
        top_k: targets per query; clamped to ``M``.
        num_angles: yaw candidates ``A``.
        exclude: optional ``[N, M]`` bool, True where a target must not be retrieved for a query (same object,
            same scene, or the query itself when ``target_crops`` is ``query_crops``); set to ``-inf``.
        method: ``"fast"`` or ``"exact"``, see ``all_pairs_rotation_max``.

    Returns:
        ``idx`` ``[N, k]`` long target indices, best first; ``sim`` ``[N, k]`` their rotation-max cosines (``-inf``
        marks a slot with no admissible target left); ``angle`` ``[N, k]`` long yaw indices.

    Convention:
        As ``all_pairs_rotation_max``: rotating query ``n`` by ``2 pi angle / A`` aligns it with target ``idx``.
    """
    query_crops = _check_volume(query_crops, "query_crops", 5)
    target_crops = _check_volume(target_crops, "target_crops", 5)
    if query_crops.shape[1:] != target_crops.shape[1:]:
        raise ValueError(f"query_crops and target_crops must share [C, Z, Y, X], got {tuple(query_crops.shape)} and "
                         f"{tuple(target_crops.shape)}")
    _check_ints(top_k=top_k, num_angles=num_angles)
    n, m = query_crops.shape[0], target_crops.shape[0]
    bad = not isinstance(exclude, Tensor) or exclude.dtype != torch.bool or exclude.shape != (n, m)
    if exclude is not None and bad:
        got = (tuple(exclude.shape), exclude.dtype) if isinstance(exclude, Tensor) else type(exclude).__name__
        raise ValueError(f"exclude must be a bool tensor of shape [{n}, {m}], got {got}")
    k = min(top_k, m)
    if n == 0 or m == 0:
        empty = torch.zeros(n, k, dtype=torch.long, device=query_crops.device)
        return empty, empty.to(query_crops.dtype), empty.clone()
    sim, angle = all_pairs_rotation_max(query_crops, target_crops, num_angles, method)
    if exclude is not None:
        sim = sim.masked_fill(exclude.to(sim.device), float("-inf"))
    top_sim, idx = sim.topk(k, dim=1)
    return idx, top_sim, angle.gather(1, idx)


@torch.no_grad()
def match_patch(query_crop: Tensor, query_pos: Sequence[int] | Tensor, target_crops: Tensor, num_angles: int = 36,
                patch: int = 2, grid: int = 4, allowed_yaws: Tensor | None = None) -> tuple[Tensor, Tensor, Tensor]:
    """Best (yaw, grid position) of a query patch in each target crop.

    The query patch is compared by cosine with every target rotated by each of the ``num_angles`` yaws (as
    ``rotate_yaw``), at each position of the centred ``grid^3`` grid of :func:`patch_grid`; the argmax over
    (yaw, position) is returned (first one on ties).

    Args:
        query_crop: ``[C, Z, Y, X]`` features of the query crop.
        query_pos: ``(z, y, x)`` ints, the query patch's first voxel.
        target_crops: ``[K, C, S, S, S]`` target features (``C`` as the query).
        num_angles: yaw candidates ``A``.
        patch: patch edge in voxels.
        grid: grid positions per axis.
        allowed_yaws: optional ``[K, A]`` bool, the yaws searched per target (default: all); each row needs one.

    Returns:
        ``yaw`` ``[K]`` long yaw index; ``pos`` ``[K, 3]`` long ``(z, y, x)`` of the best patch in the ALIGNED
        target ``rotate_yaw(target, 2 pi yaw / A)``; ``cosine`` ``[K]``. Map ``pos`` to the unrotated target with
        ``rotate_patch_positions(pos, -2 pi yaw / A, target.shape[-3:], patch)``.

    Convention:
        Rotating the target by ``yaw`` steps aligns it with the query around the patch (query rotated by ``-yaw``
        steps aligns with the target).
    """
    query_crop = _check_volume(query_crop, "query_crop", 4)
    target_crops = _check_volume(target_crops, "target_crops", 5)
    if target_crops.shape[1] != query_crop.shape[0]:
        raise ValueError(f"target_crops must have C={query_crop.shape[0]} channels, got {target_crops.shape[1]}")
    _check_ints(num_angles=num_angles, patch=patch, grid=grid)
    pos = _check_pos(query_pos, "query_pos", query_crop.shape[1:], patch, query_crop.device)
    dtype = torch.promote_types(query_crop.dtype, target_crops.dtype)
    target_crops = target_crops.to(dtype)
    starts = [patch_grid(n, grid, patch) for n in target_crops.shape[2:]]
    z, y, x = pos.tolist()
    q = F.normalize(query_crop[:, z : z + patch, y : y + patch, x : x + patch].reshape(-1).to(dtype), dim=0)
    k = target_crops.shape[0]
    dev = target_crops.device
    if k == 0:
        empty = torch.zeros(0, dtype=torch.long, device=dev)
        return empty, empty.view(0, 3), torch.zeros(0, dtype=dtype, device=dev)
    ok = allowed_yaws is None or isinstance(allowed_yaws, Tensor) and allowed_yaws.dtype == torch.bool
    if not ok or allowed_yaws is not None and (allowed_yaws.shape != (k, num_angles) or not allowed_yaws.any(1).all()):
        got = _desc(allowed_yaws)
        raise ValueError(f"allowed_yaws must be a bool tensor [{k}, {num_angles}] with a True in every row, got {got}")
    if allowed_yaws is not None and bool(allowed_yaws.all()):
        allowed_yaws = None  # every yaw allowed: the shared path (one sampling grid for all targets) is faster
    angles = yaw_angles(num_angles, device=dev, dtype=dtype)
    # The yaws searched per target, ascending: all, or only the allowed ones (rows padded with their first allowed
    # yaw, which cannot win a tie against itself listed earlier).
    if allowed_yaws is None:
        yaw_table = torch.arange(num_angles, device=dev).expand(k, -1)
    else:
        allowed = allowed_yaws.to(dev)
        width = int(allowed.sum(dim=1).max())
        order = torch.sort((~allowed).to(torch.int8), dim=1, stable=True).indices[:, :width]  # allowed first, ascending
        first = order[:, :1].expand(-1, width)
        yaw_table = torch.where(torch.gather(allowed, 1, order), order, first)
    n_grid = math.prod(len(s) for s in starts)
    per_target = yaw_table.shape[1] * n_grid * q.numel() * 2  # samples + normalised copy
    chunk = max(1, _CHUNK_FLOATS // per_target)
    best = []
    for i in range(0, k, chunk):
        t_angles = angles if allowed_yaws is None else angles[yaw_table[i : i + chunk]]
        feats = F.normalize(_rotated_grid_patches(target_crops[i : i + chunk], t_angles, starts, patch), dim=-1)
        best.append((feats @ q).flatten(1).max(dim=1))  # over [k_i, A' * G]
    cosine, flat = torch.cat([b.values for b in best]), torch.cat([b.indices for b in best])
    yaw = torch.gather(yaw_table, 1, (flat // n_grid)[:, None])[:, 0]
    gi = torch.unravel_index(flat % n_grid, tuple(len(s) for s in starts))
    best_pos = torch.stack([torch.tensor(s, dtype=torch.long, device=dev)[i] for s, i in zip(starts, gi)], dim=-1)
    return yaw, best_pos, cosine


def _verify_batch(query_crops: Tensor, query_pos: Tensor, target_crops: Tensor, target_pos: Tensor, yaw: Tensor,
                  num_angles: int, patch: int, context_distance: int, min_cosine: float,
                  search_radius: int) -> tuple[Tensor, Tensor]:
    """Batched :func:`verify_match`: scores ``[P]`` and the number of context patches used ``[P]``."""
    p_count = query_crops.shape[0]
    dev = query_crops.device
    if p_count == 0:
        return torch.zeros(0, dtype=query_crops.dtype, device=dev), torch.zeros(0, dtype=torch.long, device=dev)
    qsize, tsize = query_crops.shape[2:], target_crops.shape[2:]
    hi_q, hi_t = (torch.tensor([n - patch for n in size], device=dev) for size in (qsize, tsize))
    offsets = context_offsets(context_distance, dev)  # [D, 3]
    r = torch.arange(-search_radius, search_radius + 1, device=dev)
    near = torch.stack(torch.meshgrid(r, r, r, indexing="ij"), dim=-1).reshape(-1, 3)  # [E, 3]
    feat = query_crops.shape[1] * patch**3
    per_pair = offsets.shape[0] * (near.shape[0] + 1) * feat * 3
    chunk = max(1, _CHUNK_FLOATS // per_pair)
    angles = yaw_angles(num_angles, device=dev, dtype=query_crops.dtype)[yaw]  # as match_patch's
    scores, counts = [], []
    for i in range(0, p_count, chunk):
        sl = slice(i, i + chunk)
        aligned = rotate_yaw(target_crops[sl], angles[sl])  # [P, C, Z, Y, X]
        ones = target_crops.new_ones(aligned.shape[0], 1, *tsize)
        coverage = -F.max_pool3d(-rotate_yaw(ones, angles[sl]), patch, stride=1)[:, 0]  # min over each patch
        qc = query_pos[sl, None] + offsets  # [P, D, 3]
        tc = target_pos[sl, None] + offsets
        ok_q, ok_t = _inside(qc, qsize, patch), _inside(tc, tsize, patch)
        tcc = torch.minimum(tc.clamp(min=0), hi_t)
        rows = torch.arange(aligned.shape[0], device=dev)[:, None]
        ok_t &= coverage[rows, tcc[..., 0], tcc[..., 1], tcc[..., 2]] >= _MIN_COVERAGE
        used = ok_q & ok_t  # [P, D]
        qv = F.normalize(_gather_patches(query_crops[sl], torch.minimum(qc.clamp(min=0), hi_q), patch), dim=-1)
        cand = tc[:, :, None] + near  # [P, D, E, 3]
        ok_c = _inside(cand, tsize, patch)
        tv = F.normalize(_gather_patches(aligned, torch.minimum(cand.clamp(min=0), hi_t), patch), dim=-1)
        cos = torch.einsum("pdef,pdf->pde", tv, qv).masked_fill(~ok_c, float("-inf"))
        found = (cos.max(dim=-1).values >= min_cosine) & used
        n_used = used.sum(dim=1)
        scores.append(torch.where(n_used > 0, found.sum(dim=1).to(cos.dtype) / n_used.clamp(min=1), 0.0))
        counts.append(n_used)
    return torch.cat(scores), torch.cat(counts)


@torch.no_grad()
def verify_match(query_crop: Tensor, query_pos: Sequence[int] | Tensor, target_crop: Tensor,
                 target_pos: Sequence[int] | Tensor, yaw_index: int, num_angles: int = 36, patch: int = 2,
                 context_distance: int = 6, *, min_cosine: float = 0.5, search_radius: int = 1) -> Tensor:
    """Spatial-consistency score of a patch match: the fraction of the query's context patches found again.

    The context patches are those at every offset ``d`` of :func:`context_offsets` from the query patch. In the
    target rotated by the match's yaw, context patch ``d`` is expected at ``target_pos + d``; the best cosine over
    the ``(2 search_radius + 1)^3`` positions around it (those inside the crop) is taken. A context patch counts
    only if it lies inside the query crop and its expected place lies inside the target crop, in the part that
    the rotation filled (every voxel at least half from inside the unrotated crop).

    Rule: ``score = #{used context patches with best cosine >= min_cosine} / #{used}``; 0 when none is used.

    Args:
        query_crop: ``[C, Z, Y, X]`` query features.
        query_pos: ``(z, y, x)`` of the query patch.
        target_crop: ``[C, Z, Y, X]`` target features (unrotated).
        target_pos: ``(z, y, x)`` of the match in the ALIGNED target (as returned by :func:`match_patch`).
        yaw_index: the match's yaw index (rotates the target onto the query).
        num_angles: yaw candidates ``A``.
        patch: patch edge in voxels.
        context_distance: Manhattan distance of the context patches.
        min_cosine: a context patch is found when its best cosine reaches this.
        search_radius: voxels searched around each expected place, per axis.

    Returns:
        Scalar score in ``[0, 1]``.

    Convention:
        ``rotate_yaw(target_crop, 2 pi yaw_index / A)`` is aligned with the query (see the module docstring).
    """
    query_crop = _check_volume(query_crop, "query_crop", 4)
    target_crop = _check_volume(target_crop, "target_crop", 4)
    if target_crop.shape[0] != query_crop.shape[0]:
        raise ValueError(f"target_crop must have C={query_crop.shape[0]} channels, got {target_crop.shape[0]}")
    _check_ints(num_angles=num_angles, patch=patch, context_distance=context_distance)
    _check_int("search_radius", search_radius, 0)
    if isinstance(yaw_index, Tensor) and yaw_index.numel() == 1 and not yaw_index.is_floating_point():
        yaw_index = int(yaw_index)
    if isinstance(yaw_index, bool) or not isinstance(yaw_index, int) or not 0 <= yaw_index < num_angles:
        raise ValueError(f"yaw_index must be an int in [0, {num_angles}), got {yaw_index!r}")
    _check_unit("min_cosine", min_cosine, -1.0)
    dev = query_crop.device
    qp = _check_pos(query_pos, "query_pos", query_crop.shape[1:], patch, dev)
    tp = _check_pos(target_pos, "target_pos", target_crop.shape[1:], patch, dev)
    dtype = torch.promote_types(query_crop.dtype, target_crop.dtype)
    yaw, args = torch.tensor([yaw_index], device=dev), (num_angles, patch, context_distance, float(min_cosine))
    return _verify_batch(query_crop[None].to(dtype), qp[None], target_crop[None].to(dtype), tp[None], yaw, *args,
                         search_radius)[0][0]


def salient_positions(crops: Tensor, candidates: Tensor | None = None, patch: int = 2) -> Tensor:
    """The most salient patch of each crop: lowest mean cosine of its voxels to the crop's mean feature.

    Saliency of a voxel: ``cos(f_v, mean_u f_u / |f_u|)`` (an all-zero voxel has cosine 0); of a patch: the mean
    over its ``patch^3`` voxels.

    Args:
        crops: ``[N, C, Z, Y, X]``.
        candidates: optional ``[G, 3]`` long positions to choose from (default: every position).
        patch: patch edge in voxels.

    Returns:
        ``[N, 3]`` long positions ``(z, y, x)``.
    """
    crops = _check_volume(crops, "crops", 5)
    _check_int("patch", patch)
    unit = F.normalize(crops, dim=1)
    mean = F.normalize(unit.mean(dim=(2, 3, 4)), dim=1)  # [N, C]
    cos = torch.einsum("nczyx,nc->nzyx", unit, mean)
    pooled = F.avg_pool3d(cos[:, None], patch, stride=1)[:, 0]  # [N, Z', Y', X']
    if candidates is None:
        zz, yy, xx = (torch.arange(n, device=crops.device) for n in pooled.shape[1:])
        candidates = torch.stack(torch.meshgrid(zz, yy, xx, indexing="ij"), dim=-1).reshape(-1, 3)
    elif candidates.ndim != 2 or candidates.shape[1] != 3 or candidates.shape[0] == 0:
        raise ValueError(f"candidates must have shape [G, 3] with G >= 1, got {tuple(candidates.shape)}")
    elif not _inside(candidates, crops.shape[2:], patch).all():
        raise ValueError("candidates must be patch positions inside the crops")
    vals = pooled[:, candidates[:, 0], candidates[:, 1], candidates[:, 2]]  # [N, G]
    return candidates[vals.argmin(dim=1)]


@torch.no_grad()
def calibrate_context_cosine(crops: Tensor, scene: Tensor, quantile: float = 0.95, patch: int = 2, pairs: int = 2048,
                             generator: torch.Generator | None = None) -> float:
    """A ``min_cosine`` for :func:`verify_match` that does not saturate: the ``quantile`` quantile, over ``pairs``
    random patch pairs from crops of different scenes, of the best cosine within +-1 voxel of the second patch.
    0.5 if no two crops come from different scenes.

    Args:
        crops: ``[N, C, S, S, S]``; scene: ``[N]`` scene id of each crop.
        quantile: in (0, 1).
        patch: patch edge in voxels.
        pairs: random pairs drawn (those within one scene are dropped).
        generator: torch generator of the draw (CPU).
    """
    crops = _check_volume(crops, "crops", 5)
    _check_int("patch", patch)
    if not 0.0 < quantile < 1.0:
        raise ValueError(f"quantile must be in (0, 1), got {quantile!r}")
    n, s = crops.shape[0], crops.shape[-1]
    a = torch.randint(0, n, (pairs,), generator=generator)
    b = torch.randint(0, n, (pairs,), generator=generator)
    keep = scene.cpu()[a] != scene.cpu()[b]
    a, b = a[keep], b[keep]
    if a.numel() == 0:
        return 0.5
    pa = torch.randint(0, s - patch + 1, (a.numel(), 3), generator=generator)
    pb = torch.randint(1, s - patch, (a.numel(), 3), generator=generator)  # room for the +-1 neighbourhood
    off = _patch_voxels(patch, torch.device("cpu"))  # [p^3, 3]
    near = torch.stack(torch.meshgrid(*[torch.arange(-1, 2)] * 3, indexing="ij"), dim=-1).reshape(-1, 3)

    def vecs(idx: Tensor, pos: Tensor) -> Tensor:  # pos [m, ..., 3] -> [m, ..., p^3 * C], indexed without copies
        v = (pos[..., None, :] + off).to(crops.device)  # [m, ..., p^3, 3]
        i = idx.view(-1, *([1] * (v.ndim - 2))).expand(v.shape[:-1]).to(crops.device)
        f = crops[i, :, v[..., 0], v[..., 1], v[..., 2]]  # [m, ..., p^3, C]
        return F.normalize(f.flatten(-2).float(), dim=-1)

    cos = torch.einsum("mf,mef->me", vecs(a, pa), vecs(b, pb[:, None] + near)).amax(dim=1)
    return float(cos.float().quantile(quantile))  # einsum gives bf16 under a GPU's autocast; quantile needs float


def _checked_query_positions(query_positions: object, query_crops: Tensor, patch: int) -> Tensor | None:
    """``query_positions`` as a long ``[N, 3]`` tensor on the crops' device, checked to lie inside the crops."""
    if query_positions is None:
        return None
    n, size, qp = query_crops.shape[0], query_crops.shape[2:], query_positions
    if not isinstance(qp, Tensor) or qp.shape != (n, 3) or qp.is_floating_point() or qp.dtype == torch.bool:
        raise ValueError(f"query_positions must be an integer tensor of shape [{n}, 3], got {_desc(qp)}")
    qp = qp.to(device=query_crops.device, dtype=torch.long)
    if not _inside(qp, size, patch).all():
        raise ValueError(f"query_positions must be {patch}^3 patch positions inside crops of size {tuple(size)}")
    return qp


def _default_query_positions(crops: Tensor, patch: int, grid: int, distance: int, min_fraction: float) -> Tensor:
    """Salient positions among the search grid's positions that keep ``min_fraction`` of the context ring inside."""
    size, dev = crops.shape[2:], crops.device
    starts = [torch.tensor(patch_grid(s, grid, patch), device=dev) for s in size]
    cands = torch.stack(torch.meshgrid(*starts, indexing="ij"), dim=-1).reshape(-1, 3)
    frac = _inside(cands[:, None] + context_offsets(distance, dev), size, patch).float().mean(dim=1)
    good = cands[frac >= min_fraction]
    return salient_positions(crops, good if good.shape[0] else cands, patch)


def _match_queries(query_crops: Tensor, target_crops: Tensor, query_positions: Tensor,
                   retrieved: tuple[Tensor, Tensor, Tensor], num_angles: int, patch: int, grid: int,
                   yaw_window: int | None) -> list[tuple[Tensor, ...]]:
    """:func:`match_patch` of each query in its retrieved targets: per query with a target, the rows (query index,
    target index, yaw, aligned position, match cosine, retrieval similarity)."""
    idx, sim, ret_angle = retrieved
    rows = []
    for q in range(query_crops.shape[0]):
        valid = torch.isfinite(sim[q])
        t_idx = idx[q][valid]
        if t_idx.numel() == 0:
            continue
        allowed = None
        if yaw_window is not None:
            b0 = torch.remainder(-ret_angle[q][valid], num_angles)  # [K]: target yaw implied by the retrieval
            d = torch.remainder(torch.arange(num_angles, device=query_crops.device)[None] - b0[:, None], num_angles)
            allowed = torch.minimum(d, num_angles - d) <= yaw_window
        match = match_patch(query_crops[q], query_positions[q], target_crops[t_idx], num_angles, patch, grid, allowed)
        rows.append((torch.full_like(t_idx, q), t_idx, *match, sim[q][valid]))
    return rows


def _verify_pairs(query_crops: Tensor, target_crops: Tensor, pairs: Sequence[Tensor],
                  verify_args: tuple[int, int, int, float], keep: int, min_score: float, by_sim: bool) -> Tensor:
    """Verification scores of the pairs ``(qi, ti, yaw, pos, cos, rsim, qpos)``, in chunks of ``_VERIFY_PAIRS``.

    With ``by_sim`` the pairs are verified from the most similar down, only until ``keep`` of them have passed and
    the next pair is strictly less similar: the pairs left unverified (score ``-inf``) could not be kept, so the
    result is the one of verifying them all.
    """
    qi, ti, yaw, pos, cos, rsim, qpos = pairs
    n_pairs = qi.numel()
    dev = query_crops.device
    visit = torch.argsort(rsim, descending=True, stable=True) if by_sim else torch.arange(n_pairs, device=dev)
    score = torch.full_like(cos, float("-inf"))
    passed = 0
    for i in range(0, n_pairs, _VERIFY_PAIRS):
        sl = visit[i : i + _VERIFY_PAIRS]
        tc = target_crops[ti[sl]].to(query_crops.dtype)
        batch = _verify_batch(query_crops[qi[sl]], qpos[sl], tc, pos[sl], yaw[sl], *verify_args, 1)[0]
        score[sl] = batch.to(score.dtype)
        passed += int((score[sl] >= min_score).sum())
        done = i + sl.numel()
        if by_sim and passed >= keep and done < n_pairs and rsim[visit[done]] < rsim[visit[done - 1]]:
            break
    return score


@torch.no_grad()
def mine_correspondences(query_crops: Tensor, target_crops: Tensor, top_k: int = 30, keep: int = 200,
                         num_angles: int = 36, query_positions: Tensor | None = None, *, exclude: Tensor | None = None,
                         patch: int = 2, grid: int = 4, context_distance: int = 6, min_cosine: float = 0.5,
                         min_score: float = 0.5, min_context_fraction: float = 0.9, method: str = "fast",
                         yaw_window: int | None = None, rank_by: str = "score") -> dict[str, Tensor]:
    """Mine verified patch correspondences between query crops and retrieved target crops.

    For each query: retrieve ``top_k`` targets (:func:`retrieve_targets`), match its query patch in each of them
    (:func:`match_patch`), verify every match (:func:`verify_match`), then keep over all queries the ``keep``
    pairs of highest verification score (ties: higher match cosine) among those with score ``>= min_score``.

    Default query patch (``query_positions=None``): :func:`salient_positions` restricted to the positions of
    the search grid (:func:`patch_grid`) at which at least ``min_context_fraction`` of the context ring lies
    inside the crop (all grid positions if none qualifies).

    Args:
        query_crops: ``[N, C, S, S, S]`` query features.
        target_crops: ``[M, C, S, S, S]`` target features.
        top_k: targets retrieved per query.
        keep: most pairs returned.
        num_angles: yaw candidates ``A`` (retrieval and matching).
        query_positions: optional ``[N, 3]`` long query patch positions.
        exclude: optional ``[N, M]`` bool, targets not to retrieve per query (see :func:`retrieve_targets`).
        patch: patch edge in voxels.
        grid: grid positions per axis of the patch search.
        context_distance: Manhattan distance of the context patches.
        min_cosine: cosine at which a context patch counts as found.
        min_score: verification score a pair needs to be kept.
        min_context_fraction: part of the context ring a default query position must keep inside the crop.
        method: retrieval kernel, ``"fast"`` or ``"exact"``.
        yaw_window: search the patch only at yaws within this many steps of the one the object-level retrieval
            found (``b = -angle mod A``); ``None`` searches all ``A`` yaws.
        rank_by: order of the verified pairs before the ``keep`` best are taken: ``"score"`` (verification
            score, ties by match cosine) or ``"retrieval"`` (object-level rotation-max similarity, ties by
            verification score).

    Returns:
        A dict of ``P <= keep`` rows, best first: ``query_index`` ``[P]`` long, ``target_index`` ``[P]`` long,
        ``query_pos`` ``[P, 3]`` long, ``target_pos`` ``[P, 3]`` long (in the UNROTATED target crop, rounded to
        the voxel), ``target_pos_aligned`` ``[P, 3]`` long (in the target rotated by ``yaw``), ``yaw`` ``[P]``
        long, ``match_cosine`` ``[P]``, ``score`` ``[P]`` (verification), ``retrieval_sim`` ``[P]``.

    Convention:
        ``rotate_yaw(target, 2 pi yaw / A)`` aligns the target with the query around the patch (the opposite
        sign of the retrieval angle); positions are patch starts ``(z, y, x)``.
    """
    query_crops = _check_volume(query_crops, "query_crops", 5)
    target_crops = _check_volume(target_crops, "target_crops", 5)
    _check_ints(keep=keep, patch=patch, grid=grid, context_distance=context_distance)
    _check_unit("min_cosine", min_cosine, -1.0)
    _check_unit("min_score", min_score, 0.0)
    _check_unit("min_context_fraction", min_context_fraction, 0.0)
    query_positions = _checked_query_positions(query_positions, query_crops, patch)
    if yaw_window is not None:
        _check_int("yaw_window", yaw_window, minimum=0)
    if rank_by not in ("score", "retrieval"):
        raise ValueError(f"rank_by must be 'score' or 'retrieval', got {rank_by!r}")
    retrieved = retrieve_targets(query_crops, target_crops, top_k, num_angles, exclude, method=method)
    if query_positions is None:
        query_positions = _default_query_positions(query_crops, patch, grid, context_distance, min_context_fraction)
    rows = _match_queries(query_crops, target_crops, query_positions, retrieved, num_angles, patch, grid, yaw_window)
    dev, by_sim = query_crops.device, rank_by == "retrieval"
    if not rows:
        dtypes = {k: torch.long if k in _LONG_KEYS else query_crops.dtype for k in _KEYS}
        return {k: torch.zeros((0, 3) if "pos" in k else (0,), dtype=t, device=dev) for k, t in dtypes.items()}
    qi, ti, yaw, pos, cos, rsim = pairs = tuple(torch.cat(c) for c in zip(*rows))
    qpos = query_positions[qi]
    verify_args = (num_angles, patch, context_distance, float(min_cosine))
    score = _verify_pairs(query_crops, target_crops, (*pairs, qpos), verify_args, keep, min_score, by_sim)
    first, second = (rsim, score) if by_sim else (score, cos)
    order = torch.argsort(second, descending=True, stable=True)
    order = order[torch.argsort(first[order], descending=True, stable=True)]
    order = order[score[order] >= min_score][:keep]
    out = dict(zip(_KEYS, (t[order] for t in (qi, ti, qpos, pos, pos, yaw, cos, score, rsim))))
    yaw_rad = out["yaw"].to(torch.float64) * (2.0 * math.pi / num_angles)
    out["target_pos"] = rotate_patch_positions(out["target_pos_aligned"], -yaw_rad, target_crops.shape[2:], patch)
    return out
