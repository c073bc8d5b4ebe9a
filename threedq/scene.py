"""The canonical posed multi-view RGB-D scene record, its ``.npz`` file and the dataset ``index.json``.

Keys of a :class:`SceneRecord` (``V`` views of ``H x W`` pixels, ``M`` objects):

- ``rgb`` [V,H,W,3] u8; ``depth`` [V,H,W] f32 metric z-depth (camera-frame z), 0 = invalid;
- ``K`` [V,3,3] f32 pinhole intrinsics, pixel centres at integer (u, v);
- ``world_T_cam`` [V,4,4] f32 camera-to-world pose, OpenCV camera axes (x right, y down, z forward);
- ``instance`` [V,H,W] i32, optional: 0 = background, object ``i`` (1-based row of boxes) -> i;
- ``boxes`` [M,7] f32 ``(cx, cy, cz, sx, sy, sz, yaw)`` in the world frame; ``categories`` [M] i64 category ids.

Convention: world frame in metres, right-handed, **z up**, centred on the scene; yaw about +z, counter-clockwise seen
from above, radians; ``a_T_b`` maps points in frame b to frame a. Files are written atomically and deterministically.
"""

from __future__ import annotations

import json
import zipfile
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from threedq.atomic_io import atomic_write_bytes, atomic_write_json, npz_bytes
from threedq.boxes import box_corners
from threedq.errors import InputError

__all__ = [
    "INDEX_NAME", "DatasetIndex", "SceneRecord", "SceneValidationError", "load_index", "load_scene", "load_scene_boxes",
    "load_scene_gt", "save_index", "save_scene", "validate_scene",
]  # fmt: skip

INDEX_NAME = "index.json"
INDEX_FORMAT = "threedq-scenes"
INDEX_VERSION = 1
INDEX_SPLITS = ("train", "val", "test")
#: the required arrays of a scene file and their canonical dtypes
_DTYPES = {"rgb": np.uint8, "depth": np.float32, "K": np.float32, "world_T_cam": np.float32, "boxes": np.float32,
           "categories": np.int64}  # fmt: skip
REQUIRED_KEYS = tuple(_DTYPES)
_ROT_TOL = 1e-3
_BOUNDS_TOL = 1e-3
#: ``((xmin, ymin, zmin), (xmax, ymax, zmax))``
Bounds = tuple[tuple[float, float, float], tuple[float, float, float]]


class SceneValidationError(InputError):
    """A scene record or file breaks the canonical format. The message names the file and field."""

    def __init__(self, source: str, field_name: str, message: str) -> None:
        message = " ".join(str(message).split())  # always one line (a library's reason may span several)
        self.source, self.field, self.reason = source, field_name, message
        super().__init__(f"{source}: field '{field_name}': {message}")


@dataclass
class SceneRecord:
    """One posed multi-view RGB-D scene with its objects (keys, shapes and convention in the module docstring)."""

    rgb: np.ndarray
    depth: np.ndarray
    K: np.ndarray
    world_T_cam: np.ndarray
    boxes: np.ndarray
    categories: np.ndarray
    instance: np.ndarray | None = None
    meta: dict[str, Any] = field(default_factory=dict)

    @property
    def num_views(self) -> int:
        return int(self.rgb.shape[0])

    @property
    def num_objects(self) -> int:
        return int(self.boxes.shape[0])

    @property
    def image_size(self) -> tuple[int, int]:
        """``(H, W)``."""
        return int(self.rgb.shape[1]), int(self.rgb.shape[2])

    def arrays(self) -> dict[str, np.ndarray]:
        """The on-disk arrays in canonical dtypes (``meta`` is stored as a JSON string array)."""
        out = {k: np.ascontiguousarray(getattr(self, k), dtype=dtype) for k, dtype in _DTYPES.items()}
        out["boxes"], out["categories"] = out["boxes"].reshape(-1, 7), out["categories"].reshape(-1)
        if self.instance is not None:
            out["instance"] = np.ascontiguousarray(self.instance, dtype=np.int32)
        if self.meta:
            out["meta"] = np.array(json.dumps(self.meta, sort_keys=True))
        return out


def _check_finite(source: str, name: str, a: np.ndarray) -> None:
    if not np.all(np.isfinite(a)):
        bad = int(np.size(a) - np.count_nonzero(np.isfinite(a)))
        raise SceneValidationError(source, name, f"{bad} non-finite value(s) (NaN or inf)")


