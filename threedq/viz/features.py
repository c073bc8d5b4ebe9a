"""Pictures of the learned 3D features: view prediction, mined correspondences, retrieval and rotational alignment.

| picture | function | written by |
|---|---|---|
| ``images/*_step*.png`` of view prediction (input, predicted and true target view, occupancy) | :func:`view_prediction_figure` | ``threedq.stages.viewpred`` |
| ``mining/refresh_*.png`` (mined pairs, matched patch boxed) | :func:`mined_pairs_figure` | ``threedq.stages.mining`` |
| ``retrieval.png`` (queries and their nearest objects) | :func:`retrieval_figure` | ``threedq eval`` (``threedq.pipeline.report``) |
| ``prototype_alignment.png`` (a prototype's members before / after rotation) | :func:`alignment_figure` | ``threedq eval`` |
| ``per_category_retrieval.png`` | :func:`per_category_figure` | ``threedq eval`` |

Convention: crops are ``[4, S, S, S]`` raw ``(occ, occ * rgb)`` volumes, drawn as bird's-eye views (x right, y up);
images ``[H, W, 3]`` uint8 RGB; matplotlib pictures are ``Figure`` objects for :func:`~threedq.viz.png.write_png`.
"""

from __future__ import annotations

import math
from typing import Any

import cv2
import numpy as np
import torch
from torch import Tensor

from threedq.data.draw import crop_birds_eye
from threedq.geometry import rotate_yaw, yaw_angles
from threedq.viz.png import new_figure

__all__ = ["alignment_figure", "mined_pairs_figure", "per_category_figure", "retrieval_figure", "view_prediction_figure"]


def _to_u8(img: Tensor, size: tuple[int, int]) -> np.ndarray:
    a = (img.detach().float().clamp(0, 1).permute(1, 2, 0).cpu().numpy() * 255).round().astype(np.uint8)
    return cv2.resize(a, (size[1], size[0]), interpolation=cv2.INTER_NEAREST)


def view_prediction_figure(
    input_rgb: Tensor, pred_rgb: Tensor, true_rgb: Tensor, occ_prob: Tensor, occ_true: Tensor
) -> np.ndarray:
    """One row: input view | predicted target | true target | predicted occupancy | true occupancy.

    Args:
        input_rgb ``[3, H, W]``, pred_rgb and true_rgb ``[3, h, w]`` in [0, 1]; occ_prob, occ_true
        ``[Z, Y, X]``. Occupancy is shown as a bird's-eye view: the max over the upper 70% of z (above
        the ground of the embedded scenes, which sits at 25% of the grid height), x to the right, y up.

    Returns:
        ``[H', W', 3]`` uint8 RGB.
    """
    H, W = input_rgb.shape[-2:]
    tiles = [_to_u8(input_rgb, (H, W)), _to_u8(pred_rgb, (H, W)), _to_u8(true_rgb, (H, W))]
    lo = int(round(0.3 * occ_prob.shape[0]))  # skip the ground slab
    for occ in (occ_prob, occ_true):
        bev = occ[lo:].amax(0).flip(0)  # y up
        tiles.append(_to_u8(bev[None].expand(3, -1, -1), (H, W)))
    sep = np.full((H, 2, 3), 255, np.uint8)
    row = [t for tile in tiles for t in (tile, sep)][:-1]
    return np.concatenate(row, axis=1)


def _bev(raw: Tensor, scale: int) -> np.ndarray:
    """:func:`~threedq.data.draw.crop_birds_eye` of a raw crop as uint8, upscaled ``scale`` times (grey background)."""
    a = (crop_birds_eye(raw, background=0.5) * 255).round().astype(np.uint8)
    return cv2.resize(a, (a.shape[1] * scale, a.shape[0] * scale), interpolation=cv2.INTER_NEAREST)


def mined_pairs_figure(query_raw: Tensor, target_raw_aligned: Tensor, query_pos: Tensor, target_pos_aligned: Tensor,
                       captions: list[str], patch: int = 2, scale: int = 8) -> np.ndarray:
    """Rows of mined pairs: query (bird's-eye view) | target rotated onto the query, matched patch boxed in red.

    Args:
        query_raw, target_raw_aligned: ``[P, 4, S, S, S]`` raw crops (target already rotated by the mined yaw).
        query_pos, target_pos_aligned: ``[P, 3]`` long patch starts ``(z, y, x)``.
        captions: one line of text per pair.

    Returns:
        ``[H, W, 3]`` uint8 RGB.
    """
    rows = []
    for i in range(query_raw.shape[0]):
        tiles = []
        for raw, pos in ((query_raw[i], query_pos[i]), (target_raw_aligned[i], target_pos_aligned[i])):
            img = np.ascontiguousarray(_bev(raw, scale))
            S = raw.shape[-1]
            y0 = (S - int(pos[1]) - patch) * scale  # flipped: y up
            x0 = int(pos[2]) * scale
            cv2.rectangle(img, (x0, y0), (x0 + patch * scale - 1, y0 + patch * scale - 1), (255, 0, 0), 2)
            tiles.append(img)
        h = tiles[0].shape[0]
        row = np.concatenate([tiles[0], np.full((h, 4, 3), 255, np.uint8), tiles[1]], axis=1)
        bar = np.full((18, row.shape[1], 3), 255, np.uint8)
        cv2.putText(bar, captions[i][:40], (2, 13), cv2.FONT_HERSHEY_SIMPLEX, 0.4, (0, 0, 0), 1, cv2.LINE_AA)
        rows.append(np.concatenate([bar, row], axis=0))
    if not rows:
        return np.full((18, 18, 3), 255, np.uint8)
    sep = np.full((4, rows[0].shape[1], 3), 255, np.uint8)
    return np.concatenate([x for r in rows for x in (r, sep)][:-1], axis=0)


