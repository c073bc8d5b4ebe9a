"""What every capture reader returns (:class:`Capture`) and the file readers they share.

A reader reads one on-disk capture into a :class:`Capture` (views in the capture's own world frame, metric depth, one
``K`` per view on the colour-and-depth pixel grid, the frames it skipped);
:func:`threedq.data.formats.normalise.normalise_capture` turns it into a canonical :class:`~threedq.scene.SceneRecord`.

Convention: capture frame as the format defines it, metres; ``world_T_cam`` camera-to-world with OpenCV camera axes
(x right, y down, z forward); ``K`` with pixel centres at integer ``(u, v)``. Images are read with OpenCV
(``cv2.IMREAD_UNCHANGED`` for depth, so 16-bit PNGs stay 16-bit).
"""

from __future__ import annotations

import json
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from threedq.scene import SceneValidationError

__all__ = ["OBJECTS_NAME", "Capture", "CaptureObjects", "Frame", "FrameSkip", "check_rigid", "farthest_order",
           "load_frames", "png_frame", "read_depth_png", "read_matrix", "read_objects", "read_rgb", "resize_to",
           "skipping"]

#: optional threedq annotation beside a capture: boxes in the capture's own frame (see :func:`read_objects`)
OBJECTS_NAME = "threedq_objects.json"
_RIGID_TOL = 1e-4


@dataclass
class FrameSkip:
    """One frame the reader left out: the file and field at fault and why (one line)."""

    source: str
    field: str
    reason: str

    def __str__(self) -> str:
        return f"{self.source}: field '{self.field}': {self.reason}"


@contextmanager
def skipping(skipped: list[FrameSkip]) -> Iterator[None]:
    """Record a :class:`~threedq.scene.SceneValidationError` raised in the block in ``skipped`` instead of raising."""
    try:
        yield
    except SceneValidationError as e:
        skipped.append(FrameSkip(e.source, e.field, e.reason))


@dataclass
class CaptureObjects:
    """Annotated objects of a capture, in its own frame: ``capture_T_box`` ``[M,4,4]`` box-to-capture poses (local z
    up), ``size`` ``[M,3]`` full extents ``(sx, sy, sz)`` in metres, ``categories`` ``[M]`` names."""

    capture_T_box: np.ndarray
    size: np.ndarray
    categories: list[str]


@dataclass
class Capture:
    """One parsed capture (``V`` views of ``H x W`` pixels), in the capture's own world frame.

    ``rgb`` ``[V,H,W,3]`` uint8, ``depth`` ``[V,H,W]`` float32 metres (0 = invalid), ``K`` ``[V,3,3]``, ``world_T_cam``
    ``[V,4,4]``, ``frame_ids`` the format's frame names, ``skipped`` the frames left out (and malformed lines),
    ``objects`` optional annotated boxes, ``num_frames`` the frames with a valid pose before subsampling.
    """

    rgb: np.ndarray
    depth: np.ndarray
    K: np.ndarray
    world_T_cam: np.ndarray
    frame_ids: list[str]
    source: str
    format: str
    skipped: list[FrameSkip] = field(default_factory=list)
    objects: CaptureObjects | None = None
    num_frames: int = 0

    @property
    def num_views(self) -> int:
        return int(self.rgb.shape[0])


def _decode(path: Path, field_name: str, flags: int) -> np.ndarray:
    """Decode an image file with OpenCV; a JPEG must end with its EOI marker and a PNG with its ``IEND`` chunk."""
    if not path.is_file():
        raise SceneValidationError(str(path), field_name, "no such file")
    data = path.read_bytes()
    marker = {".jpg": b"\xff\xd9", ".jpeg": b"\xff\xd9", ".png": b"IEND"}.get(path.suffix.lower())
    if marker is not None and marker not in data[-16:]:
        raise SceneValidationError(str(path), field_name, "truncated image (no end marker)")
    img = cv2.imdecode(np.frombuffer(data, np.uint8), flags)
    if img is None:
        raise SceneValidationError(str(path), field_name, "not a readable image (corrupt)")
    return img


def read_rgb(path: Path) -> np.ndarray:
    """``[H,W,3]`` uint8 RGB of an image file; a missing, truncated or unreadable file raises naming it."""
    return cv2.cvtColor(_decode(path, "rgb", cv2.IMREAD_COLOR), cv2.COLOR_BGR2RGB)