def validate_scene(record: SceneRecord, source: str = "<in-memory scene>", bounds: Bounds | None = None,
                   num_categories: int | None = None) -> SceneRecord:  # fmt: skip
    """``record``, unchanged, after checking it against the canonical format (and that every box corner lies in
    ``bounds``, every category id below ``num_categories``); :class:`SceneValidationError` naming ``source`` (usually
    the file path) on the first fault."""

    def check(bad: Any, name: str, message: str) -> None:
        if bad:
            raise SceneValidationError(source, name, message)

    rgb, depth, K, pose, inst = record.rgb, record.depth, record.K, record.world_T_cam, record.instance
    check(rgb.ndim != 4 or rgb.shape[-1] != 3, "rgb", f"expected shape [V,H,W,3], got {list(rgb.shape)}")
    check(rgb.dtype != np.uint8, "rgb", f"expected dtype uint8, got {rgb.dtype}")
    V, H, W = rgb.shape[:3]
    check(V < 1 or H < 1 or W < 1, "rgb", f"no pixels or no views: shape {list(rgb.shape)}")
    check(depth.shape != (V, H, W), "depth", f"expected shape {[V, H, W]} to match rgb, got {list(depth.shape)}")
    check(not np.issubdtype(depth.dtype, np.floating), "depth", f"expected a float dtype (metres), got {depth.dtype}")
    _check_finite(source, "depth", depth)
    if np.any(depth < 0):
        raise SceneValidationError(source, "depth", f"{int(np.count_nonzero(depth < 0))} negative value(s)")
    blank = np.nonzero(~np.any(depth > 0, axis=(1, 2)))[0]
    if blank.size:
        why = f"view {int(blank[0])} has no valid depth at all (every pixel 0; {blank.size} such view(s))"
        raise SceneValidationError(source, "depth", f"{why}; drop the view(s) from the capture")
    check(K.shape != (V, 3, 3), "K", f"expected shape {[V, 3, 3]}, got {list(K.shape)}")
    _check_finite(source, "K", K)
    check(np.any(K[:, 0, 0] <= 0) or np.any(K[:, 1, 1] <= 0), "K", "focal lengths K[0,0], K[1,1] must be positive")
    check(pose.shape != (V, 4, 4), "world_T_cam", f"expected shape {[V, 4, 4]}, got {list(pose.shape)}")
    _check_finite(source, "world_T_cam", pose)
    Rm = pose[:, :3, :3].astype(np.float64)
    ortho_err = np.abs(np.swapaxes(Rm, 1, 2) @ Rm - np.eye(3)).max(axis=(1, 2))
    dets = np.linalg.det(Rm)
    bad_views = np.nonzero((ortho_err > _ROT_TOL) | (np.abs(dets - 1) > _ROT_TOL))[0]
    if bad_views.size:
        v = int(bad_views[0])
        why = f"max |R^T R - I| = {ortho_err[v]:.3g}, det = {dets[v]:.4g}"
        raise SceneValidationError(source, "world_T_cam", f"view {v}: rotation is not rigid ({why})")
    check(np.abs(pose[:, 3] - np.array([0, 0, 0, 1])).max() > 1e-6, "world_T_cam", "last row must be [0, 0, 0, 1]")
    if inst is not None:
        check(inst.shape != (V, H, W), "instance", f"expected shape {[V, H, W]} to match rgb, got {list(inst.shape)}")
        check(not np.issubdtype(inst.dtype, np.integer), "instance", f"expected an integer dtype, got {inst.dtype}")
    boxes, cats = record.boxes, record.categories
    check(boxes.ndim != 2 or boxes.shape[1] != 7, "boxes", f"expected shape [M,7], got {list(boxes.shape)}")
    M = boxes.shape[0]
    why = "only an imported capture marked 'unannotated' in its meta may have none"
    check(M == 0 and not record.meta.get("unannotated", False), "boxes", f"empty scene: no objects ({why})")
    _check_finite(source, "boxes", boxes)
    check(np.any(boxes[:, 3:6] <= 0), "boxes", "box extents (sx, sy, sz) must be positive")
    check(cats.shape != (M,), "categories", f"expected shape [{M}] to match boxes, got {list(cats.shape)}")
    bad = not np.issubdtype(cats.dtype, np.integer) or np.any(cats < 0)
    check(bad, "categories", "expected non-negative integer category ids")
    if num_categories is not None and np.any(cats >= num_categories):
        why = f"id {int(cats.max())} >= number of categories {num_categories} in index.json"
        raise SceneValidationError(source, "categories", why)
    if inst is not None and inst.max(initial=0) > M:
        raise SceneValidationError(source, "instance", f"id {int(inst.max())} > number of objects {M}")
    if bounds is not None:
        lo, hi = np.asarray(bounds[0], np.float64), np.asarray(bounds[1], np.float64)
        corners = box_corners(boxes.astype(np.float64))
        outside = np.any((corners < lo - _BOUNDS_TOL) | (corners > hi + _BOUNDS_TOL), axis=(1, 2))
        if np.any(outside):
            where = f"the scene bounds {lo.tolist()} .. {hi.tolist()}"
            raise SceneValidationError(source, "boxes", f"object {int(np.argmax(outside))} lies outside {where}")
    return record


