"""BigBIRD raw captures: one object on a turntable seen by 5 RGB-D cameras at 120 angles.

Expected tree::

    <object>/
      NP1_0.jpg NP1_3.jpg ... NP5_357.jpg    # colour of camera c at turntable angle deg (1280x1024)
      NP1_0.h5 ...                           # dataset "depth": uint16 in 100 um units (/ 10000 = metres),
                                             # in the camera's IR (depth) frame
      calibration.h5                         # NP{c}_rgb_K, NP{c}_depth_K (3x3), H_NP{c}_from_NP5,
                                             # H_NP{c}_ir_from_NP5 (4x4)
      poses/NP5_0_pose.h5 ...                # dataset "H_table_from_reference_camera" (4x4) per angle
      threedq_objects.json                   # optional: annotated boxes in the table frame

The object is static and the (up to) 600 images are cameras around it: ``table_T_rgb(c, deg) =
H_table_from_reference_camera(deg) @ inv(H_NP{c}_from_NP5)``. Views are on the colour camera's grid resized to the
depth image's size (``resize_to``); depth is moved from the IR camera into it (:func:`register_depth`, ``rgb_T_ir =
H_NP{c}_from_NP5 @ inv(H_NP{c}_ir_from_NP5)``). A missing or corrupt image, depth or pose file skips that view and is
counted. The layout is not verified against a real download.

Convention: table frame, metres; OpenCV camera axes.
"""

from __future__ import annotations

import re
from pathlib import Path

import h5py
import numpy as np

from threedq.data.formats.capture import (
    Capture,
    Frame,
    FrameSkip,
    check_rigid,
    load_frames,
    read_rgb,
    resize_to,
    skipping,
)
from threedq.scene import SceneValidationError

__all__ = ["MARKER", "read_bigbird", "register_depth"]

MARKER = "calibration.h5"
DEPTH_UNITS_PER_METRE = 10000.0


def register_depth(depth: np.ndarray, K_src: np.ndarray, dst_T_src: np.ndarray, K_dst: np.ndarray,
                   size_hw: tuple[int, int]) -> np.ndarray:
    """Re-render a metric z-depth map ``[h,w]`` (0 = invalid) in another camera by forward splatting with a z-buffer.

    ``K_src``, ``K_dst``: ``[3,3]``; ``dst_T_src``: ``[4,4]`` source-to-destination camera. Returns ``[H,W]`` float32
    z-depth for ``size_hw = (H, W)``: each point lands on its nearest pixel, the nearest wins; other pixels are 0.
    """
    v, u = np.nonzero(depth > 0)
    z = depth[v, u].astype(np.float64)
    rays = np.linalg.inv(K_src) @ np.stack([u, v, np.ones_like(u)]).astype(np.float64)
    p = dst_T_src[:3, :3] @ (rays * z) + dst_T_src[:3, 3:4]
    ok = p[2] > 1e-6
    uv, zd = K_dst @ (p[:, ok] / p[2, ok]), p[2, ok]
    ui, vi = np.rint(uv[0]).astype(np.int64), np.rint(uv[1]).astype(np.int64)
    H, W = size_hw
    inside = (ui >= 0) & (ui < W) & (vi >= 0) & (vi < H)
    out = np.full(H * W, np.inf)
    np.minimum.at(out, vi[inside] * W + ui[inside], zd[inside])
    out[~np.isfinite(out)] = 0
    return out.reshape(H, W).astype(np.float32)


def _h5(path: Path, key: str, field_name: str) -> np.ndarray:
    if not path.is_file():
        raise SceneValidationError(str(path), field_name, "no such file")
    try:
        with h5py.File(path, "r") as f:
            if key not in f:
                raise SceneValidationError(str(path), field_name, f"no dataset {key!r}")
            return np.asarray(f[key][()])
    except OSError as e:
        why = f"not a readable HDF5 file (truncated or corrupt: {e})"
        raise SceneValidationError(str(path), field_name, why) from e


def _rigid_h5(path: Path, key: str) -> np.ndarray:
    """The checked rigid ``[4,4]`` dataset ``key`` of an HDF5 file (errors name the key)."""
    return check_rigid(_h5(path, key, key), str(path), key)


def _load_view(folder: Path, fid: str, cam: tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray],
               scale: float) -> tuple[np.ndarray, np.ndarray, np.ndarray, str]:
    """One view: colour resized to the depth size (and its K), depth registered into it."""
    K_rgb, K_ir, c_T_5, ir_T_5 = cam
    depth_path = folder / f"{fid}.h5"
    raw = _h5(depth_path, "depth", "depth")
    if raw.ndim != 2:
        raise SceneValidationError(str(depth_path), "depth", f"expected an [H,W] image, got {list(raw.shape)}")
    rgb, K = resize_to(read_rgb(folder / f"{fid}.jpg"), K_rgb, raw.shape)
    depth = register_depth(raw.astype(np.float64) / scale, K_ir, c_T_5 @ np.linalg.inv(ir_T_5), K, raw.shape)
    return rgb, depth, K, str(depth_path)


def read_bigbird(folder: str | Path, depth_units_per_metre: float | None = None,
                 max_views: int | None = None) -> Capture:
    """Read one BigBIRD object folder (tree in the module docstring): views ordered by camera then angle, frame ids
    ``"NP{c}_{deg}"``; ``depth_units_per_metre`` ``None`` = 10000; at most ``max_views`` views (farthest camera
    positions; ``None`` = all)."""
    folder = Path(folder)
    scale = DEPTH_UNITS_PER_METRE if depth_units_per_metre is None else float(depth_units_per_metre)
    calib = folder / "calibration.h5"
    names = sorted((int(m.group(1)), int(m.group(2))) for p in folder.glob("NP*_*.jpg")
                   if (m := re.fullmatch(r"NP(\d)_(\d+)", p.stem)))
    skipped: list[FrameSkip] = []
    cams: dict[int, tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]] = {}
    frames = []
    for c, deg in names:
        fid = f"NP{c}_{deg}"
        with skipping(skipped):
            if c not in cams:  # (K_rgb, K_ir, rgb_T_5, ir_T_5)
                Ks = [_h5(calib, k, k).astype(np.float64).reshape(3, 3) for k in (f"NP{c}_rgb_K", f"NP{c}_depth_K")]
                cams[c] = (*Ks, *(_rigid_h5(calib, k) for k in (f"H_NP{c}_from_NP5", f"H_NP{c}_ir_from_NP5")))
            table_T_5 = _rigid_h5(folder / "poses" / f"NP5_{deg}_pose.h5", "H_table_from_reference_camera")
            pose = table_T_5 @ np.linalg.inv(cams[c][2])
            frames.append(Frame(fid, pose, lambda fid=fid, c=c: _load_view(folder, fid, cams[c], scale)))
    return load_frames(frames, str(folder), "bigbird", skipped, folder, max_views)
