"""Drawing on scene images: projected 3D box wireframes with labels, colourised depth and instance maps.

The helpers take RGB ``uint8`` images (colours are RGB tuples) and return new arrays.

Convention:
    OpenCV camera axes (x right, y down, z forward); ``world_T_cam`` ``[4, 4]`` is camera-to-world; ``K`` ``[3, 3]``
    has pixel centres at integer coordinates. An image upscaled ``s`` times by nearest neighbour maps pixel
    coordinate ``u`` to ``s * u + (s - 1) / 2``. Boxes are ``(cx, cy, cz, sx, sy, sz, yaw)`` in the world frame (z up,
    yaw counter-clockwise about +z), with corners in :func:`threedq.boxes.box_corners` order.
"""

from __future__ import annotations

import colorsys
import zlib
from collections.abc import Sequence
from typing import TYPE_CHECKING

import cv2
import numpy as np

from threedq.boxes import box_corners

if TYPE_CHECKING:
    import torch

__all__ = ["BOX_EDGES", "colorize_depth", "colorize_instances", "crop_birds_eye", "distinct_colour", "draw_boxes",
           "project_points", "upscale_nearest"]

#: The 12 edges of a box as corner-index pairs (corners differing in exactly one of the bits x, y, z).
BOX_EDGES: tuple[tuple[int, int], ...] = tuple((i, i | bit) for bit in (1, 2, 4) for i in range(8) if not i & bit)
_TOP_EDGES = tuple(e for e in BOX_EDGES if e[0] & 4 and e[1] & 4)  # edges of the top face (corners 4-7)

_FONT = cv2.FONT_HERSHEY_SIMPLEX