def save_scene(path: str | Path, record: SceneRecord, validate: bool = True) -> Path:
    """Write ``record`` to a compressed ``.npz`` atomically and deterministically (same record -> same bytes)."""
    path = Path(path)
    if validate:
        validate_scene(record, source=str(path))
    return atomic_write_bytes(path, npz_bytes(record.arrays()))


def _read_npz(path: Path, keys: tuple[str, ...], optional: tuple[str, ...] = ()) -> dict[str, Any]:
    """The arrays ``keys`` (each required) and ``optional`` (where present) of a scene ``.npz``, and no other;
    :class:`SceneValidationError` naming the file and field on any fault."""
    source = str(path)
    if not path.is_file():
        raise SceneValidationError(source, "<file>", "no such file")
    if not zipfile.is_zipfile(path):  # np.load would take other bytes for a pickle or a .npy and say so
        raise SceneValidationError(source, "<file>", "not a .npz (zip) archive: truncated, or another kind of file")
    try:
        with np.load(path, allow_pickle=False) as npz:
            missing = [k for k in keys if k not in npz.files]
            if missing:
                raise SceneValidationError(source, missing[0], "missing key")
            arrays: dict[str, Any] = {}
            for k in [k for k in (*keys, *optional) if k in npz.files]:
                try:
                    arrays[k] = npz[k]
                except (zipfile.BadZipFile, ValueError, OSError, EOFError) as e:
                    raise SceneValidationError(source, k, f"cannot be read (corrupt data: {e})") from e
    except SceneValidationError:
        raise
    except (zipfile.BadZipFile, ValueError, OSError, EOFError) as e:
        raise SceneValidationError(source, "<file>", f"not a readable .npz archive (truncated or corrupt: {e})") from e
    return arrays


def load_scene_boxes(path: str | Path) -> np.ndarray:
    """The ``boxes`` ``[G, 7]`` ``(cx, cy, cz, sx, sy, sz, yaw)`` of a scene ``.npz`` as stored, reading nothing else.
    Not validated; errors as :func:`load_scene`'s."""
    return _read_npz(Path(path), ("boxes",))["boxes"]


def load_scene_gt(path: str | Path) -> tuple[np.ndarray, np.ndarray]:
    """The ``boxes`` ``[G, 7]`` and ``categories`` ``[G]`` of a scene ``.npz`` as stored, reading nothing else.
    Not validated; errors as :func:`load_scene`'s."""
    arrays = _read_npz(Path(path), ("boxes", "categories"))
    return arrays["boxes"], arrays["categories"]


def load_scene(path: str | Path, validate: bool = True, bounds: Bounds | None = None,
               num_categories: int | None = None) -> SceneRecord:  # fmt: skip
    """Read a scene ``.npz``; raise :class:`SceneValidationError` naming the file and field on any fault (missing,
    truncated or corrupt file, missing key, invalid value)."""
    path = Path(path)
    source = str(path)
    arrays = _read_npz(path, REQUIRED_KEYS, ("instance", "meta"))
    meta: dict[str, Any] = {}
    if "meta" in arrays:
        try:
            meta = json.loads(str(arrays.pop("meta")))
        except json.JSONDecodeError as e:
            raise SceneValidationError(source, "meta", f"not valid JSON: {e}") from e
    record = SceneRecord(**arrays, meta=meta)
    if validate:
        validate_scene(record, source=source, bounds=bounds, num_categories=num_categories)
    return record


