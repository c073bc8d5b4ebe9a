"""The canonical posed multi-view RGB-D scene record, its ``.npz`` file and the dataset ``index.json``.

Every data source (the embedded generator, parsers of on-disk formats) produces a :class:`SceneRecord`;
every DataModule consumes only this record.

Per view ``v`` (``V`` views of ``H x W`` pixels):

==================  ==============  ===============================================================
key                 shape, dtype    meaning
==================  ==============  ===============================================================
``rgb``             [V,H,W,3] u8    colour
``depth``           [V,H,W] f32     metric z-depth (camera-frame z), 0 = invalid
``K``               [V,3,3] f32     pinhole intrinsics; pixel centres at integer (u, v)
``world_T_cam``     [V,4,4] f32     camera-to-world pose, OpenCV camera axes (x right, y down, z fwd)
``instance``        [V,H,W] i32     optional; 0 = background, object ``i`` (1-based row of boxes) -> i
==================  ==============  ===============================================================

Per object ``m`` (``M`` objects):

==================  ==============  ===============================================================
``boxes``           [M,7] f32       ``(cx, cy, cz, sx, sy, sz, yaw)`` in the world frame
``categories``      [M] i64         category id (names in ``index.json``)
==================  ==============  ===============================================================

Convention: world frame in metres, right-handed, **z up**, centred on the scene; yaw about +z,
counter-clockwise seen from above, radians; ``a_T_b`` maps points in frame b to frame a.

An ``index.json`` beside the scene files lists them with their split, the category names, which
categories are rotationally symmetric about the vertical, the scene bounds and the generator version
and seed. Files are written atomically (temporary file + rename) and deterministically.
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
    "SceneRecord",
    "SceneValidationError",
    "DatasetIndex",
    "validate_scene",
    "save_scene",
    "load_scene",
    "load_scene_gt",
    "load_scene_boxes",
    "load_index",
    "save_index",
    "INDEX_NAME",
]

INDEX_NAME = "index.json"
INDEX_FORMAT = "threedq-scenes"
INDEX_VERSION = 1
INDEX_SPLITS = ("train", "val", "test")
REQUIRED_KEYS = ("rgb", "depth", "K", "world_T_cam", "boxes", "categories")
_ROT_TOL = 1e-3
_BOUNDS_TOL = 1e-3


class SceneValidationError(InputError):
    """A scene record or file breaks the canonical format. The message names the file and field."""

    def __init__(self, source: str, field_name: str, message: str) -> None:
        message = " ".join(str(message).split())  # always one line (a library's reason may span several)
        self.source, self.field, self.reason = source, field_name, message
        super().__init__(f"{source}: field '{field_name}': {message}")


@dataclass
class SceneRecord:
    """One posed multi-view RGB-D scene with its objects (see the module docstring for shapes).

    Convention: world frame in metres, z up, centred on the scene; OpenCV camera axes; ``world_T_cam``
    camera-to-world; boxes ``(cx, cy, cz, sx, sy, sz, yaw)``, yaw counter-clockwise about +z.
    """

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
        out = {
            "rgb": np.ascontiguousarray(self.rgb, dtype=np.uint8),
            "depth": np.ascontiguousarray(self.depth, dtype=np.float32),
            "K": np.ascontiguousarray(self.K, dtype=np.float32),
            "world_T_cam": np.ascontiguousarray(self.world_T_cam, dtype=np.float32),
            "boxes": np.ascontiguousarray(self.boxes, dtype=np.float32).reshape(-1, 7),
            "categories": np.ascontiguousarray(self.categories, dtype=np.int64).reshape(-1),
        }
        if self.instance is not None:
            out["instance"] = np.ascontiguousarray(self.instance, dtype=np.int32)
        if self.meta:
            out["meta"] = np.array(json.dumps(self.meta, sort_keys=True))
        return out


def _check_finite(source: str, name: str, a: np.ndarray) -> None:
    if not np.all(np.isfinite(a)):
        bad = int(np.size(a) - np.count_nonzero(np.isfinite(a)))
        raise SceneValidationError(source, name, f"{bad} non-finite value(s) (NaN or inf)")


def validate_scene(
    record: SceneRecord,
    source: str = "<in-memory scene>",
    bounds: tuple[tuple[float, float, float], tuple[float, float, float]] | None = None,
    num_categories: int | None = None,
) -> SceneRecord:
    """Check a record against the canonical format; raise :class:`SceneValidationError` on the first fault.

    Args:
        record: the scene.
        source: what to name in the error (usually the file path).
        bounds: optional ``((xmin, ymin, zmin), (xmax, ymax, zmax))`` every box corner must lie in.
        num_categories: optional number of category names; category ids must be below it.

    Returns:
        The record, unchanged, so calls can be chained.

    Convention: see the module docstring.
    """
    rgb, depth, K, pose = record.rgb, record.depth, record.K, record.world_T_cam
    if rgb.ndim != 4 or rgb.shape[-1] != 3:
        raise SceneValidationError(source, "rgb", f"expected shape [V,H,W,3], got {list(rgb.shape)}")
    if rgb.dtype != np.uint8:
        raise SceneValidationError(source, "rgb", f"expected dtype uint8, got {rgb.dtype}")
    V, H, W = rgb.shape[:3]
    if V < 1 or H < 1 or W < 1:
        raise SceneValidationError(source, "rgb", f"no pixels or no views: shape {list(rgb.shape)}")
    if depth.shape != (V, H, W):
        raise SceneValidationError(source, "depth", f"expected shape {[V, H, W]} to match rgb, got {list(depth.shape)}")
    if not np.issubdtype(depth.dtype, np.floating):
        raise SceneValidationError(source, "depth", f"expected a float dtype (metres), got {depth.dtype}")
    _check_finite(source, "depth", depth)
    if np.any(depth < 0):
        raise SceneValidationError(source, "depth", f"{int(np.count_nonzero(depth < 0))} negative value(s)")
    blank = np.nonzero(~np.any(depth > 0, axis=(1, 2)))[0]
    if blank.size:
        raise SceneValidationError(source, "depth", f"view {int(blank[0])} has no valid depth at all (every pixel 0; "
                                   f"{blank.size} such view(s)); drop the view(s) from the capture")
    if K.shape != (V, 3, 3):
        raise SceneValidationError(source, "K", f"expected shape {[V, 3, 3]}, got {list(K.shape)}")
    _check_finite(source, "K", K)
    if np.any(K[:, 0, 0] <= 0) or np.any(K[:, 1, 1] <= 0):
        raise SceneValidationError(source, "K", "focal lengths K[0,0], K[1,1] must be positive")
    if pose.shape != (V, 4, 4):
        raise SceneValidationError(source, "world_T_cam", f"expected shape {[V, 4, 4]}, got {list(pose.shape)}")
    _check_finite(source, "world_T_cam", pose)
    Rm = pose[:, :3, :3].astype(np.float64)
    ortho_err = np.abs(np.swapaxes(Rm, 1, 2) @ Rm - np.eye(3)).max(axis=(1, 2))
    dets = np.linalg.det(Rm)
    bad_views = np.nonzero((ortho_err > _ROT_TOL) | (np.abs(dets - 1) > _ROT_TOL))[0]
    if bad_views.size:
        v = int(bad_views[0])
        raise SceneValidationError(
            source,
            "world_T_cam",
            f"view {v}: rotation is not rigid (max |R^T R - I| = {ortho_err[v]:.3g}, det = {dets[v]:.4g})",
        )
    if np.abs(pose[:, 3] - np.array([0, 0, 0, 1])).max() > 1e-6:
        raise SceneValidationError(source, "world_T_cam", "last row must be [0, 0, 0, 1]")
    if record.instance is not None:
        if record.instance.shape != (V, H, W):
            raise SceneValidationError(
                source, "instance", f"expected shape {[V, H, W]} to match rgb, got {list(record.instance.shape)}"
            )
        if not np.issubdtype(record.instance.dtype, np.integer):
            raise SceneValidationError(source, "instance", f"expected an integer dtype, got {record.instance.dtype}")
    boxes, cats = record.boxes, record.categories
    if boxes.ndim != 2 or boxes.shape[1] != 7:
        raise SceneValidationError(source, "boxes", f"expected shape [M,7], got {list(boxes.shape)}")
    M = boxes.shape[0]
    if M == 0 and not record.meta.get("unannotated", False):
        raise SceneValidationError(source, "boxes", "empty scene: no objects (only an imported capture marked "
                                   "'unannotated' in its meta may have none)")
    _check_finite(source, "boxes", boxes)
    if np.any(boxes[:, 3:6] <= 0):
        raise SceneValidationError(source, "boxes", "box extents (sx, sy, sz) must be positive")
    if cats.shape != (M,):
        raise SceneValidationError(source, "categories", f"expected shape [{M}] to match boxes, got {list(cats.shape)}")
    if not np.issubdtype(cats.dtype, np.integer) or np.any(cats < 0):
        raise SceneValidationError(source, "categories", "expected non-negative integer category ids")
    if num_categories is not None and np.any(cats >= num_categories):
        raise SceneValidationError(
            source, "categories", f"id {int(cats.max())} >= number of categories {num_categories} in index.json"
        )
    if record.instance is not None and record.instance.max(initial=0) > M:
        raise SceneValidationError(source, "instance", f"id {int(record.instance.max())} > number of objects {M}")
    if bounds is not None:
        lo, hi = np.asarray(bounds[0], np.float64), np.asarray(bounds[1], np.float64)
        corners = box_corners(boxes.astype(np.float64))
        outside = np.any((corners < lo - _BOUNDS_TOL) | (corners > hi + _BOUNDS_TOL), axis=(1, 2))
        if np.any(outside):
            m = int(np.nonzero(outside)[0][0])
            raise SceneValidationError(
                source, "boxes", f"object {m} lies outside the scene bounds {lo.tolist()} .. {hi.tolist()}"
            )
    return record


def save_scene(path: str | Path, record: SceneRecord, validate: bool = True) -> Path:
    """Write ``record`` to a compressed ``.npz`` atomically and deterministically (same record -> same bytes)."""
    path = Path(path)
    if validate:
        validate_scene(record, source=str(path))
    return atomic_write_bytes(path, npz_bytes(record.arrays()))


def _read_npz(path: Path, keys: tuple[str, ...], optional: tuple[str, ...] = ()) -> dict[str, Any]:
    """The arrays ``keys`` (each required) and ``optional`` (where present) of a scene ``.npz``, and no other (a
    ``.npz`` member is decompressed only when read); :class:`SceneValidationError` naming the file and field on any
    fault (missing, truncated or corrupt file, missing key, unreadable member)."""
    source = str(path)
    if not path.is_file():
        raise SceneValidationError(source, "<file>", "no such file")
    if not zipfile.is_zipfile(path):  # np.load would take other bytes for a pickle or a .npy and say so
        raise SceneValidationError(source, "<file>", "not a .npz (zip) archive: truncated, or another kind of file")
    try:
        with np.load(path, allow_pickle=False) as npz:
            present = set(npz.files)
            missing = [k for k in keys if k not in present]
            if missing:
                raise SceneValidationError(source, missing[0], "missing key")
            arrays: dict[str, Any] = {}
            for k in (*keys, *optional):
                if k in present:
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
    """The ``boxes`` array of a scene ``.npz`` as stored (``[G, 7]`` ``(cx, cy, cz, sx, sy, sz, yaw)``), reading
    nothing else (not the views). Not validated; errors as :func:`load_scene`'s.

    Convention: world frame in metres, z up; yaw counter-clockwise about +z.
    """
    return _read_npz(Path(path), ("boxes",))["boxes"]


def load_scene_gt(path: str | Path) -> tuple[np.ndarray, np.ndarray]:
    """The ``boxes`` ``[G, 7]`` and ``categories`` ``[G]`` arrays of a scene ``.npz`` as stored, reading nothing else.
    Not validated; errors as :func:`load_scene`'s (naming the file and the field).

    Convention: as :func:`load_scene_boxes`.
    """
    arrays = _read_npz(Path(path), ("boxes", "categories"))
    return arrays["boxes"], arrays["categories"]


def load_scene(
    path: str | Path,
    validate: bool = True,
    bounds: tuple[tuple[float, float, float], tuple[float, float, float]] | None = None,
    num_categories: int | None = None,
) -> SceneRecord:
    """Read a scene ``.npz``; raise :class:`SceneValidationError` naming the file and field on any fault.

    Missing, truncated or corrupt files and missing keys are reported like invalid values.
    """
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

    ``scenes`` holds ``{"file": relative path, "split": "train"|"val"|"test"}`` entries; ``symmetry_order``
    holds, per category, how many yaw angles map the shape onto itself (1 = asymmetric, 2 = 180 deg, 4 =
    90 deg, 0 = continuous); ``symmetric[c]`` is ``symmetry_order[c] != 1``.
    """

    categories: list[str]
    symmetry_order: list[int]
    scenes: list[dict[str, str]]
    scene_bounds: tuple[tuple[float, float, float], tuple[float, float, float]]
    generator: dict[str, Any] = field(default_factory=dict)
    seed: int | None = None

    @property
    def symmetric(self) -> list[bool]:
        return [o != 1 for o in self.symmetry_order]

    def files(self, split: str | None = None) -> list[str]:
        return [s["file"] for s in self.scenes if split is None or s["split"] == split]

    def to_dict(self) -> dict[str, Any]:
        return {
            "format": INDEX_FORMAT,
            "version": INDEX_VERSION,
            "categories": list(self.categories),
            "symmetry_order": [int(o) for o in self.symmetry_order],
            "symmetric": self.symmetric,
            "scene_bounds": {"min": list(self.scene_bounds[0]), "max": list(self.scene_bounds[1])},
            "generator": self.generator,
            "seed": self.seed,
            "scenes": self.scenes,
        }


