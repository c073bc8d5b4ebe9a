"""nerfstudio / instant-ngp ``transforms.json`` captures with depth (what ``ns-process-data polycam|record3d`` writes).

Expected tree::

    capture/
      transforms.json                  # fl_x, fl_y, cx, cy, w, h global or per frame; frames[]
      images/frame_00001.jpg ...       # frames[].file_path (relative to the folder)
      depth/frame_00001.png ...        # frames[].depth_file_path: 16-bit, millimetres unless
                                       # "depth_unit_scale_factor" (metres per unit) says otherwise
      threedq_objects.json             # optional: annotated boxes in the transforms' world frame

``frames[].transform_matrix`` is camera-to-world with OpenGL camera axes (x right, y up, z back): negating its y and
z columns gives OpenCV axes. nerfstudio puts pixel centres at ``i + 0.5``, ours at ``i``: ``cx_ours = cx - 0.5``.
Only undistorted pinhole cameras are read (any non-zero ``k1..k4, p1, p2`` is refused). A frame without
``depth_file_path`` is skipped and counted.

Convention: the transforms' world frame (any orientation), metres; OpenCV camera axes after conversion.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np

from threedq.data.formats.capture import Capture, FrameSkip, check_rigid, load_frames, png_frame
from threedq.scene import SceneValidationError

__all__ = ["MARKER", "OPENGL_T_OPENCV", "read_nerfstudio"]

MARKER = "transforms.json"
#: maps OpenCV camera coordinates to OpenGL camera coordinates (and back: it is its own inverse)
OPENGL_T_OPENCV = np.diag([1.0, -1.0, -1.0, 1.0])
_INTRINSIC_KEYS = ("fl_x", "fl_y", "cx", "cy")
_DISTORTION_KEYS = ("k1", "k2", "k3", "k4", "p1", "p2")


def _camera(frame: dict[str, Any], top: dict[str, Any], source: str) -> np.ndarray:
    vals = {}
    for k in _INTRINSIC_KEYS:
        v = frame.get(k, top.get(k))
        if v is None:
            raise SceneValidationError(source, k, "missing (neither per frame nor global)")
        vals[k] = float(v)
    for k in _DISTORTION_KEYS:
        if float(frame.get(k, top.get(k, 0.0)) or 0.0) != 0.0:
            raise SceneValidationError(source, k, "lens distortion is not supported: undistort the images first")
    return np.array([[vals["fl_x"], 0, vals["cx"] - 0.5], [0, vals["fl_y"], vals["cy"] - 0.5], [0, 0, 1]])


def read_nerfstudio(folder: str | Path, depth_units_per_metre: float | None = None,
                    max_views: int | None = None) -> Capture:
    """Read a ``transforms.json`` capture with depth (tree in the module docstring); frame ids are the ``file_path``s.

    ``depth_units_per_metre`` ``None`` = ``1 / depth_unit_scale_factor`` from the JSON if present, else 1000; at most
    ``max_views`` frames are read (farthest camera positions; ``None`` = all).
    """
    folder = Path(folder)
    path = folder / "transforms.json"
    source = str(path)
    if not path.is_file():
        raise SceneValidationError(source, "<file>", "no such file")
    try:
        top = json.loads(path.read_text(encoding="utf-8"))
        frames = top["frames"]
        assert isinstance(frames, list)
    except (json.JSONDecodeError, KeyError, AssertionError, TypeError) as e:
        raise SceneValidationError(source, "frames", f"not a transforms.json with a 'frames' list ({e})") from e
    if depth_units_per_metre is None:
        depth_units_per_metre = 1.0 / float(top.get("depth_unit_scale_factor", 1e-3))
    skipped: list[FrameSkip] = []
    scale = float(depth_units_per_metre)
    todo = []
    for i, fr in enumerate(frames):
        where = f"{source}: frames[{i}]"
        try:
            for key in ("file_path", "transform_matrix"):
                if key not in fr:
                    raise SceneValidationError(where, key, "missing")
            if not fr.get("depth_file_path"):
                raise SceneValidationError(where, "depth_file_path", "missing (a frame without depth)")
            K = _camera(fr, top, where)
            gl = np.array(fr["transform_matrix"], dtype=np.float64)
            if gl.shape == (3, 4):
                gl = np.vstack([gl, [0, 0, 0, 1]])
            pose = check_rigid(gl, where, "transform_matrix") @ OPENGL_T_OPENCV
        except (SceneValidationError, ValueError, TypeError) as e:
            if isinstance(e, SceneValidationError):
                skipped.append(FrameSkip(e.source, e.field, e.reason))
            else:
                skipped.append(FrameSkip(where, "transform_matrix", f"not a 4x4 matrix of numbers ({e})"))
            continue
        rgb, depth = folder / fr["file_path"], folder / fr["depth_file_path"]
        todo.append(png_frame(str(fr["file_path"]), pose, rgb, depth, scale, K))
    return load_frames(todo, source, "nerfstudio", skipped, folder, max_views)
