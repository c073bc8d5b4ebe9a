"""Kinect captures in the layout of Open3D's reconstruction system (and the Redwood data): colour + depth + .log.

Expected tree::

    capture/
      color/000000.jpg|png ...         # or image/; numbered frames (numeric order)
      depth/000000.png ...             # uint16, registered to colour (same size), depth / depth_scale = metres
      camera_intrinsic.json            # or intrinsic.json: {"width", "height", "intrinsic_matrix": 9 numbers,
                                       #  column-major (Eigen order): [fx, 0, 0, 0, fy, 0, cx, cy, 1]}
      trajectory.log                   # 5-line items: "i j k" (i = frame index from 0), then a 4x4
                                       # camera-to-world (Redwood "log" format, Open3D's writer)
      threedq_objects.json             # optional: annotated boxes in the trajectory's frame

Depth must already be registered to the colour image (the Azure Kinect SDK's
``transformation_depth_image_to_color_camera``); a depth image of another size, a frame missing from the trajectory
or whose matrix is not rigid is skipped and counted.

Convention: the trajectory's world frame, metres; OpenCV camera axes.
"""

from __future__ import annotations

import json
import re
from pathlib import Path

import numpy as np

from threedq.data.formats.capture import Capture, FrameSkip, check_rigid, load_frames, png_frame, skipping
from threedq.scene import SceneValidationError

__all__ = ["MARKER", "read_log", "read_open3d"]

MARKER = "trajectory.log"


def read_log(path: Path, skipped: list[FrameSkip]) -> dict[int, np.ndarray]:
    """Frame index -> camera-to-world ``[4,4]`` of a Redwood/Open3D ``.log``; malformed items are skipped, counted."""
    if not path.is_file():
        raise SceneValidationError(str(path), "trajectory", "no such file")
    lines = [ln for ln in path.read_text(encoding="utf-8").splitlines() if ln.strip()]
    out: dict[int, np.ndarray] = {}
    for s in range(0, len(lines), 5):
        try:
            head = lines[s].split()
            if len(head) != 3:
                raise ValueError(f"expected 3 integers in the item's first line, got {len(head)} fields")
            idx = int(head[0])
            rows = [[float(x) for x in ln.split()] for ln in lines[s + 1 : s + 5]]
            m = np.array(rows, np.float64)
            if m.shape != (4, 4):
                raise ValueError(f"expected a 4x4 matrix, got {len(rows)} rows")
            out[idx] = m
        except ValueError as e:
            skipped.append(FrameSkip(f"{path}:{s + 1}", "trajectory", f"malformed item ({e})"))
    return out


def _number(p: Path) -> int:
    """The last number in a file's stem (-1 if none)."""
    return int(re.findall(r"\d+", p.stem)[-1]) if re.search(r"\d", p.stem) else -1


def _intrinsics(folder: Path) -> np.ndarray:
    for name in ("camera_intrinsic.json", "intrinsic.json"):
        p = folder / name
        if p.is_file():
            try:
                v = [float(x) for x in json.loads(p.read_text(encoding="utf-8"))["intrinsic_matrix"]]
                assert len(v) == 9
            except (json.JSONDecodeError, KeyError, TypeError, ValueError, AssertionError) as e:
                raise SceneValidationError(str(p), "intrinsic_matrix", "expected 9 numbers (column-major)") from e
            return np.array(v).reshape(3, 3).T  # column-major -> row-major
    raise SceneValidationError(str(folder / "camera_intrinsic.json"), "intrinsic_matrix", "no such file")


def read_open3d(folder: str | Path, depth_units_per_metre: float | None = None,
                max_views: int | None = None) -> Capture:
    """Read an Open3D/Kinect capture folder (tree in the module docstring); frame ids are the colour file stems.
    ``depth_units_per_metre`` is Open3D's ``depth_scale`` (``None`` = 1000); at most ``max_views`` frames are read."""
    folder = Path(folder)
    scale = 1000.0 if depth_units_per_metre is None else float(depth_units_per_metre)
    K = _intrinsics(folder)
    skipped: list[FrameSkip] = []
    traj_path = folder / "trajectory.log"
    poses = read_log(traj_path, skipped)
    cdir = folder / "color" if (folder / "color").is_dir() else folder / "image"
    colour = sorted((p for p in cdir.glob("*") if p.suffix.lower() in (".jpg", ".png") and _number(p) >= 0),
                    key=_number)
    depths = {_number(p): p for p in (folder / "depth").glob("*.png") if _number(p) >= 0}
    frames = []
    for i, f in enumerate(colour):
        n = _number(f)
        with skipping(skipped):
            if i not in poses:
                raise SceneValidationError(str(traj_path), "trajectory", f"no item for frame {i} ({f.name})")
            pose = check_rigid(poses[i], str(traj_path), f"trajectory[{i}]")
            if n not in depths:
                raise SceneValidationError(str(folder / "depth"), "depth", f"no depth image numbered {n}")
            frames.append(png_frame(f.stem, pose, f, depths[n], scale, K))
    return load_frames(frames, str(folder), "open3d", skipped, folder, max_views)
