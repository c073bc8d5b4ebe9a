"""ScanNet scenes as exported by ScanNet's SensReader (``reader.py --export_color_images --export_depth_images ...``).

Expected tree::

    scene0000_00/
      color/0.jpg 1.jpg ...            # colour, 1296x968 typically (no zero padding: numeric order)
      depth/0.png 1.png ...            # uint16 millimetres, 640x480 (a different size from colour)
      pose/0.txt 1.txt ...             # 4x4 camera-to-world; some frames hold -inf (skipped and counted)
      intrinsic/intrinsic_color.txt    # 4x4 (top-left 3x3 is K of the colour image)
      intrinsic/intrinsic_depth.txt    # 4x4 (top-left 3x3 is K of the depth image)
      threedq_objects.json             # optional: annotated boxes in the scan's frame

Views are on the depth camera's pixel grid with ``K = intrinsic_depth``: the colour image is resized towards the
depth size (:func:`~threedq.data.formats.capture.resize_to`) and resampled onto the depth pixels with the homography
``K_color' K_depth^-1`` (the export's two cameras share their centre and axes).

Convention: the scan's frame (z up in ScanNet), metres; OpenCV camera axes; frames in numeric order.
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from threedq.data.formats.capture import (
    Capture,
    Frame,
    FrameSkip,
    check_rigid,
    load_frames,
    read_depth_png,
    read_matrix,
    read_rgb,
    resize_to,
    skipping,
)

__all__ = ["MARKER", "read_scannet", "register_colour"]

MARKER = "intrinsic/intrinsic_depth.txt"


def register_colour(rgb: np.ndarray, K_color: np.ndarray, K_depth: np.ndarray, size_hw: tuple[int, int]) -> np.ndarray:
    """Colour ``[Hc,Wc,3]`` resampled onto the depth camera's ``size_hw`` pixel grid (same centre and axes): ``[H,W,3]``
    uint8, depth pixel ``x_d`` takes the colour at ``K_color K_depth^-1 x_d`` (bilinear, border replicated)."""
    small, Kc = resize_to(rgb, K_color, size_hw)
    return cv2.warpPerspective(small, Kc @ np.linalg.inv(K_depth), (size_hw[1], size_hw[0]),
                               flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP, borderMode=cv2.BORDER_REPLICATE)


def read_scannet(folder: str | Path, depth_units_per_metre: float | None = None,
                 max_views: int | None = None) -> Capture:
    """Read a SensReader export (tree in the module docstring) on the depth grid; frame ids are the file numbers.
    ``depth_units_per_metre`` ``None`` = 1000; at most ``max_views`` frames are read."""
    folder = Path(folder)
    scale = 1000.0 if depth_units_per_metre is None else float(depth_units_per_metre)
    K_color = read_matrix(folder / "intrinsic" / "intrinsic_color.txt", "intrinsic_color")[:3, :3]
    K_depth = read_matrix(folder / "intrinsic" / "intrinsic_depth.txt", "intrinsic_depth")[:3, :3]
    skipped: list[FrameSkip] = []

    def load(fid: str) -> tuple[np.ndarray, np.ndarray, np.ndarray, str]:
        depth_path = folder / "depth" / f"{fid}.png"
        depth = read_depth_png(depth_path, scale)
        rgb = register_colour(read_rgb(folder / "color" / f"{fid}.jpg"), K_color, K_depth, depth.shape)
        return rgb, depth, K_depth, str(depth_path)

    frames = []
    for fid in sorted((p.stem for p in (folder / "color").glob("*.jpg") if p.stem.isdigit()), key=int):
        with skipping(skipped):
            pose = read_matrix(folder / "pose" / f"{fid}.txt", "pose")
            check_rigid(pose, str(folder / "pose" / f"{fid}.txt"))
            frames.append(Frame(fid, pose, lambda fid=fid: load(fid)))
    return load_frames(frames, str(folder), "scannet", skipped, folder, max_views)
