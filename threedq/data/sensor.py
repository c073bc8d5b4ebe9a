"""Capture conditions of a consumer RGB-D sensor, applied to clean rendered views.

Each effect ``f(array, rng, level)`` returns a new array of the input's shape and dtype, never modifies its input and
draws only from ``rng``. ``level`` scales an effect: 0 returns a copy, 1 is a Kinect-like structured-light camera, 2
doubles every magnitude. :func:`apply_capture` applies a set of them to a :class:`~threedq.scene.SceneRecord` (or a
dict of its arrays); boxes, intrinsics and instance masks are kept.

Convention: metres; depth ``[..., H, W]`` is camera-frame z (OpenCV axes, z forward), 0 = no measurement; poses are
camera-to-world ``[V, 4, 4]``; world z up (see :mod:`threedq.scene`).
"""

from __future__ import annotations

import copy
import dataclasses
import math
import numbers
import zlib
from collections.abc import Iterable
from pathlib import Path
from statistics import NormalDist
from typing import Any

import cv2
import numpy as np

from threedq.scene import SceneRecord

__all__ = ["EFFECTS", "apply_capture", "axial_noise", "degrade_dataset", "drop_depth", "effect_names", "exposure",
           "pose_drift", "quantise_disparity", "tilt_gravity"]

#: The effects, in the order :func:`apply_capture` applies them (dropout first: it finds the geometry's depth jumps).
EFFECTS: tuple[str, ...] = ("drop_depth", "axial_noise", "quantise_disparity", "exposure", "pose_drift", "tilt_gravity")

_EDGE_JUMP_M = 0.05  # pixels beside a depth jump larger than this lose their depth more often
_DROP_CLUSTER_PX = 1.5  # std of the Gaussian that smooths the dropout field: clusters of a few pixels
_DRIFT_VIEWS = 3.0  # std (in views) of the Gaussian that correlates the pose errors along the sequence


def _level(level: Any, name: str = "level") -> float:
    if isinstance(level, bool) or not isinstance(level, numbers.Real) or not math.isfinite(level) or level < 0:
        raise ValueError(f"{name}: expected a finite number >= 0, got {level!r}")
    return float(level)


def _depth(depth: Any) -> np.ndarray:
    depth = np.asarray(depth)
    if depth.ndim < 2 or not np.issubdtype(depth.dtype, np.floating):
        raise ValueError(f"depth: expected a float array [..., H, W] of metres, got {depth.dtype} {list(depth.shape)}")
    return depth


def _poses(poses: Any) -> np.ndarray:
    poses = np.asarray(poses)
    if poses.ndim != 3 or poses.shape[1:] != (4, 4) or not np.issubdtype(poses.dtype, np.floating):
        raise ValueError(f"poses: expected a float array [V, 4, 4], got {poses.dtype} {list(poses.shape)}")
    return poses


def _rotation(rotvec: np.ndarray) -> np.ndarray:
    """Rotation matrices ``[..., 3, 3]`` of rotation vectors ``[..., 3]`` (axis times angle, radians; Rodrigues)."""
    angle = np.linalg.norm(rotvec, axis=-1)[..., None, None]
    axis = rotvec / np.maximum(angle[..., 0], 1e-12)
    x, y, z = axis[..., 0], axis[..., 1], axis[..., 2]
    zero = np.zeros_like(x)
    k = np.stack([zero, -z, y, z, zero, -x, -y, x, zero], axis=-1).reshape(*axis.shape[:-1], 3, 3)
    return np.eye(3) + np.sin(angle) * k + (1 - np.cos(angle)) * (k @ k)


def axial_noise(depth: np.ndarray, rng: np.random.Generator, level: float) -> np.ndarray:
    """Add Gaussian depth noise of std ``level * (0.0012 + 0.0019 * (z - 0.4)^2)`` metres (Nguyen, Izadi and Lovell
    2012) to ``depth`` ``[..., H, W]``. Pixels without depth (0) stay 0; a noisy value below 0 becomes 0."""
    depth, level = _depth(depth), _level(level)
    if level == 0:
        return depth.copy()
    z = depth.astype(np.float64)
    sigma = level * (0.0012 + 0.0019 * (z - 0.4) ** 2)
    noisy = np.maximum(z + sigma * rng.standard_normal(z.shape), 0.0)
    return np.where(z > 0, noisy, 0.0).astype(depth.dtype)