def read_depth_png(path: Path, units_per_metre: float) -> np.ndarray:
    """``[H,W]`` float32 metres from a 16-bit depth image holding ``units_per_metre`` units per metre (0 = invalid)."""
    img = _decode(path, "depth", cv2.IMREAD_UNCHANGED)
    if img.ndim != 2:
        raise SceneValidationError(str(path), "depth", f"expected a single-channel image, got shape {list(img.shape)}")
    return (img.astype(np.float64) / units_per_metre).astype(np.float32)


def read_matrix(path: Path, field_name: str, shape: tuple[int, int] = (4, 4)) -> np.ndarray:
    """A whitespace-separated matrix of a text file, checked for shape and finiteness (float64)."""
    if not path.is_file():
        raise SceneValidationError(str(path), field_name, "no such file")
    try:
        m = np.loadtxt(path, dtype=np.float64, ndmin=2)
    except ValueError as e:
        raise SceneValidationError(str(path), field_name, f"not a matrix of numbers ({e})") from e
    if m.shape != shape:
        why = f"expected a {shape[0]}x{shape[1]} matrix, got {list(m.shape)}"
        raise SceneValidationError(str(path), field_name, why)
    if not np.all(np.isfinite(m)):
        raise SceneValidationError(str(path), field_name, "non-finite values (inf/NaN): invalid pose")
    return m


def check_rigid(pose: np.ndarray, source: str, field_name: str = "pose") -> np.ndarray:
    """``pose`` ``[4,4]`` if finite and rigid (``R^T R = I``, ``det R = 1``, last row ``0 0 0 1``), else raise."""
    pose = np.asarray(pose, np.float64)
    if pose.shape != (4, 4):
        raise SceneValidationError(source, field_name, f"expected a 4x4 matrix, got {list(pose.shape)}")
    if not np.all(np.isfinite(pose)):
        raise SceneValidationError(source, field_name, "non-finite values (inf/NaN): invalid pose")
    R = pose[:3, :3]
    err = float(np.abs(R.T @ R - np.eye(3)).max())
    det = float(np.linalg.det(R))
    if err > _RIGID_TOL or abs(det - 1) > _RIGID_TOL:
        raise SceneValidationError(source, field_name, f"not rigid (max |R^T R - I| = {err:.3g}, det = {det:.4g})")
    if np.abs(pose[3] - [0, 0, 0, 1]).max() > 1e-9:
        raise SceneValidationError(source, field_name, "last row must be [0, 0, 0, 1]")
    return pose


