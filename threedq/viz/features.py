"""Pictures of the learned 3D features: view prediction, mined correspondences, retrieval and rotational alignment.

- :func:`view_prediction_figure`: ``images/*_step*.png`` of view prediction (input, predicted and true target view,
  occupancy), written by ``threedq.stages.viewpred``;
- :func:`mined_pairs_figure`: ``mining/refresh_*.png`` (mined pairs, matched patch boxed), by ``threedq.stages.mining``;
- :func:`retrieval_figure`: ``retrieval.png`` (queries and their nearest objects), by ``threedq eval``
  (``threedq.pipeline.report``);
- :func:`alignment_figure`: ``prototype_alignment.png`` (a prototype's members before / after rotation), and
  :func:`per_category_figure`: ``per_category_retrieval.png``, both by ``threedq eval``.

Convention: crops are ``[4, S, S, S]`` raw ``(occ, occ * rgb)`` volumes, drawn as bird's-eye views (x right, y up);
images ``[H, W, 3]`` uint8 RGB (picture grids are drawn with OpenCV); the one plot, :func:`per_category_figure`, is a
matplotlib ``Figure``; both go to :func:`~threedq.viz.png.write_png`.
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

__all__ = ["alignment_figure", "mined_pairs_figure", "per_category_figure", "retrieval_figure",
           "view_prediction_figure"]


def _to_u8(img: Tensor, size: tuple[int, int]) -> np.ndarray:
    a = (img.detach().float().clamp(0, 1).permute(1, 2, 0).cpu().numpy() * 255).round().astype(np.uint8)
    return cv2.resize(a, (size[1], size[0]), interpolation=cv2.INTER_NEAREST)


def view_prediction_figure(input_rgb: Tensor, pred_rgb: Tensor, true_rgb: Tensor, occ_prob: Tensor,
                           occ_true: Tensor) -> np.ndarray:
    """One row ``[H', W', 3]`` uint8 RGB: input view | predicted target | true target | predicted and true occupancy.

    Args:
        input_rgb ``[3, H, W]``, pred_rgb and true_rgb ``[3, h, w]`` in [0, 1]; occ_prob, occ_true ``[Z, Y, X]``.
        Occupancy is shown as a bird's-eye view: the max over the upper 70% of z (above the ground of the embedded
        scenes, which sits at 25% of the grid height), x to the right, y up.
    """
    H, W = input_rgb.shape[-2:]
    tiles = [_to_u8(img, (H, W)) for img in (input_rgb, pred_rgb, true_rgb)]
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
    """Rows of mined pairs, ``[H, W, 3]`` uint8 RGB: query (bird's-eye view) | target rotated onto the query, matched
    patch boxed in red.

    Args:
        query_raw, target_raw_aligned: ``[P, 4, S, S, S]`` raw crops (target already rotated by the mined yaw).
        query_pos, target_pos_aligned: ``[P, 3]`` long patch starts ``(z, y, x)``.
        captions: one line of text per pair.
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


_FONT = cv2.FONT_HERSHEY_SIMPLEX
_RED, _BLACK, _WHITE = (200, 0, 0), (0, 0, 0), 255


def _text_bar(text: str, width: int, height: int = 16, scale: float = 0.35, color: tuple[int, int, int] = _BLACK
              ) -> np.ndarray:
    """A white ``[height, width, 3]`` bar with ``text`` drawn left-aligned, cut to the width (uint8 RGB)."""
    bar = np.full((height, width, 3), _WHITE, np.uint8)
    while text and cv2.getTextSize(text, _FONT, scale, 1)[0][0] > width - 4:
        text = text[:-1]
    cv2.putText(bar, text, (2, height - 5), _FONT, scale, color, 1, cv2.LINE_AA)
    return bar


def _mosaic(rows: list[tuple[str | None, list[tuple[Tensor, str, tuple[int, int, int]]]]], cols: int, side: int,
            scale: int, title: str) -> np.ndarray:
    """``[H, W, 3]`` uint8 RGB: rows of captioned bird's-eye views under a title; a row may have its own heading and
    fewer than ``cols`` tiles (the rest left blank).

    Args:
        rows: ``(heading or None, [(raw crop [4, S, S, S], caption, RGB colour of the caption)])``.
        cols: tiles per row. side: ``S``. scale: pixels per voxel.
    """
    gap, tile = 4, side * scale
    width = cols * tile + (cols - 1) * gap
    parts = [_text_bar(title, width, height=20, scale=0.4)]
    for heading, cells in rows:
        if heading is not None:
            parts.append(_text_bar(heading, width, scale=0.38))
        row = np.full((16 + tile, width, 3), _WHITE, np.uint8)
        for c, (raw, caption, color) in enumerate(cells[:cols]):
            x = c * (tile + gap)
            row[:16, x:x + tile] = _text_bar(caption, tile, color=color)
            row[16:, x:x + tile] = _bev(raw, scale)
        parts += [row, np.full((gap, width, 3), _WHITE, np.uint8)]
    return np.concatenate(parts[:-1] if len(parts) > 1 else parts, axis=0)


def retrieval_figure(test: dict[str, Tensor], sim: Tensor, categories: list[str], queries: int = 6, k: int = 5,
                     scale: int = 6) -> np.ndarray:
    """Query objects (left) and their top-k rotation-max neighbours (bird's-eye views of raw crops), each captioned
    with its category, red where it differs from the query's.

    Args:
        test: ``{"raw": [N, 4, S, S, S], "labels": [N]}``. sim: ``[N, N]`` rotation-max similarities.
        scale: pixels per voxel of the pictures.

    Returns:
        ``[H, W, 3]`` uint8 RGB: a title bar, then one row per query: ``k + 1`` tiles of a 16-pixel caption over the
        ``S * scale`` square picture, 4 pixels apart.
    """
    sim = sim.clone()
    sim.fill_diagonal_(-math.inf)
    n = sim.shape[0]
    k = min(k, n - 1)  # a small split: as many neighbours as there are
    picks = torch.linspace(0, n - 1, steps=min(queries, n)).long()
    rows = []
    for q in picks.tolist():
        nn_idx = sim[q].topk(k).indices.tolist()
        cells = []
        for c, i in enumerate([q, *nn_idx]):
            same = c == 0 or int(test["labels"][i]) == int(test["labels"][q])
            cells.append((test["raw"][i], ("query: " if c == 0 else "") + categories[int(test["labels"][i])],
                          _BLACK if same else _RED))
        rows.append((None, cells))
    return _mosaic(rows, k + 1, test["raw"].shape[-1], scale,
                   f"Retrieval with learned features: query and top-{k} (red = other category)")


def alignment_figure(test: dict[str, Tensor], clusters: Tensor, angles: Tensor, num_angles: int, categories: list[str],
                     rows: int = 4, cols: int = 6, scale: int = 6) -> np.ndarray:
    """Members of the largest prototypes before (as seen) and after rotation to the canonical yaw, bird's-eye views
    captioned with their categories.

    Args:
        test: ``{"raw": [N, 4, S, S, S], "labels": [N]}``. clusters, angles: ``[N]`` prototype and yaw index of each
            object. num_angles: yaw steps of the search. categories: label names. scale: pixels per voxel.

    Returns:
        ``[H, W, 3]`` uint8 RGB: a title bar, then per prototype two headed rows (as seen, aligned) of up to
        ``cols`` members.
    """
    counts = torch.bincount(clusters)
    top = counts.argsort(descending=True)[:rows]
    top = top[counts[top] > 0]
    yaw = yaw_angles(num_angles)
    out = []
    for k in top.tolist():
        members = (clusters == k).nonzero().flatten()[:cols]
        raw = test["raw"][members]
        aligned = rotate_yaw(raw, yaw[angles[members]])
        names = [categories[int(test["labels"][m])] for m in members]
        for vols, tag in ((raw, "as seen"), (aligned, "aligned")):
            out.append((f"prototype {k} ({tag})", [(v, name, _BLACK) for v, name in zip(vols, names)]))
    return _mosaic(out, cols, test["raw"].shape[-1], scale,
                   "Rotational alignment: members of a prototype (bird's-eye view), before and after rotation")


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
    sizes = [int(category_sizes[c]) for c in present]
    ax.plot([min(k, n - 1) / k for n in sizes], y - 0.2, "k|", ms=7, label="ceiling, strict (category size)")
    if "paper" in curves:
        ax.plot([min(k, n) / k for n in sizes], y + 0.2, "r|", ms=7, label="ceiling, paper")
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