def quantise_disparity(depth: np.ndarray, level: float) -> np.ndarray:
    """Round the disparity ``1 / z`` of ``depth`` ``[..., H, W]`` to multiples of ``q = level * 2.85e-3`` per metre:
    depth steps of about ``q z^2`` (Khoshelham and Elberink 2012). Pixels without depth (0) stay 0, and so does a depth
    too far to have a non-zero disparity step."""
    depth, level = _depth(depth), _level(level)
    if level == 0:
        return depth.copy()
    q = level * 2.85e-3
    z = depth.astype(np.float64)
    steps = np.round(np.divide(1.0, z, out=np.zeros_like(z), where=z > 0) / q)
    return np.divide(1.0, steps * q, out=np.zeros_like(z), where=steps > 0).astype(depth.dtype)


def _beside_jump(depth: np.ndarray) -> np.ndarray:
    """``[..., H, W]`` bool: pixels beside a depth jump of more than 5 cm along a row or column, measured against the
    plane through the two neighbours as ``|d[i-1] - 2 d[i] + d[i+1]| * z[i]^2`` metres (``d = 1 / z``). Pixels without
    depth, or next to one, and border pixels are never beside a jump.
    """
    z = depth.astype(np.float64)
    d = np.divide(1.0, z, out=np.zeros_like(z), where=z > 0)
    edge = np.zeros(depth.shape, dtype=bool)
    for axis in (-1, -2):
        a, b = np.moveaxis(d, axis, -1), np.moveaxis(z, axis, -1)
        valid = (a[..., :-2] > 0) & (a[..., 1:-1] > 0) & (a[..., 2:] > 0)
        jump = np.abs(a[..., :-2] - 2 * a[..., 1:-1] + a[..., 2:]) * b[..., 1:-1] ** 2 > _EDGE_JUMP_M
        np.moveaxis(edge, axis, -1)[..., 1:-1] |= valid & jump  # a view: writes go to ``edge``
    return edge


def drop_depth(depth: np.ndarray, rng: np.random.Generator, level: float) -> np.ndarray:
    """Remove depth (set 0) of ``depth`` ``[..., H, W]`` in small clusters, mostly beside depth jumps: a white-noise
    field smoothed with a Gaussian (std 1.5 pixels), scaled to unit variance, drops a pixel where it exceeds the
    standard normal's upper ``p`` quantile, ``p = min(1, 0.5 * level)`` beside a jump, ``min(1, 0.02 * level)``
    elsewhere."""
    depth, level = _depth(depth), _level(level)
    if level == 0:
        return depth.copy()
    H, W = depth.shape[-2:]
    noise = rng.standard_normal((int(np.prod(depth.shape[:-2], dtype=np.int64)), H, W)).astype(np.float32)
    kernel = cv2.getGaussianKernel(int(2 * math.ceil(3 * _DROP_CLUSTER_PX) + 1), _DROP_CLUSTER_PX)
    unit = float((kernel**2).sum())  # std of the smoothed field away from the border
    field = np.stack([cv2.sepFilter2D(n, -1, kernel, kernel) / unit for n in noise]).reshape(depth.shape)

    def threshold(p: float) -> float:
        return math.inf if p <= 0 else -math.inf if p >= 1 else NormalDist().inv_cdf(1 - p)

    limit = np.where(_beside_jump(depth), threshold(min(1.0, 0.5 * level)), threshold(min(1.0, 0.02 * level)))
    return np.where(field > limit, 0, depth).astype(depth.dtype)