def _as_pose(K: np.ndarray, world_T_cam: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    K = np.asarray(K, dtype=np.float64)
    pose = np.asarray(world_T_cam, dtype=np.float64)
    if K.shape != (3, 3):
        raise ValueError(f"K must have shape [3, 3], got {list(K.shape)}")
    if pose.shape != (4, 4):
        raise ValueError(f"world_T_cam must have shape [4, 4], got {list(pose.shape)}")
    return K, pose


def _to_camera(points_world: np.ndarray, world_T_cam: np.ndarray) -> np.ndarray:
    """``[N, 3]`` world points -> ``[N, 3]`` camera-frame points (float64)."""
    cam_T_world = np.linalg.inv(world_T_cam)
    return points_world @ cam_T_world[:3, :3].T + cam_T_world[:3, 3]


def project_points(points_world: np.ndarray, K: np.ndarray, world_T_cam: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Project world points ``[N, 3]`` into a pinhole camera: ``uv`` ``[N, 2]`` float64 pixel coordinates (NaN where
    the camera-frame depth ``z`` ``[N]`` float64, also returned, is ``<= 0``)."""
    K, pose = _as_pose(K, world_T_cam)
    pts = np.asarray(points_world, dtype=np.float64)
    if pts.ndim != 2 or pts.shape[1] != 3:
        raise ValueError(f"points_world must have shape [N, 3], got {list(pts.shape)}")
    cam = _to_camera(pts, pose)
    z = cam[:, 2]
    uv = np.full((pts.shape[0], 2), np.nan)
    front = z > 0
    if np.any(front):
        h = cam[front] @ K.T
        uv[front] = h[:, :2] / h[:, 2:3]
    return uv, z


def _clip_segment_2d(p: np.ndarray, q: np.ndarray, lo: np.ndarray,
                     hi: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
    """Liang-Barsky clip of the 2D segment ``p -> q`` to the rectangle ``[lo, hi]``; ``None`` if outside."""
    d = q - p
    t0, t1 = 0.0, 1.0
    for k in range(2):
        for num, den in ((p[k] - lo[k], -d[k]), (hi[k] - p[k], d[k])):
            if den == 0:
                if num < 0:
                    return None
                continue
            t = num / den
            if den < 0:
                t0 = max(t0, t)
            else:
                t1 = min(t1, t)
            if t0 > t1:
                return None
    return p + t0 * d, p + t1 * d


def _visible_segments(corners_cam: np.ndarray, K: np.ndarray, edges: Sequence[tuple[int, int]],
                      near: float) -> list[tuple[np.ndarray, np.ndarray]]:
    """Clip each 3D edge at the plane ``z = near`` and project what is in front; returns pixel segments."""
    out = []
    for a, b in edges:
        pa, pb = corners_cam[a], corners_cam[b]
        za, zb = pa[2], pb[2]
        if za <= near and zb <= near:
            continue
        if za <= near or zb <= near:
            t = (near - za) / (zb - za)  # za != zb here
            cut = pa + t * (pb - pa)
            cut[2] = near
            if za <= near:
                pa = cut
            else:
                pb = cut
        ha, hb = K @ pa, K @ pb
        out.append((ha[:2] / ha[2], hb[:2] / hb[2]))
    return out


def distinct_colour(key: int | str) -> tuple[int, int, int]:
    """A fixed, saturated RGB colour for an integer id or a name (CRC-32 hashed); stable across runs and processes."""
    n = zlib.crc32(key.encode("utf-8")) if isinstance(key, str) else int(key)
    hue = (n * 0.618033988749895) % 1.0
    sat = 0.65 + 0.3 * ((n * 7) % 3) / 2  # 0.65, 0.8, 0.95
    r, g, b = colorsys.hsv_to_rgb(hue, sat, 1.0)
    return int(round(r * 255)), int(round(g * 255)), int(round(b * 255))


def _put_label(img: np.ndarray, text: str, anchor: tuple[float, float], colour: tuple[int, int, int], scale: float,
               placed: list[tuple[int, int, int, int]]) -> None:
    """Write ``text`` on a filled tag in ``colour`` above ``anchor``, inside the image, moved up or down by whole tag
    heights off the ``(x0, y0, x1, y1)`` rectangles in ``placed`` (a few tries), and append its rectangle there."""
    H, W = img.shape[:2]
    (tw, th), base = cv2.getTextSize(text, _FONT, scale, 1)
    x = int(round(anchor[0] - tw / 2))
    x = min(max(x, 1), max(W - tw - 1, 1))
    y_lo, y_hi = th + 1, max(H - base - 1, th + 1)  # allowed baselines

    def rect(y: int) -> tuple[int, int, int, int]:
        return x - 1, y - th - 1, x + tw, y + base

    def free(r: tuple[int, int, int, int]) -> bool:
        return all(r[2] < p[0] or p[2] < r[0] or r[3] < p[1] or p[3] < r[1] for p in placed)

    y0 = min(max(int(round(anchor[1])) - 3 - base, y_lo), y_hi)  # text baseline
    candidates = (min(max(y0 + k * (th + base + 2), y_lo), y_hi) for k in (0, -1, -2, -3, 1, 2, 3))
    y = next((c for c in candidates if free(rect(c))), y0)
    r = rect(y)
    placed.append(r)
    cv2.rectangle(img, r[:2], r[2:], colour, thickness=-1)
    luma = 0.299 * colour[0] + 0.587 * colour[1] + 0.114 * colour[2]
    cv2.putText(img, text, (x, y), _FONT, scale, (0, 0, 0) if luma > 140 else (255, 255, 255), 1, cv2.LINE_AA)


def upscale_nearest(img: np.ndarray, upscale: int) -> np.ndarray:
    """``img`` ``[H, W, ...]`` enlarged ``upscale`` times by nearest neighbour (a new array; a copy for 1)."""
    if int(upscale) != upscale or upscale < 1:
        raise ValueError(f"upscale must be a positive integer, got {upscale!r}")
    upscale = int(upscale)
    if upscale == 1:
        return np.ascontiguousarray(img).copy()
    return cv2.resize(img, (img.shape[1] * upscale, img.shape[0] * upscale), interpolation=cv2.INTER_NEAREST)


def _box_colours(colour: tuple[int, int, int] | Sequence[tuple[int, int, int]] | None, labels: Sequence[str] | None,
                 M: int) -> list[tuple[int, int, int]]:
    """The ``M`` RGB colours of :func:`draw_boxes`'s boxes: one per label (or box id), one for all, or as given."""
    if colour is None:
        return [distinct_colour(labels[m] if labels is not None else m + 1) for m in range(M)]
    if len(colour) == 3 and all(np.isscalar(c) for c in colour):
        return [tuple(int(c) for c in colour)] * M  # type: ignore[union-attr]
    if len(colour) != M:
        raise ValueError(f"colour: expected one RGB triple or {M} of them, got {len(colour)}")
    return [tuple(int(c) for c in col) for col in colour]  # type: ignore[union-attr]


def _draw_wireframe(out: np.ndarray, corners: np.ndarray, K: np.ndarray, pose: np.ndarray, col: tuple[int, int, int],
                    s: int, thickness: int, near: float, heading: bool) -> tuple[list[np.ndarray], list[np.ndarray]]:
    """Draw one box's edges (and yaw tick) on ``out``, upscaled ``s`` times, in place; returns the end points (output
    pixels) of the drawn edge segments and of the visible top-face segments."""
    H, W = out.shape[:2]
    shift = 4  # cv2 fixed-point fractional bits: sub-pixel line placement
    lo = np.array([-2.0 * thickness, -2.0 * thickness])
    hi = np.array([W - 1 + 2.0 * thickness, H - 1 + 2.0 * thickness])
    offset = (s - 1) / 2.0

    def to_out(p: np.ndarray) -> np.ndarray:
        return p * s + offset

    def fixed(p: np.ndarray) -> tuple[int, int]:
        return int(round(p[0] * (1 << shift))), int(round(p[1] * (1 << shift)))

    cam = _to_camera(corners, pose)
    drawn: list[np.ndarray] = []
    top: list[np.ndarray] = []
    for edges, sink in ((BOX_EDGES, drawn), (_TOP_EDGES, top)):
        for p, q in _visible_segments(cam, K, edges, near):
            clipped = _clip_segment_2d(to_out(p), to_out(q), lo, hi)
            if clipped is None:
                continue
            sink.extend(clipped)
            if sink is drawn:
                cv2.line(out, fixed(clipped[0]), fixed(clipped[1]), col, thickness, cv2.LINE_AA, shift)
    if heading:
        uv, z = project_points(np.stack([corners.mean(axis=0), corners[[1, 3, 5, 7]].mean(axis=0)]), K, pose)
        if np.all(z > near):
            clipped = _clip_segment_2d(to_out(uv[0]), to_out(uv[1]), lo, hi)
            if clipped is not None:
                cv2.line(out, fixed(clipped[0]), fixed(clipped[1]), col, max(1, thickness - 1), cv2.LINE_AA, shift)
    return drawn, top


def draw_boxes(rgb: np.ndarray, boxes: np.ndarray, labels: Sequence[str] | None, K: np.ndarray, world_T_cam: np.ndarray,
               scores: Sequence[float] | None = None,
               colour: tuple[int, int, int] | Sequence[tuple[int, int, int]] | None = None, upscale: int = 3,
               thickness: int = 2, near: float = 1e-3, heading: bool = True, font_scale: float = 0.4) -> np.ndarray:
    """Draw oriented 3D boxes as projected wireframes with their labels on an image upscaled ``upscale`` times.

    Edges are clipped at the near plane ``z = near`` (metres), then to the image. The label (``"name"``, or ``"name
    0.87"`` with ``scores``) is written on a tag in the box colour above the box's topmost visible top-face point;
    ``heading`` draws a line from the box centre to the centre of its +x face.

    Args:
        rgb: ``[H, W, 3]`` uint8 image, RGB order.
        boxes: ``[M, 7]`` ``(cx, cy, cz, sx, sy, sz, yaw)`` world-frame boxes; labels: ``M`` names or ``None``.
        K: ``[3, 3]`` intrinsics of ``rgb`` (at its original size); world_T_cam: ``[4, 4]`` camera-to-world pose.
        colour: one RGB colour for all boxes, ``M`` colours, or ``None`` for :func:`distinct_colour` of each label.
        thickness: line thickness in output pixels; font_scale: OpenCV font scale of the labels.

    Returns:
        ``[H * upscale, W * upscale, 3]`` uint8 RGB image.
    """
    rgb = np.asarray(rgb)
    if rgb.ndim != 3 or rgb.shape[2] != 3 or rgb.dtype != np.uint8:
        raise ValueError(f"rgb must be a [H, W, 3] uint8 image, got shape {list(rgb.shape)} dtype {rgb.dtype}")
    K, pose = _as_pose(K, world_T_cam)
    boxes = np.asarray(boxes, dtype=np.float64).reshape(-1, 7)
    M = boxes.shape[0]
    if labels is not None and len(labels) != M:
        raise ValueError(f"labels: expected {M} names (one per box), got {len(labels)}")
    if scores is not None and len(scores) != M:
        raise ValueError(f"scores: expected {M} values (one per box), got {len(scores)}")
    colours = _box_colours(colour, labels, M)

    out = upscale_nearest(rgb, upscale)
    H, W = out.shape[:2]
    if M == 0:
        return out
    corners = box_corners(boxes)  # [M, 8, 3]
    placed: list[tuple[int, int, int, int]] = []
    for m in range(M):
        col = colours[m]
        drawn, top = _draw_wireframe(out, corners[m], K, pose, col, int(upscale), thickness, near, heading)
        text = "" if labels is None else str(labels[m])
        if scores is not None:
            text = f"{text} {float(scores[m]):.2f}".strip()
        pts = top or drawn
        if text and pts:
            arr = np.clip(np.stack(pts), [0, 0], [W - 1, H - 1])
            anchor = arr[int(np.argmin(arr[:, 1]))]
            _put_label(out, text, (float(anchor[0]), float(anchor[1])), col, font_scale, placed)
    return out


def colorize_depth(depth: np.ndarray) -> np.ndarray:
    """Colourise a depth map ``[H, W]`` (metres; 0 or non-finite = invalid, black) with viridis into ``[H, W, 3]``
    uint8 RGB; the valid depths' 1st to 99th percentiles span the colormap."""
    d = np.asarray(depth, dtype=np.float64)
    if d.ndim != 2:
        raise ValueError(f"depth must have shape [H, W], got {list(d.shape)}")
    valid = np.isfinite(d) & (d > 0)
    out = np.zeros((*d.shape, 3), dtype=np.uint8)
    if not np.any(valid):
        return out
    lo, hi = (float(x) for x in np.percentile(d[valid], [1.0, 99.0]))
    scaled = np.zeros(d.shape, dtype=np.float64)
    scaled[valid] = np.clip((d[valid] - lo) / max(hi - lo, 1e-9), 0.0, 1.0)
    grey = np.clip(np.round(scaled * 255), 0, 255).astype(np.uint8)
    coloured = cv2.cvtColor(cv2.applyColorMap(grey, cv2.COLORMAP_VIRIDIS), cv2.COLOR_BGR2RGB)
    out[valid] = coloured[valid]
    return out


def colorize_instances(instance: np.ndarray) -> np.ndarray:
    """Colour an instance-id map ``[H, W]`` into ``[H, W, 3]`` uint8 RGB: id ``i > 0`` in ``distinct_colour(i)``,
    background (ids ``<= 0``) black."""
    inst = np.asarray(instance)
    if inst.ndim != 2:
        raise ValueError(f"instance must have shape [H, W], got {list(inst.shape)}")
    ids, inverse = np.unique(inst.astype(np.int64), return_inverse=True)
    lut = np.array([distinct_colour(int(i)) if i > 0 else (0, 0, 0) for i in ids], dtype=np.uint8).reshape(-1, 3)
    return lut[inverse.reshape(inst.shape)]


def crop_birds_eye(raw: torch.Tensor, background: float = 0.15) -> np.ndarray:
    """Bird's-eye view ``[Y, X, 3]`` float RGB in [0, 1] of a raw ``[4, Z, Y, X]`` crop (``cat[occ, occ * rgb]``):
    the colour of the highest voxel with occupancy > 0.5 per column, else ``background``; x right, y up (row 0 = the
    largest y)."""
    import torch

    raw = raw.detach().float().cpu()
    occ, rgb = raw[0] > 0.5, raw[1:4]
    z_top = occ.float() * torch.arange(1, occ.shape[0] + 1, dtype=torch.float32)[:, None, None]
    top = z_top.argmax(0)  # [Y, X]
    col = torch.gather(rgb, 1, top[None, None].expand(3, 1, *top.shape))[:, 0]
    img = torch.where(occ.any(0)[None], col, torch.full_like(col, background))
    return img.flip(1).permute(1, 2, 0).clamp(0, 1).numpy()
