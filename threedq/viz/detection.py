"""Pictures of 3D boxes: detections against the GT, self-labels, objects found per size band.

- :func:`detection_figure`: ``detections.png`` (evaluation, ``threedq.pipeline.detection_eval``),
  ``images/val_detections_step*.png`` (training, ``threedq.stages.detector``);
- :func:`self_labels_figure`: ``labels.png`` of a self-labelling round, by ``threedq.stages.self_labelling``;
- :func:`size_band_figure`: ``detection_by_size.png``, by ``threedq.pipeline.detection_eval``.

Convention: boxes axis-aligned ``(xmin, ymin, zmin, xmax, ymax, zmax)`` in frame R (metres, z up), drawn on a
scene's first input view; images ``[H, W, 3]`` uint8 RGB.
"""

from __future__ import annotations

from typing import Any

import numpy as np
from torch import Tensor

from threedq.data.draw import draw_boxes
from threedq.viz.png import new_figure

__all__ = ["aabb_to_boxes7", "detection_figure", "self_labels_figure", "size_band_figure"]


def aabb_to_boxes7(aabb: np.ndarray) -> np.ndarray:
    """Axis-aligned boxes ``[N, 6]`` as oriented boxes ``[N, 7]`` ``(cx, cy, cz, sx, sy, sz, yaw = 0)``."""
    c, s = (aabb[:, :3] + aabb[:, 3:]) / 2, aabb[:, 3:] - aabb[:, :3]
    return np.concatenate([c, s, np.zeros((len(aabb), 1))], axis=1)


def detection_figure(batch: dict[str, Any], dets: list[dict[str, Tensor]], max_scenes: int = 4,
                     upscale: int = 3) -> np.ndarray:
    """Rows of (detections with scores | GT boxes) projected onto each scene's first input view: ``[H', W', 3]`` uint8
    RGB.

    Args:
        batch: a SceneDataset batch (``rgb``, ``K``, ``R_T_cam``, ``gt_aabb``, ``gt_mask``).
        dets: per scene ``{"boxes": [P, 6], "scores": [P]}``.
    """
    rows = []
    for i in range(min(max_scenes, len(dets))):
        rgb = (batch["rgb"][i, 0].permute(1, 2, 0).cpu().numpy() * 255).round().astype(np.uint8)
        K, pose = batch["K"][i, 0].cpu().numpy(), batch["R_T_cam"][i, 0].cpu().numpy()
        db = dets[i]["boxes"].cpu().numpy().astype(np.float64)
        ds = dets[i]["scores"].cpu().numpy().tolist()
        gt = batch["gt_aabb"][i][batch["gt_mask"][i]].cpu().numpy().astype(np.float64)
        left = draw_boxes(rgb, aabb_to_boxes7(db), ["det"] * len(db), K, pose, scores=ds, colour=(255, 80, 40),
                          upscale=upscale, heading=False)  # fmt: skip
        right = draw_boxes(rgb, aabb_to_boxes7(gt), ["GT"] * len(gt), K, pose, colour=(40, 220, 80),
                           upscale=upscale, heading=False)  # fmt: skip
        sep = np.full((left.shape[0], 4, 3), 255, np.uint8)
        rows.append(np.concatenate([left, sep, right], axis=1))
    gap = np.full((4, rows[0].shape[1], 3), 255, np.uint8)
    return np.concatenate([r for row in rows for r in (row, gap)][:-1], axis=0)


def self_labels_figure(scenes: list[tuple[dict[str, Tensor], Tensor]], upscale: int = 3) -> np.ndarray:
    """Labelled candidates on each scene's first input view, positives green, negatives red: ``[H', W', 3]`` uint8 RGB
    (the scenes side by side).

    Args:
        scenes: per scene (``{"rgb": [S,3,H,W], "K": [S,3,3], "R_T_cam": [S,4,4]}``, rows ``[L, 7]`` = kind
            (1 positive, 0 negative) + aabb).
    """
    tiles = []
    for sample, rows in scenes:
        rgb = (sample["rgb"][0].permute(1, 2, 0).cpu().numpy() * 255).round().astype(np.uint8)
        K, pose = sample["K"][0].cpu().numpy(), sample["R_T_cam"][0].cpu().numpy()
        rows = rows.cpu().numpy().astype(np.float64)
        pos = rows[:, 0] > 0.5
        colours = [(40, 220, 80) if p else (230, 40, 40) for p in pos]
        names = ["kept" if p else "pruned" for p in pos]
        tiles.append(draw_boxes(rgb, aabb_to_boxes7(rows[:, 1:]), names, K, pose, colour=colours, upscale=upscale,
                                heading=False))  # fmt: skip
    h = max(t.shape[0] for t in tiles)
    tiles = [np.pad(t, ((0, h - t.shape[0]), (0, 4), (0, 0)), constant_values=255) for t in tiles]
    return np.concatenate(tiles, axis=1)


def size_band_figure(tables: dict[str, list[dict[str, Any]]]) -> Any:
    """A matplotlib ``Figure`` of bars: per size band, the share of objects each box set finds at IoU 0.25 (light) and
    0.5 (dark).

    Args:
        tables: ``{box set name: rows}``, rows of :func:`~threedq.metrics.localisation.by_size_band` (``band``,
            ``objects``, ``found_25``, ``found_50``), the same bands in every set.
    """
    names = list(tables)
    bands = [r["band"] for r in tables[names[0]]]
    fig = new_figure(figsize=(2.2 + 1.6 * len(bands), 3.6), dpi=100)
    ax = fig.add_subplot(1, 1, 1)
    width = 0.8 / len(names)
    colours = ["#4c72b0", "#dd8452", "#55a868", "#c44e52"]
    for i, name in enumerate(names):
        x = np.arange(len(bands)) + (i - (len(names) - 1) / 2) * width
        c = colours[i % len(colours)]
        ax.bar(x, np.nan_to_num([r["found_25"] for r in tables[name]]), width * 0.95, color=c, alpha=0.35)
        ax.bar(x, np.nan_to_num([r["found_50"] for r in tables[name]]), width * 0.95, color=c, label=name)
    ax.set_xticks(np.arange(len(bands)))
    ax.set_xticklabels([f"{b}\n({r['objects']} obj.)" for b, r in zip(bands, tables[names[0]])], fontsize=8)
    ax.set_ylim(0, 1)
    ax.set_ylabel("objects found (dark: IoU 0.5, light: 0.25)", fontsize=8)
    ax.set_title("objects found per size (largest extent of the GT box), test split", fontsize=9)
    ax.legend(fontsize=7, loc="upper left")
    return fig
