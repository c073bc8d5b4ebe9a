"""What a mined pair teaches: the positives of one pair of objects, as query cells and their keys.

Two kinds, chosen by the mining stage's ``positives``: ``patches`` (the paper's; the 8 corners of a cube around the
verified patch match, each keyed by its best match in the target turned onto the query, :func:`patch_positives`) and
``occupancy`` (the pairs whose input occupancy agrees best, positives at cells both objects occupy at that yaw,
:func:`occupancy_positives`).

Convention: crops ``[N, C, Z, Y, X]``; yaw about the crop's vertical axis through its centre, counter-clockwise seen
from above, step ``b`` meaning ``2 pi b / num_angles``; a pair's yaw rotates the TARGET crop onto the query.
"""

from __future__ import annotations

import math
from typing import Any

import torch
import torch.nn.functional as F
from torch import Tensor

from threedq.geometry import rotate_yaw

__all__ = ["corner_keys", "corner_offsets", "crop_voxels", "occupancy_positives", "patch_positives",
           "shape_agreement", "shape_cells", "take_pairs"]


def take_pairs(mined: dict[str, Any], idx: Tensor) -> dict[str, Any]:
    """The pairs ``idx`` of a :func:`~threedq.contrastive.mine_correspondences` result (its per-pair ``[P, ...]``
    tensors indexed, the rest kept)."""
    n = mined["query_index"].shape[0]
    return {k: v[idx] if isinstance(v, Tensor) and v.shape[:1] == (n,) else v for k, v in mined.items()}


def corner_offsets(corner_offset: int = 4, patch: int = 2, device: torch.device | str | None = None) -> Tensor:
    """``[8, 3]`` long ``(dz, dy, dx)`` offsets from a patch start to the corners of a cube centred on the patch:
    ``patch // 2 - corner_offset`` and ``patch // 2 + corner_offset - 1`` per axis."""
    lo, hi = patch // 2 - corner_offset, patch // 2 + corner_offset - 1
    vals = torch.tensor([lo, hi], device=device)
    return torch.cartesian_prod(vals, vals, vals)


def corner_keys(
    query_crop: Tensor, query_pos: Tensor, target_aligned: Tensor, target_pos_aligned: Tensor,
    offsets: Tensor, search: int = 1,
) -> tuple[Tensor, Tensor]:
    """Hard positives of one verified match: query corners and their best matches in the aligned target.

    Args:
        query_crop: ``[C, S, S, S]``; query_pos: ``[3]`` long patch start of the match in the query.
        target_aligned: ``[C, S, S, S]`` the target rotated onto the query; target_pos_aligned ``[3]`` long.
        offsets: ``[P, 3]`` long, from :func:`corner_offsets`.
        search: the key is the voxel of highest cosine to the query corner within ``+-search`` voxels per axis of
            ``target_pos_aligned + offset``.

    Returns:
        ``query_voxels`` ``[P, 3]`` long (clamped into the crop) and ``keys`` ``[P, C]`` L2-normalised.
    """
    size = torch.tensor(query_crop.shape[1:], device=query_crop.device)
    qv = torch.minimum((query_pos + offsets).clamp_min(0), size - 1)
    expected = target_pos_aligned + offsets  # [P, 3]
    r = torch.arange(-search, search + 1, device=query_crop.device)
    neigh = torch.cartesian_prod(r, r, r)  # [G, 3]
    cand = torch.minimum((expected[:, None] + neigh[None]).clamp_min(0), size - 1)  # [P, G, 3]
    qf = F.normalize(query_crop[:, qv[:, 0], qv[:, 1], qv[:, 2]].T, dim=1)  # [P, C]
    tf = F.normalize(target_aligned[:, cand[..., 0], cand[..., 1], cand[..., 2]].permute(1, 2, 0), dim=2)  # [P, G, C]
    best = torch.einsum("pc,pgc->pg", qf, tf).argmax(dim=1)
    return qv, tf[torch.arange(tf.shape[0]), best]


def shape_agreement(query_occ: Tensor, target_occ: Tensor, num_angles: int, chunk: int = 64
                    ) -> tuple[Tensor, Tensor]:
    """How well each pair's two objects agree in shape: the cosine of the query's occupancy crop with the target's
    rotated onto it, at the yaw where it is highest.

    Args:
        query_occ: ``[P, 1, s, s, s]`` occupancy crops (any non-negative weights); target_occ: the same, pairwise.
        num_angles: yaw steps in a full turn.
        chunk: pairs rotated at once.

    Returns:
        ``cos`` ``[P]`` (0 where a crop is empty) and ``yaw`` ``[P]`` long, the best step ``b`` (ties: the lowest).
    """
    P, A = query_occ.shape[0], num_angles
    cos = query_occ.new_zeros(P)
    yaw = torch.zeros(P, dtype=torch.long, device=query_occ.device)
    angles = torch.arange(A, device=query_occ.device, dtype=query_occ.dtype) * (2 * math.pi / A)
    for s in range(0, P, chunk):
        q = F.normalize(query_occ[s:s + chunk].flatten(1), dim=1)  # [n, V]
        t = rotate_yaw(target_occ[s:s + chunk], angles.expand(q.shape[0], A))  # [n, A, 1, s, s, s]
        t = F.normalize(t.flatten(2), dim=2)  # [n, A, V]
        c = torch.einsum("nv,nav->na", q, t)
        cos[s:s + chunk], yaw[s:s + chunk] = c.max(dim=1)
    return cos, yaw


