"""A recorded fixed multi-camera rig (e.g. CARLA's 17 cameras around a car): per-camera folders + one YAML spec.

Expected tree::

    capture/
      rig.yaml
      cam_00/rgb_000000.png ...        # colour of camera cam_00 at capture 0, 1, ...
      cam_00/depth_000000.png|npy ...  # depth, encoded as rig.yaml says
      cam_01/...
      threedq_objects.json             # optional: annotated boxes in the rig's world frame

``rig.yaml``::

    depth:
      encoding: uint16          # uint16 (PNG, / units_per_metre), npy (float metres) or carla (see below)
      units_per_metre: 1000     # uint16 only
    cameras:                    # one entry per camera folder
      cam_00:
        K: [[fx, 0, cx], [0, fy, cy], [0, 0, 1]]
        rig_T_cam: [[...4x4 rows...]]   # camera-to-rig, OpenCV camera axes
    captures:                   # optional: world_T_rig (4x4 rows) per capture number; default identity
      0: [[...]]

``carla`` depth is CARLA's RGB-encoded depth image: ``1000 m * (R + 256 G + 65536 B) / (256^3 - 1)``. CARLA's own
transforms are left-handed (Unreal axes): convert them to right-handed poses with OpenCV camera axes before writing
``rig.yaml``. Every (camera, capture) pair is one view; a pair with a corrupt image, a missing capture pose or a
non-rigid pose is skipped and counted.

Convention: the rig's world frame, metres; ``world_T_cam = world_T_rig @ rig_T_cam``; OpenCV camera axes.
"""

from __future__ import annotations

import re
from functools import partial
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from threedq.data.formats.capture import (
    Capture,
    Frame,
    FrameSkip,
    check_rigid,
    load_frames,
    read_depth_png,
    read_rgb,
    skipping,
)
from threedq.scene import SceneValidationError

__all__ = ["MARKER", "decode_carla_depth", "read_rig"]

MARKER = "rig.yaml"
CARLA_FAR_M = 1000.0


def decode_carla_depth(rgb: np.ndarray) -> np.ndarray:
    """Metric depth ``[H,W]`` float32 of CARLA's RGB-encoded depth image ``[H,W,3]`` uint8 (RGB order)."""
    c = rgb.astype(np.float64)
    return (CARLA_FAR_M * (c[..., 0] + 256.0 * c[..., 1] + 65536.0 * c[..., 2]) / (256.0**3 - 1)).astype(np.float32)


def _spec(path: Path) -> dict[str, Any]:
    if not path.is_file():
        raise SceneValidationError(str(path), "<file>", "no such file")
    try:
        spec = yaml.safe_load(path.read_text(encoding="utf-8"))
    except yaml.YAMLError as e:
        mark = getattr(e, "problem_mark", None)
        where = f" at line {mark.line + 1}, column {mark.column + 1}" if mark is not None else ""
        why = f"not valid YAML{where} ({getattr(e, 'problem', None) or e})"
        raise SceneValidationError(str(path), "<file>", why) from e
    if not isinstance(spec, dict) or not isinstance(spec.get("cameras"), dict) or not spec["cameras"]:
        raise SceneValidationError(str(path), "cameras", "expected a mapping of camera folders")
    enc = (spec.get("depth") or {}).get("encoding", "uint16")
    if enc not in ("uint16", "npy", "carla"):
        raise SceneValidationError(str(path), "depth.encoding", f"expected uint16, npy or carla, got {enc!r}")
    return spec


def _matrix(v: Any, shape: tuple[int, int], source: str, field_name: str) -> np.ndarray:
    try:
        m = np.array(v, np.float64)
    except (TypeError, ValueError) as e:
        raise SceneValidationError(source, field_name, f"not a matrix of numbers ({e})") from e
    if m.shape != shape:
        raise SceneValidationError(source, field_name, f"expected a {shape[0]}x{shape[1]} matrix, got {list(m.shape)}")
    return m


def _pose(v: Any, source: str, field_name: str) -> np.ndarray:
    return check_rigid(_matrix(v, (4, 4), source, field_name), source, field_name)


def _load(rgb: Path, depth_stem: Path, enc: str, units: float, K: np.ndarray) -> tuple[np.ndarray, ...]:
    """One view: ``(rgb, depth in metres, K, depth file)``, the depth file encoded as ``enc``."""
    if enc == "npy":
        p = depth_stem.with_suffix(".npy")
        if not p.is_file():
            raise SceneValidationError(str(p), "depth", "no such file")
        try:
            d = np.load(p, allow_pickle=False)
        except (ValueError, OSError, EOFError) as e:
            raise SceneValidationError(str(p), "depth", f"not a readable .npy (truncated or corrupt: {e})") from e
        if d.ndim != 2:
            raise SceneValidationError(str(p), "depth", f"expected an [H,W] array, got {list(d.shape)}")
        depth = d.astype(np.float32)
    else:
        p = depth_stem.with_suffix(".png")
        depth = decode_carla_depth(read_rgb(p)) if enc == "carla" else read_depth_png(p, units)
    return read_rgb(rgb), depth, K, str(p)


def read_rig(folder: str | Path, max_views: int | None = None) -> Capture:
    """Read a recorded rig capture (tree and ``rig.yaml`` in the module docstring): one view per (camera, capture
    number), cameras in ``rig.yaml`` order, frame ids ``"<camera>/<capture number>"``; at most ``max_views`` views
    (farthest camera positions; ``None`` = all)."""
    folder = Path(folder)
    spec_path = folder / "rig.yaml"
    src = str(spec_path)
    spec = _spec(spec_path)
    enc = (spec.get("depth") or {}).get("encoding", "uint16")
    units = float((spec.get("depth") or {}).get("units_per_metre", 1000.0))
    captures = {int(k): v for k, v in (spec.get("captures") or {}).items()}
    skipped: list[FrameSkip] = []
    frames = []
    for cam, cs in spec["cameras"].items():
        K = _matrix((cs or {}).get("K"), (3, 3), src, f"cameras.{cam}.K")
        rig_T_cam = _pose((cs or {}).get("rig_T_cam"), src, f"cameras.{cam}.rig_T_cam")
        cam_dir = folder / str(cam)
        numbers = sorted(int(m.group(1)) for p in cam_dir.glob("rgb_*.png")
                         if (m := re.fullmatch(r"rgb_(\d+)", p.stem)))
        if not numbers:
            skipped.append(FrameSkip(str(cam_dir), "rgb", "no rgb_<number>.png files"))
        for t in numbers:
            stem = f"{t:06d}"
            with skipping(skipped):
                if captures and t not in captures:
                    raise SceneValidationError(src, f"captures.{t}", f"no rig pose for capture {t}")
                world_T_rig = _pose(captures[t], src, f"captures.{t}") if captures else np.eye(4)
                load = partial(_load, cam_dir / f"rgb_{stem}.png", cam_dir / f"depth_{stem}", enc, units, K)
                frames.append(Frame(f"{cam}/{stem}", world_T_rig @ rig_T_cam, load))
    return load_frames(frames, str(folder), "rig", skipped, folder, max_views)