def exposure(rgb: np.ndarray, rng: np.random.Generator, level: float) -> np.ndarray:
    """Change each view's exposure and white balance of ``rgb`` ``[V, H, W, 3]`` (uint8 0..255 or float 0..1) and add
    pixel noise: view ``v`` channel ``c`` times ``g_v * w_vc`` (``g_v`` uniform in ``1 +- 0.2 * level``, ``w_vc`` in
    ``1 +- 0.15 * level``, both at least 0), plus Gaussian noise of std ``0.01 * level`` of the range, clipped."""
    rgb, level = np.asarray(rgb), _level(level)
    if rgb.ndim != 4 or rgb.shape[-1] != 3 or not (rgb.dtype == np.uint8 or np.issubdtype(rgb.dtype, np.floating)):
        raise ValueError(f"rgb: expected a uint8 or float array [V, H, W, 3], got {rgb.dtype} {list(rgb.shape)}")
    if level == 0:
        return rgb.copy()
    full = 255.0 if rgb.dtype == np.uint8 else 1.0
    V = rgb.shape[0]
    gain = np.maximum(1 + 0.2 * level * rng.uniform(-1, 1, (V, 1)), 0)
    balance = np.maximum(1 + 0.15 * level * rng.uniform(-1, 1, (V, 3)), 0)
    out = rgb.astype(np.float64) * (gain * balance)[:, None, None, :]
    out = np.clip(out + 0.01 * level * full * rng.standard_normal(rgb.shape), 0, full)
    return np.round(out).astype(np.uint8) if rgb.dtype == np.uint8 else out.astype(rgb.dtype)


def pose_drift(poses: np.ndarray, rng: np.random.Generator, level: float) -> np.ndarray:
    """Perturb each camera pose ``[V, 4, 4]`` by a small rigid motion ``world_T_cam @ [R | t]`` that drifts smoothly
    along the view sequence: white noise smoothed over the view index (Gaussian, std 3 views), scaled to a
    root-mean-square angle of ``level`` degrees and length of ``level`` cm."""
    poses, level = _poses(poses), _level(level)
    if level == 0:
        return poses.copy()
    V = poses.shape[0]
    radius = math.ceil(3 * _DRIFT_VIEWS)
    kernel = np.exp(-0.5 * (np.arange(-radius, radius + 1) / _DRIFT_VIEWS) ** 2)
    kernel /= np.sqrt((kernel**2).sum())  # unit variance after smoothing
    white = rng.standard_normal((V + 2 * radius, 6))
    smooth = np.stack([np.convolve(white[:, j], kernel, mode="valid") for j in range(6)], axis=1)  # [V, 6]
    rotvec = smooth[:, :3] * math.radians(level) / math.sqrt(3)  # rms angle = level degrees
    shift = smooth[:, 3:] * 0.01 * level / math.sqrt(3)  # rms length = level cm
    delta = np.tile(np.eye(4), (V, 1, 1))
    delta[:, :3, :3] = _rotation(rotvec)
    delta[:, :3, 3] = shift
    return (poses.astype(np.float64) @ delta).astype(poses.dtype)


def tilt_gravity(poses: np.ndarray, rng: np.random.Generator, level: float) -> np.ndarray:
    """Tilt the world frame of poses ``[V, 4, 4]``: each becomes ``G @ world_T_cam``, ``G`` a rotation of ``2 * level``
    degrees about the horizontal axis ``(cos a, sin a, 0)`` through the origin (``a`` uniform)."""
    poses, level = _poses(poses), _level(level)
    if level == 0:
        return poses.copy()
    a = rng.uniform(0, 2 * math.pi)
    G = np.eye(4)
    G[:3, :3] = _rotation(np.array([math.cos(a), math.sin(a), 0.0]) * math.radians(2.0 * level))
    return (G @ poses.astype(np.float64)).astype(poses.dtype)


def effect_names(effects: Iterable[str] | None, argument: str = "effects") -> tuple[str, ...]:
    """``effects`` checked and in the order of :data:`EFFECTS` (``None`` = all); a ``ValueError`` names ``argument``."""
    if effects is None:
        return EFFECTS
    if isinstance(effects, str) or not all(isinstance(e, str) for e in effects):
        raise ValueError(f"{argument}: expected a collection of effect names or None, got {effects!r}")
    effects = set(effects)
    unknown = sorted(effects - set(EFFECTS))
    if unknown:
        raise ValueError(f"{argument}: unknown effect(s) {unknown}; expected names from {', '.join(EFFECTS)}")
    return tuple(e for e in EFFECTS if e in effects)