def resize_to(rgb: np.ndarray, K: np.ndarray, size_hw: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
    """Resize a colour image to ``size_hw`` (area interpolation down, linear up) and scale its intrinsics to match.

    With ``s_x = W'/W``, ``s_y = H'/H`` and integer pixel centres: ``fx' = s_x fx``, ``fy' = s_y fy``, ``skew' = s_x
    skew``, ``cx' = s_x (cx + 0.5) - 0.5``, ``cy' = s_y (cy + 0.5) - 0.5``.
    """
    H, W = rgb.shape[:2]
    H2, W2 = size_hw
    if (H, W) == (H2, W2):
        return rgb, np.asarray(K, np.float64)
    sx, sy = W2 / W, H2 / H
    interp = cv2.INTER_AREA if W2 < W else cv2.INTER_LINEAR
    out = cv2.resize(rgb, (W2, H2), interpolation=interp)
    S = np.array([[sx, 0, 0.5 * sx - 0.5], [0, sy, 0.5 * sy - 0.5], [0, 0, 1]])
    return out, S @ np.asarray(K, np.float64)


def read_objects(folder: Path) -> CaptureObjects | None:
    """The optional ``threedq_objects.json`` of a capture folder, or ``None``: ``{"objects": [{"category": name,
    "capture_T_box": 4x4 rows (box-local centre at the origin, local z up), "size": [sx, sy, sz]}, ...]}``."""
    path = folder / OBJECTS_NAME
    if not path.is_file():
        return None
    try:
        d = json.loads(path.read_text(encoding="utf-8"))
        objs: list[dict[str, Any]] = d["objects"]
        poses = np.array([o["capture_T_box"] for o in objs], np.float64).reshape(-1, 4, 4)
        size = np.array([o["size"] for o in objs], np.float64).reshape(-1, 3)
        cats = [str(o["category"]) for o in objs]
    except (json.JSONDecodeError, KeyError, TypeError, ValueError) as e:
        why = f"expected {{'objects': [{{category, capture_T_box, size}}]}}: {e}"
        raise SceneValidationError(str(path), "objects", why) from e
    for m, p in enumerate(poses):
        check_rigid(p, str(path), f"objects[{m}].capture_T_box")
    if np.any(size <= 0):
        raise SceneValidationError(str(path), "size", "box extents must be positive")
    return CaptureObjects(poses, size, cats)


@dataclass
class Frame:
    """One frame of a capture before its pixels are read: ``world_T_cam`` ``[4,4]`` (checked) and ``load()``
    returning ``(rgb [H,W,3] u8, depth [H,W] f32 metres, K [3,3], depth file)`` or raising
    :class:`~threedq.scene.SceneValidationError` naming the file and field."""

    frame_id: str
    world_T_cam: np.ndarray
    load: Callable[[], tuple[np.ndarray, np.ndarray, np.ndarray, str]]


def png_frame(frame_id: str, pose: np.ndarray, rgb: Path, depth: Path, units_per_metre: float, K: np.ndarray) -> Frame:
    """A :class:`Frame` of a colour image file and a 16-bit depth PNG of ``units_per_metre`` units per metre."""
    return Frame(frame_id, pose, lambda: (read_rgb(rgb), read_depth_png(depth, units_per_metre), K, str(depth)))


def farthest_order(centres: np.ndarray) -> np.ndarray:
    """All indices of ``centres`` ``[V,3]`` in farthest-point order from index 0 (ties: the lowest index)."""
    V = centres.shape[0]
    order = [0]
    dist = np.linalg.norm(centres - centres[0], axis=1)
    dist[0] = -1
    for _ in range(V - 1):
        i = int(np.argmax(dist))
        order.append(i)
        dist = np.minimum(dist, np.linalg.norm(centres - centres[i], axis=1))
        dist[order] = -1
    return np.array(order, np.int64)


def load_frames(
    frames: list[Frame], source: str, fmt: str, skipped: list[FrameSkip], folder: Path, max_views: int | None = None
) -> Capture:
    """Read the pixels of at most ``max_views`` frames (``None``: all) into a :class:`Capture` (in capture order),
    with the objects of ``folder`` (:func:`read_objects`).

    Frames are read in farthest-camera-position order; one that fails to load, whose depth and colour sizes differ, or
    whose size differs from the first read frame's is skipped and counted, and the next farthest is read instead.
    """
    objects = read_objects(folder)
    if max_views is not None and max_views < 1:
        raise ValueError(f"max_views: expected >= 1 or None, got {max_views}")
    order = farthest_order(np.array([f.world_T_cam[:3, 3] for f in frames])) if frames else np.zeros(0, np.int64)
    kept: dict[int, tuple[np.ndarray, np.ndarray, np.ndarray]] = {}
    shape: tuple[int, ...] | None = None
    for i in order:
        if max_views is not None and len(kept) >= max_views:
            break
        f = frames[int(i)]
        try:
            rgb, depth, K, depth_file = f.load()
        except SceneValidationError as e:
            skipped.append(FrameSkip(e.source, e.field, e.reason))
            continue
        hw = list(rgb.shape[:2])
        if depth.shape != rgb.shape[:2]:
            skipped.append(FrameSkip(depth_file, "depth", f"depth is {list(depth.shape)} but colour is {hw}"))
            continue
        if shape is not None and rgb.shape != shape:
            why = f"frame {f.frame_id}: size {hw} differs from the first read frame's {list(shape[:2])}"
            skipped.append(FrameSkip(depth_file, "rgb", why))
            continue
        shape = rgb.shape
        kept[int(i)] = (rgb, depth, np.asarray(K, np.float64))
    if not kept:
        reasons = "; ".join(dict.fromkeys(str(s) for s in skipped[:3])) or "no frames found"
        raise SceneValidationError(source, "frames", f"no usable frame ({reasons})")
    idx = sorted(kept)
    rgb, depth, K = (np.stack([kept[i][j] for i in idx]) for j in range(3))
    depth = depth.astype(np.float32)
    depth[~np.isfinite(depth) | (depth < 0)] = 0
    poses = np.stack([frames[i].world_T_cam for i in idx]).astype(np.float64)
    return Capture(rgb=rgb, depth=depth, K=K, world_T_cam=poses, frame_ids=[frames[i].frame_id for i in idx],
                   source=source, format=fmt, skipped=skipped, objects=objects, num_frames=len(frames))
