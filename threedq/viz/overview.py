"""The README's overview picture: a scene with its detected boxes, each labelled with the prototype it falls into,
beside other objects each prototype holds (:func:`prototype_overview`; composed from a run folder by
:func:`threedq.pipeline.results_pages.overview_figure`).

Convention: boxes axis-aligned ``(xmin, ymin, zmin, xmax, ymax, zmax)`` in the world frame (frame R), metres, z up;
``K`` pinhole intrinsics, ``world_T_cam`` camera-to-world (OpenCV camera axes); images ``[H, W, 3]`` uint8 RGB.
"""

from __future__ import annotations

from collections.abc import Sequence

import cv2
import numpy as np

from threedq.data.draw import distinct_colour, draw_boxes
from threedq.viz.detection import aabb_to_boxes7

__all__ = ["box_tile", "prototype_overview"]


def box_tile(rgb: np.ndarray, K: np.ndarray, world_T_cam: np.ndarray, aabb: Sequence[float], side: int = 104,
             pad: float = 0.15) -> np.ndarray:
    """The image region of a 3D box (the bounding rectangle of its projected corners, ``pad`` of its size added),
    scaled into a white ``side`` x ``side`` tile."""
    a = np.asarray(aabb, np.float64)
    corners = np.array([[x, y, z, 1.0] for x in a[[0, 3]] for y in a[[1, 4]] for z in a[[2, 5]]])
    cam = (np.linalg.inv(np.asarray(world_T_cam, np.float64)) @ corners.T)[:3]
    uv = (np.asarray(K, np.float64) @ cam)[:2] / np.maximum(cam[2], 1e-3)
    (u0, v0), (u1, v1) = uv.min(1), uv.max(1)
    margin = pad * max(u1 - u0, v1 - v0)
    h, w = rgb.shape[:2]
    u0, v0 = int(np.clip(u0 - margin, 0, w - 1)), int(np.clip(v0 - margin, 0, h - 1))
    u1, v1 = int(np.clip(u1 + margin + 1, u0 + 1, w)), int(np.clip(v1 + margin + 1, v0 + 1, h))
    crop = rgb[v0:v1, u0:u1]
    s = side / max(crop.shape[:2])
    crop = cv2.resize(crop, (max(1, round(crop.shape[1] * s)), max(1, round(crop.shape[0] * s))),
                      interpolation=cv2.INTER_NEAREST)
    tile = np.full((side, side, 3), 255, np.uint8)
    y, x = (side - crop.shape[0]) // 2, (side - crop.shape[1]) // 2
    tile[y:y + crop.shape[0], x:x + crop.shape[1]] = crop
    return tile


def _text(img: np.ndarray, text: str, xy: tuple[int, int], scale: float = 0.45) -> None:
    cv2.putText(img, text, xy, cv2.FONT_HERSHEY_SIMPLEX, scale, (0, 0, 0), 1, cv2.LINE_AA)


def prototype_overview(rgb: np.ndarray, K: np.ndarray, world_T_cam: np.ndarray, boxes: Sequence[Sequence[float]],
                       rows: Sequence[tuple[int, int, Sequence[np.ndarray]]], title: str = "",
                       upscale: int = 3) -> np.ndarray:
    """``[H, W, 3]`` uint8 RGB. Left: the scene with ``boxes`` drawn, box i labelled ``P<prototype>`` of ``rows[i]``;
    right: per box a row of ``(prototype, its number of objects, tiles of other objects it holds)`` in its colour."""
    colours = [distinct_colour(j) for j in range(len(rows))]
    left = draw_boxes(rgb, aabb_to_boxes7(np.asarray(boxes, np.float64).reshape(-1, 6)),
                      [f"P{p}" for p, _, _ in rows], np.asarray(K, np.float64), np.asarray(world_T_cam, np.float64),
                      colour=colours, upscale=upscale, heading=False, font_scale=0.6)
    H = left.shape[0]
    row_h = H // max(3, len(rows))
    side = row_h - 24
    most = max([len(t) for _, _, t in rows] + [1])
    right_rows = []
    for (proto, count, tiles), colour in zip(rows, colours):
        row = np.full((row_h, max(460, 10 + most * (side + 6)), 3), 255, np.uint8)
        cv2.rectangle(row, (0, 0), (5, row_h - 1), colour, -1)
        _text(row, f"prototype P{proto}: {count} test objects; {len(tiles)} others of them", (10, 16))
        for j, t in enumerate(tiles):
            t = cv2.resize(t, (side, side), interpolation=cv2.INTER_NEAREST) if t.shape[0] != side else t
            row[22:22 + side, 10 + j * (side + 6):10 + j * (side + 6) + side] = t
        right_rows.append(row)
    right = np.concatenate(right_rows, axis=0) if right_rows else np.full((H, 460, 3), 255, np.uint8)
    right = np.pad(right, ((0, max(0, H - right.shape[0])), (0, 0), (0, 0)), constant_values=255)[:H]
    img = np.concatenate([left, np.full((H, 12, 3), 255, np.uint8), right], axis=1)
    if title:
        bar = np.full((26, img.shape[1], 3), 255, np.uint8)
        _text(bar, title, (4, 18), 0.5)
        img = np.concatenate([bar, img], axis=0)
    return img
