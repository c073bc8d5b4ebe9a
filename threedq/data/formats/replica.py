"""Replica scenes as rendered and exported for NICE-SLAM (``cvg/nice-slam``'s ``Replica`` loader).

Expected tree::

    Replica/
      cam_params.json                  # optional, here or in the scene folder:
                                       # {"camera": {"w", "h", "fx", "fy", "cx", "cy", "scale"}}
      room0/
        results/frame000000.jpg ...    # colour, 1200x680
        results/depth000000.png ...    # uint16, depth / 6553.5 = metres ("scale")
        traj.txt                       # line i: row-major 4x4 camera-to-world of frame i (16 numbers)
        threedq_objects.json           # optional: annotated boxes in the scene's frame

Without ``cam_params.json`` the NICE-SLAM constants apply: 1200x680, fx = fy = 600, cx = 599.5, cy = 339.5,
scale 6553.5. A frame whose ``traj.txt`` line is missing, malformed or not rigid is skipped and counted.

Convention: the scene's frame, metres; OpenCV camera axes (as written by the export).
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from threedq.data.formats.capture import Capture, FrameSkip, check_rigid, load_frames, png_frame, skipping
from threedq.scene import SceneValidationError

__all__ = ["MARKER", "REPLICA_CAMERA", "read_replica"]

MARKER = "traj.txt"
REPLICA_CAMERA = {"w": 1200, "h": 680, "fx": 600.0, "fy": 600.0, "cx": 599.5, "cy": 339.5, "scale": 6553.5}


def _camera(folder: Path) -> dict[str, float]:
    for p in (folder / "cam_params.json", folder.parent / "cam_params.json"):
        if p.is_file():
            try:
                cam = json.loads(p.read_text(encoding="utf-8"))["camera"]
                return {k: float(cam[k]) for k in ("fx", "fy", "cx", "cy", "scale")}
            except (json.JSONDecodeError, KeyError, TypeError, ValueError) as e:
                why = f"expected {{'camera': {{fx, fy, cx, cy, scale}}}} ({e})"
                raise SceneValidationError(str(p), "camera", why) from e
    return {k: float(v) for k, v in REPLICA_CAMERA.items()}


def read_replica(folder: str | Path, depth_units_per_metre: float | None = None,
                 max_views: int | None = None) -> Capture:
    """Read one NICE-SLAM Replica scene folder (tree in the module docstring); frame ids are the 6-digit frame
    numbers. ``depth_units_per_metre`` overrides the camera's ``scale``; at most ``max_views`` frames are read."""
    folder = Path(folder)
    cam = _camera(folder)
    scale = cam["scale"] if depth_units_per_metre is None else float(depth_units_per_metre)
    K = np.array([[cam["fx"], 0, cam["cx"]], [0, cam["fy"], cam["cy"]], [0, 0, 1]])
    traj_path = folder / "traj.txt"
    if not traj_path.is_file():
        raise SceneValidationError(str(traj_path), "pose", "no such file")
    lines = traj_path.read_text(encoding="utf-8").splitlines()
    skipped: list[FrameSkip] = []
    frames = []
    for f in sorted((folder / "results").glob("frame*.jpg")):
        fid = f.stem[len("frame") :]
        if not fid.isdigit():
            continue
        i = int(fid)
        where = f"{traj_path}:{i + 1}"
        with skipping(skipped):
            if i >= len(lines) or not lines[i].strip():
                raise SceneValidationError(where, "pose", f"no pose line for frame {fid}")
            try:
                pose = np.array([float(x) for x in lines[i].split()]).reshape(4, 4)
            except ValueError as e:
                raise SceneValidationError(where, "pose", f"expected 16 numbers ({e})") from e
            check_rigid(pose, where)
            frames.append(png_frame(fid, pose, f, folder / "results" / f"depth{fid}.png", scale, K))
    return load_frames(frames, str(folder), "replica", skipped, folder, max_views)