def save_index(folder: str | Path, index: DatasetIndex) -> Path:
    """Write ``folder/index.json`` atomically."""
    return atomic_write_json(Path(folder) / INDEX_NAME, index.to_dict())


def load_index(folder: str | Path) -> DatasetIndex:
    """Read and check ``folder/index.json``; errors name the file and field."""
    path = Path(folder) / INDEX_NAME
    source = str(path)
    if not path.is_file():
        raise SceneValidationError(source, "<file>", "no such file (is this a threedq dataset folder?)")
    try:
        d = json.loads(path.read_text(encoding="utf-8"))
    except (json.JSONDecodeError, UnicodeDecodeError) as e:
        raise SceneValidationError(source, "<file>", f"not valid JSON: {e}") from e
    if not isinstance(d, dict):
        raise SceneValidationError(source, "<file>", "expected a JSON object")
    if d.get("format") != INDEX_FORMAT:
        raise SceneValidationError(source, "format", f"expected {INDEX_FORMAT!r}, got {d.get('format')!r}")
    for key in ("categories", "symmetry_order", "scenes", "scene_bounds"):
        if key not in d:
            raise SceneValidationError(source, key, "missing key")
    cats, sym = d["categories"], d["symmetry_order"]
    if not isinstance(cats, list) or not all(isinstance(c, str) for c in cats):
        raise SceneValidationError(source, "categories", "expected a list of names")
    if not isinstance(sym, list) or len(sym) != len(cats):
        raise SceneValidationError(source, "symmetry_order", f"expected {len(cats)} integers, one per category")
    scenes = d["scenes"]
    if not isinstance(scenes, list) or not all(isinstance(s, dict) and "file" in s and "split" in s for s in scenes):
        raise SceneValidationError(source, "scenes", "expected a list of {'file': ..., 'split': ...} entries")
    for i, s in enumerate(scenes):
        if s["split"] not in INDEX_SPLITS:
            raise SceneValidationError(
                source, "scenes", f"entry {i} ({s['file']!r}): unknown split {s['split']!r} (expected one of "
                f"{', '.join(INDEX_SPLITS)})"
            )
        if not isinstance(s["file"], str) or not s["file"]:
            raise SceneValidationError(source, "scenes", f"entry {i}: 'file' must be a relative path, got {s['file']!r}")
    try:
        lo = tuple(float(x) for x in d["scene_bounds"]["min"])
        hi = tuple(float(x) for x in d["scene_bounds"]["max"])
        assert len(lo) == 3 and len(hi) == 3
    except (KeyError, TypeError, ValueError, AssertionError) as e:
        raise SceneValidationError(source, "scene_bounds", "expected {'min': [x, y, z], 'max': [x, y, z]}") from e
    return DatasetIndex(
        categories=cats,
        symmetry_order=[int(o) for o in sym],
        scenes=scenes,
        scene_bounds=(lo, hi),  # type: ignore[arg-type]
        generator=d.get("generator", {}),
        seed=d.get("seed"),
    )