def retrieval_figure(test: dict[str, Tensor], sim: Tensor, categories: list[str], queries: int = 6, k: int = 5) -> Any:
    """Query objects (left) and their top-k rotation-max neighbours (bird's-eye views of raw crops).

    Args:
        test: ``{"raw": [N, 4, S, S, S], "labels": [N]}``. sim: ``[N, N]`` rotation-max similarities.
    """
    sim = sim.clone()
    sim.fill_diagonal_(-math.inf)
    n = sim.shape[0]
    k = min(k, n - 1)  # a small split: as many neighbours as there are
    picks = torch.linspace(0, n - 1, steps=min(queries, n)).long()
    fig = new_figure(figsize=(1.3 * (k + 1), 1.4 * len(picks)))
    axes = fig.subplots(len(picks), k + 1, squeeze=False)
    for r, q in enumerate(picks.tolist()):
        nn_idx = sim[q].topk(k).indices.tolist()
        for c, i in enumerate([q, *nn_idx]):
            ax = axes[r, c]
            ax.axis("off")
            ax.imshow(crop_birds_eye(test["raw"][i]))
            same = c == 0 or int(test["labels"][i]) == int(test["labels"][q])
            ax.set_title(("query: " if c == 0 else "") + categories[int(test["labels"][i])], fontsize=5,
                         color="black" if same else "red")
    fig.suptitle(f"Retrieval with learned features: query and top-{k} (red = other category)", fontsize=8)
    return fig


def alignment_figure(test: dict[str, Tensor], clusters: Tensor, angles: Tensor, num_angles: int, categories: list[str],
                     rows: int = 4, cols: int = 6) -> Any:
    """Members of the largest prototypes before (top) and after (bottom) rotation to the canonical yaw.

    Args:
        test: ``{"raw": [N, 4, S, S, S], "labels": [N]}``. clusters, angles: ``[N]`` prototype and yaw index of each
            object. num_angles: yaw steps of the search. categories: label names.
    """
    counts = torch.bincount(clusters)
    top = counts.argsort(descending=True)[:rows]
    top = top[counts[top] > 0]
    rows = max(1, len(top))
    fig = new_figure(figsize=(1.3 * cols, 1.3 * 2 * rows))
    axes = fig.subplots(2 * rows, cols, squeeze=False)
    yaw = yaw_angles(num_angles)
    for r, k in enumerate(top.tolist()):
        members = (clusters == k).nonzero().flatten()[:cols]
        raw = test["raw"][members]
        aligned = rotate_yaw(raw, yaw[angles[members]])
        for c in range(cols):
            for row, vols, tag in ((2 * r, raw, "as seen"), (2 * r + 1, aligned, "aligned")):
                ax = axes[row, c]
                ax.axis("off")
                if c < len(members):
                    ax.imshow(crop_birds_eye(vols[c]))
                    if c == 0:
                        ax.set_title(f"prototype {k} ({tag})", fontsize=6, loc="left")
                    else:
                        ax.set_title(categories[int(test["labels"][members[c]])], fontsize=5)
    fig.suptitle("Rotational alignment: members of a prototype (bird's-eye view), before and after rotation", fontsize=8)
    return fig


def per_category_figure(curves: dict[str, dict[int, float]], category_sizes: Tensor, categories: list[str], k: int,
                        pairs: list[dict[str, Any]]) -> Any:
    """Per-category precision@k under each protocol, with the ceilings the category sizes allow, and the most
    confused category pairs.

    Args:
        curves: ``{"strict" | "paper": {category index: precision@k}}``. category_sizes: ``[C]`` test objects per
            category. categories: names. k: the k of precision@k. pairs: ``[{"a", "b", "slots"}]`` (most confused).
    """
    present = sorted(curves.get("strict", {}))
    fig = new_figure(figsize=(13, 0.18 * len(present) + 1.8))
    ax, ax2 = fig.subplots(1, 2, gridspec_kw={"width_ratios": [2, 1]})
    y = np.arange(len(present))
    for off, (name, cur) in zip((-0.2, 0.2), curves.items()):
        ax.barh(y + off, [cur.get(c, 0.0) for c in present], height=0.4, label=f"{name} protocol")
    n_c = category_sizes
    ax.plot([min(k, int(n_c[c]) - 1) / k for c in present], y - 0.2, "k|", ms=7, label="ceiling, strict (category size)")
    if "paper" in curves:
        ax.plot([min(k, int(n_c[c])) / k for c in present], y + 0.2, "r|", ms=7, label="ceiling, paper")
    ax.set_yticks(y, [categories[c] for c in present], fontsize=6)
    ax.invert_yaxis()
    ax.set_xlim(0, 1)
    ax.set_xlabel(f"precision@{k} (learned features)")
    ax.legend(fontsize=7, loc="lower right")
    ax.set_title("Per-category retrieval precision", fontsize=9)
    ax2.axis("off")
    text = "\n".join(f"{p['a']} <-> {p['b']}: {p['slots']} slots" for p in pairs) or "none"
    ax2.text(0, 1, f"Most confused category pairs\n(top-{k} slots of one held by the other,\nstrict protocol, both "
                   f"directions)\n\n{text}", va="top", fontsize=7, family="monospace")
    return fig