@dataclass
class DatasetIndex:
    """Contents of a dataset folder's ``index.json``.

    ``scenes`` holds ``{"file": relative path, "split": "train"|"val"|"test"}`` entries; ``symmetry_order`` holds, per
    category, how many yaw angles map the shape onto itself (1 = asymmetric, 4 = 90 deg, 0 = continuous).
    """

    categories: list[str]
    symmetry_order: list[int]
    scenes: list[dict[str, str]]
    scene_bounds: Bounds
    generator: dict[str, Any] = field(default_factory=dict)
    seed: int | None = None

    @property
    def symmetric(self) -> list[bool]:
        return [o != 1 for o in self.symmetry_order]

    def files(self, split: str | None = None) -> list[str]:
        return [s["file"] for s in self.scenes if split is None or s["split"] == split]

    def to_dict(self) -> dict[str, Any]:
        bounds = {"min": list(self.scene_bounds[0]), "max": list(self.scene_bounds[1])}
        return {"format": INDEX_FORMAT, "version": INDEX_VERSION, "categories": list(self.categories),
                "symmetry_order": [int(o) for o in self.symmetry_order], "symmetric": self.symmetric,
                "scene_bounds": bounds, "generator": self.generator, "seed": self.seed, "scenes": self.scenes}


def save_index(folder: str | Path, index: DatasetIndex) -> Path:
    """Write ``folder/index.json`` atomically."""
    return atomic_write_json(Path(folder) / INDEX_NAME, index.to_dict())


def load_index(folder: str | Path) -> DatasetIndex:
    """Read and check ``folder/index.json``; errors name the file and field."""
    path = Path(folder) / INDEX_NAME

    def err(name: str, message: str) -> SceneValidationError:
        return SceneValidationError(str(path), name, message)

    if not path.is_file():
        raise err("<file>", "no such file (is this a threedq dataset folder?)")
    try:
        d = json.loads(path.read_text(encoding="utf-8"))
    except (json.JSONDecodeError, UnicodeDecodeError) as e:
        raise err("<file>", f"not valid JSON: {e}") from e
    if not isinstance(d, dict):
        raise err("<file>", "expected a JSON object")
    if d.get("format") != INDEX_FORMAT:
        raise err("format", f"expected {INDEX_FORMAT!r}, got {d.get('format')!r}")
    for key in ("categories", "symmetry_order", "scenes", "scene_bounds"):
        if key not in d:
            raise err(key, "missing key")
    cats, sym, scenes = d["categories"], d["symmetry_order"], d["scenes"]
    if not isinstance(cats, list) or not all(isinstance(c, str) for c in cats):
        raise err("categories", "expected a list of names")
    if not isinstance(sym, list) or len(sym) != len(cats):
        raise err("symmetry_order", f"expected {len(cats)} integers, one per category")
    if not isinstance(scenes, list) or not all(isinstance(s, dict) and "file" in s and "split" in s for s in scenes):
        raise err("scenes", "expected a list of {'file': ..., 'split': ...} entries")
    for i, s in enumerate(scenes):
        if s["split"] not in INDEX_SPLITS:
            why = f"unknown split {s['split']!r} (expected one of {', '.join(INDEX_SPLITS)})"
            raise err("scenes", f"entry {i} ({s['file']!r}): {why}")
        if not isinstance(s["file"], str) or not s["file"]:
            raise err("scenes", f"entry {i}: 'file' must be a relative path, got {s['file']!r}")
    try:
        lo = tuple(float(x) for x in d["scene_bounds"]["min"])
        hi = tuple(float(x) for x in d["scene_bounds"]["max"])
        assert len(lo) == 3 and len(hi) == 3
    except (KeyError, TypeError, ValueError, AssertionError) as e:
        raise err("scene_bounds", "expected {'min': [x, y, z], 'max': [x, y, z]}") from e
    sym = [int(o) for o in sym]
    return DatasetIndex(cats, sym, scenes, (lo, hi), d.get("generator", {}), d.get("seed"))  # type: ignore[arg-type]