def shape_cells(query_occ: Tensor, target_occ_aligned: Tensor, count: int,
                generator: torch.Generator | None = None) -> tuple[Tensor, Tensor]:
    """``count`` cells per pair drawn where both objects have input occupancy once the target is turned onto the query
    (weight: the product of the two).

    Args:
        query_occ: ``[P, 1, s, s, s]``; target_occ_aligned: ``[P, 1, s, s, s]`` the target's, rotated onto the query.
        count: cells per pair, drawn without replacement.
        generator: the draw's generator (CPU).

    Returns:
        ``cells`` ``[P', count]`` long flat indices ``z * s * s + y * s + x`` and ``valid`` ``[P]`` bool, the pairs
        with at least ``count`` shared cells (the ``P'`` returned, in order).
    """
    w = (query_occ * target_occ_aligned).flatten(1).clamp_min(0)  # [P, s^3]
    valid = (w > 0).sum(dim=1) >= count
    if not valid.any():
        return w.new_zeros(0, count, dtype=torch.long), valid
    return torch.multinomial(w[valid].float().cpu(), count, replacement=False, generator=generator).to(w.device), valid


def crop_voxels(crops: Tensor, idx: Tensor) -> Tensor:
    """The L2-normalised features ``[N, V, C]`` of crops ``[N, C, s, s, s]`` at flat cell indices ``idx`` ``[N, V]``
    (row-major over ``(z, y, x)``, i.e. ``z * s * s + y * s + x``)."""
    flat = crops.flatten(2)  # [N, C, s^3]
    return F.normalize(flat.gather(2, idx[:, None].expand(-1, flat.shape[1], -1)).transpose(1, 2), dim=2)


def patch_positives(feats: Tensor, mined: dict[str, Tensor], offsets: Tensor, search: int, num_angles: int
                    ) -> tuple[Tensor, Tensor]:
    """``positives: patches``: each pair's query corners around its patch match and their keys (:func:`corner_keys`).

    Args:
        feats: ``[N, C, S, S, S]`` the pool's feature crops; mined: the pairs (``query_index``, ``target_index``,
            ``yaw``, ``query_pos``, ``target_pos_aligned``); offsets: ``[8, 3]`` (:func:`corner_offsets`);
            search: :func:`corner_keys`' ``search``; num_angles: yaw steps in a full turn.

    Returns:
        ``query_voxels`` ``[P, 8, 3]`` long and ``keys`` ``[P, 8, C]`` L2-normalised.
    """
    qi, ti, yaw = mined["query_index"], mined["target_index"], mined["yaw"]
    P = qi.numel()
    if not P:
        return offsets.new_zeros(0, 8, 3), feats.new_zeros(0, 8, feats.shape[1])
    aligned = rotate_yaw(feats[ti], yaw.to(feats.dtype) * (2 * math.pi / num_angles))  # [P, C, S, S, S]
    vox, keys = zip(*(corner_keys(feats[qi[j]], mined["query_pos"][j], aligned[j], mined["target_pos_aligned"][j],
                                  offsets, search) for j in range(P)))
    return torch.stack(vox), torch.stack(keys)


def occupancy_positives(feats: Tensor, occ: Tensor, mined: dict[str, Tensor], count: int, keep: int, num_angles: int,
                        generator: torch.Generator | None = None) -> tuple[dict[str, Tensor], Tensor, Tensor]:
    """``positives: occupancy``: the ``keep`` pairs whose input occupancy agrees best (:func:`shape_agreement`), at
    that yaw, and ``count`` positives per pair where both are occupied (:func:`shape_cells`).

    Args:
        feats: ``[N, C, s, s, s]`` the pool's feature crops; occ: ``[N, 1, s, s, s]`` their input occupancy;
        mined: the candidate pairs, best first; count: positives per pair; keep: pairs kept;
        num_angles: yaw steps in a full turn; generator: the cells' draw (CPU).

    Returns:
        The kept pairs (``yaw`` replaced, ``shape_cosine`` added, ``query_pos`` and ``target_pos_aligned`` one
        positive cell), their query cells ``[P, count, 3]`` long and keys ``[P, count, C]`` L2-normalised.
    """
    qi, ti = mined["query_index"], mined["target_index"]
    cos, yaw = shape_agreement(occ[qi], occ[ti], num_angles)
    order = torch.sort(cos, descending=True, stable=True).indices
    t_occ = rotate_yaw(occ[ti[order]], yaw[order].to(occ.dtype) * (2 * math.pi / num_angles))
    cells, valid = shape_cells(occ[qi[order]], t_occ, count, generator)
    order = order[valid]
    pick, cells = order[:keep], cells[:keep]
    aligned = rotate_yaw(feats[ti[pick]], yaw[pick].to(feats.dtype) * (2 * math.pi / num_angles))
    keys = crop_voxels(aligned, cells)  # [P, count, C]
    vox = torch.stack(torch.unravel_index(cells, occ.shape[2:]), dim=-1)  # [P, count, 3]
    out = take_pairs(mined, pick)
    out["yaw"], out["shape_cosine"] = yaw[pick], cos[pick]
    out["query_pos"], out["target_pos_aligned"] = vox[:, 0], vox[:, 0]
    return out, vox, keys
