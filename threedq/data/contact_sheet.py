"""Contact sheets of scene records (``threedq data show``): one row per scene, RGB | depth | instances | GT boxes per
view, as a PNG. The arrays are RGB; only the PNG encode converts to OpenCV's BGR."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import cv2
import numpy as np

from threedq.atomic_io import atomic_write_bytes
from threedq.data.draw import colorize_depth, colorize_instances, distinct_colour, draw_boxes, upscale_nearest
from threedq.scene import SceneRecord, load_index, load_scene

__all__ = ["CAPTION_HEIGHT", "PAD", "TILES_PER_VIEW", "TITLE_HEIGHT", "contact_sheet", "scene_row"]

#: Contact-sheet layout, in output pixels: outer margin and gap between tiles and rows.
PAD = 4
#: Height of the strip holding a row's title (the scene file name).
TITLE_HEIGHT = 20
#: Height of the strip holding the per-tile captions under a row's title.
CAPTION_HEIGHT = 14
#: Tiles drawn per view: RGB, depth, instance mask, RGB with GT boxes.
TILES_PER_VIEW = 4

_FONT = cv2.FONT_HERSHEY_SIMPLEX
_BACKGROUND = 32  # grey level of the contact-sheet background


def _put_text(img: np.ndarray, text: str, org: tuple[int, int], scale: float, colour=(235, 235, 235)) -> None:
    cv2.putText(img, text, org, _FONT, scale, colour, 1, cv2.LINE_AA)


def scene_row(record: SceneRecord, categories: Sequence[str], views: Sequence[int] | None = None, upscale: int = 3,
              title: str = "") -> np.ndarray:
    """One contact-sheet row: a title strip, a caption strip and, per view, RGB | depth | instance | GT boxes.

    ``categories`` are the names indexed by ``record.categories``; ``views`` default to ``0`` and ``V // 2`` (or ``0``).
    Returns ``[TITLE_HEIGHT + CAPTION_HEIGHT + H * upscale, len(views) * 4 * (W * upscale + PAD) - PAD, 3]`` uint8 RGB.
    """
    V = record.num_views
    if views is None:
        views = [0] if V < 2 else [0, V // 2]
    views = [int(v) for v in views]
    if not views:
        raise ValueError("views: need at least one view")
    bad = [v for v in views if not -V <= v < V]
    if bad:
        raise ValueError(f"views {bad} out of range for a scene with {V} views")
    H, W = record.image_size
    th, tw = H * upscale, W * upscale
    n_tiles = len(views) * TILES_PER_VIEW
    row = np.full((TITLE_HEIGHT + CAPTION_HEIGHT + th, n_tiles * (tw + PAD) - PAD, 3), _BACKGROUND, np.uint8)
    _put_text(row, title, (2, TITLE_HEIGHT - 6), 0.45)
    names = [categories[c] if 0 <= c < len(categories) else f"cat{c}" for c in record.categories.tolist()]
    box_colours = [distinct_colour(c) for c in record.categories.tolist()]
    for j, v in enumerate(views):
        v = v % V
        depth = record.depth[v]
        valid = depth[np.isfinite(depth) & (depth > 0)]
        drange = f"{valid.min():.2f}-{valid.max():.2f}m" if valid.size else "none valid"
        if record.instance is not None:
            inst = upscale_nearest(colorize_instances(record.instance[v]), upscale)
        else:
            inst = np.full((th, tw, 3), 64, np.uint8)
            _put_text(inst, "no instance mask", (4, th // 2), 0.4)
        K, pose = record.K[v], record.world_T_cam[v]
        gt = draw_boxes(record.rgb[v], record.boxes, names, K, pose, colour=box_colours, upscale=upscale)
        tiles = [(f"view {v} rgb", upscale_nearest(record.rgb[v], upscale)),
                 (f"depth {drange}", upscale_nearest(colorize_depth(depth), upscale)), ("instances", inst),
                 (f"GT boxes ({record.num_objects})", gt)]
        for k, (caption, tile) in enumerate(tiles):
            x = (j * TILES_PER_VIEW + k) * (tw + PAD)
            row[TITLE_HEIGHT + CAPTION_HEIGHT :, x : x + tw] = tile
            _put_text(row, caption, (x + 2, TITLE_HEIGHT + CAPTION_HEIGHT - 4), 0.35, (190, 190, 190))
    return row


def contact_sheet(dataset_dir: str | Path, out_png: str | Path, num_scenes: int = 4, views: Sequence[int] | None = None,
                  split: str | None = None, upscale: int = 3) -> Path:
    """Write a PNG contact sheet (atomically) of the first ``num_scenes`` scenes (of ``split``) of a dataset folder.

    Each scene is a :func:`scene_row`; rows are stacked with a :data:`PAD`-pixel margin around and between them, so
    ``n`` scenes of ``H x W`` pixels showing ``k`` views each make a sheet ``PAD + n * (TITLE_HEIGHT + CAPTION_HEIGHT +
    H * upscale + PAD)`` high and ``PAD + 4 * k * (W * upscale + PAD)`` wide. Returns the PNG's path.
    """
    dataset_dir = Path(dataset_dir)
    index = load_index(dataset_dir)
    files = index.files(split)[: max(int(num_scenes), 0)]
    if not files:
        where = f" in split {split!r}" if split is not None else ""
        raise ValueError(f"{dataset_dir / 'index.json'}: no scenes to show{where} (num_scenes={num_scenes})")
    split_of = {s["file"]: s["split"] for s in index.scenes}
    rows = []
    for f in files:
        record = load_scene(dataset_dir / f, num_categories=len(index.categories))
        title = f"{f}  [{split_of.get(f, '?')}]  {record.num_views} views, {record.num_objects} objects"
        rows.append(scene_row(record, index.categories, views=views, upscale=upscale, title=title))
    width = max(r.shape[1] for r in rows) + 2 * PAD
    height = PAD + sum(r.shape[0] + PAD for r in rows)
    sheet = np.full((height, width, 3), _BACKGROUND, np.uint8)
    y = PAD
    for r in rows:
        sheet[y : y + r.shape[0], PAD : PAD + r.shape[1]] = r
        y += r.shape[0] + PAD
    ok, buf = cv2.imencode(".png", cv2.cvtColor(sheet, cv2.COLOR_RGB2BGR))
    if not ok:
        raise RuntimeError(f"{out_png}: PNG encoding failed")
    return atomic_write_bytes(Path(out_png), buf.tobytes())