#: effect name -> (the array it changes, the function called as ``f(array, rng, level)``)
_APPLY = {"axial_noise": ("depth", axial_noise), "drop_depth": ("depth", drop_depth), "exposure": ("rgb", exposure),
          "quantise_disparity": ("depth", lambda depth, rng, level: quantise_disparity(depth, level)),
          "pose_drift": ("world_T_cam", pose_drift), "tilt_gravity": ("world_T_cam", tilt_gravity)}


def apply_capture(scene: SceneRecord | dict[str, np.ndarray], rng: np.random.Generator, level: float,
                  effects: Iterable[str] | None = None) -> SceneRecord | dict[str, np.ndarray]:
    """Apply the chosen effects (``None`` = all), in the order of :data:`EFFECTS`, to a scene's rgb, depth and poses.

    ``scene`` is a :class:`~threedq.scene.SceneRecord` or a dict with ``rgb``, ``depth`` and ``world_T_cam`` (other keys
    are passed on). Each effect draws from its own child stream of ``rng``. Returns the same kind as ``scene`` with new
    arrays; a record's ``meta`` gains ``capture: {"level", "effects"}`` when ``level > 0``.
    """
    level, effects = _level(level), effect_names(effects)
    is_record = isinstance(scene, SceneRecord)
    given = {f.name: getattr(scene, f.name) for f in dataclasses.fields(scene)} if is_record else dict(scene)
    for key in ("rgb", "depth", "world_T_cam"):
        if key not in given:
            raise ValueError(f"scene: missing '{key}'")
    arrays = {k: v.copy() if isinstance(v, np.ndarray) else copy.deepcopy(v) for k, v in given.items()}
    if level > 0:
        streams = dict(zip(EFFECTS, rng.spawn(len(EFFECTS))))
        for name in effects:
            key, effect = _APPLY[name]
            arrays[key] = effect(arrays[key], streams[name], level)
    if not is_record:
        return arrays
    if level > 0:
        arrays["meta"]["capture"] = {"level": level, "effects": list(effects)}
    return SceneRecord(**arrays)


def degrade_dataset(src: str | Path, out: str | Path, level: float, effects: Iterable[str] | None = None, seed: int = 0,
                    progress: bool = False, splits: Iterable[str] | None = None) -> int:
    """Copy the dataset folder ``src`` to ``out`` (not ``src``) with capture conditions (:func:`apply_capture`).

    Each scene keeps its relative path and layout; its random stream is seeded by ``seed`` and the file's relative
    path. Scenes already in ``out`` are kept (a killed run resumes); ``out/index.json`` is written last. With
    ``splits``, only those splits' scenes are degraded; the others are copied unchanged (hard links where possible).
    Returns the number of scenes written now.

    Raises:
        ValueError: ``out`` is ``src``, a bad level or effect name, a split the index does not hold; errors of a missing
            or corrupt scene name the file.
    """
    import os
    import shutil

    from tqdm import tqdm

    from threedq.scene import load_index, load_scene, save_index, save_scene

    src, out = Path(src), Path(out)
    level, effects = _level(level), effect_names(effects)
    if out.resolve() == src.resolve():
        raise ValueError(f"out: {out} is the source folder; write the copy elsewhere")
    index = load_index(src)
    held = {e.get("split") for e in index.scenes}
    if splits is not None:
        splits = set(splits)
        if not splits or not splits <= held:
            raise ValueError(f"splits: {sorted(splits)} not among the splits of {src / 'index.json'} ({sorted(held)})")
    written = 0
    for entry in tqdm(index.scenes, desc="threedq degrade", unit="scene", disable=not progress):
        rel = entry["file"]
        if (out / rel).is_file():
            continue
        if splits is not None and entry.get("split") not in splits:
            (out / rel).parent.mkdir(parents=True, exist_ok=True)
            tmp = out / (rel + ".tmp")
            tmp.unlink(missing_ok=True)
            try:
                os.link(src / rel, tmp)
            except OSError:  # another file system, or links not allowed
                shutil.copyfile(src / rel, tmp)
            os.replace(tmp, out / rel)
        else:
            rng = np.random.default_rng([seed, zlib.crc32(rel.encode())])
            save_scene(out / rel, apply_capture(load_scene(src / rel), rng, level, effects))
        written += 1
    save_index(out, index)
    return written
