"""Configuration of the embedded dataset generator: :class:`GeneratorConfig`, its validation and hash.

Its :meth:`~GeneratorConfig.hash` and :data:`GENERATOR_VERSION` are written into every scene file, so a resumed run
knows which files are stale.
"""

from __future__ import annotations

import hashlib
import json
import math
import numbers
from dataclasses import asdict, dataclass, fields
from typing import Any

from threedq.data.catalog import CATEGORY_NAMES, category_by_name
from threedq.data.meshes import DEFAULT_MAX_FACES
from threedq.data.sensor import _level, effect_names

__all__ = ["COLOR_MODES", "DEFAULT_SCENE_BOUNDS", "GENERATOR_VERSION", "GeneratorConfig"]

#: Bump whenever equal arguments would produce different files (resumed runs then regenerate).
GENERATOR_VERSION = "1.1.0"
#: How objects are coloured (see :class:`GeneratorConfig`).
COLOR_MODES = ("category", "random")
DEFAULT_SCENE_BOUNDS: tuple[tuple[float, float, float], tuple[float, float, float]] = (
    (-1.28, -1.28, -0.32), (1.28, 1.28, 0.96))


def _is_int(x: Any) -> bool:
    return isinstance(x, numbers.Integral) and not isinstance(x, bool)


def _need(ok: bool, message: str) -> None:
    """Raise ``ValueError(message)`` unless ``ok``."""
    if not ok:
        raise ValueError(message)


#: (field, test of its ``(low, high)`` floats, message) of the range fields, in the order they are checked
_RANGES = (
    ("scale_range", lambda r: r[0] > 0, "must be positive"),
    ("elevation_range_deg", lambda r: 0 <= r[0] and r[1] <= 89, "must lie in [0, 89] degrees"),
    ("distance_range", lambda r: r[0] > 0.2, "cameras must be > 0.2 m from the look-at point"),
)


def _float_pair(name: str, value: Any) -> tuple[float, float]:
    try:
        a, b = (float(v) for v in value)
    except (TypeError, ValueError):
        raise ValueError(f"{name}: expected two numbers (low, high), got {value!r}") from None
    _need(math.isfinite(a) and math.isfinite(b) and a <= b,
          f"{name}: expected finite numbers with low <= high, got {value!r}")
    return a, b


@dataclass(frozen=True)
class GeneratorConfig:
    """Everything that shapes the generated scenes (not the seed, sizes or splits of a dataset).

    Attributes:
        image_size: ``(H, W)`` pixels; num_views: cameras per scene; num_rings: elevation rings they are spread over.
        min_objects, max_objects: objects per scene, uniform in ``[min, max]`` (one finding no free spot is left out).
        categories: category names drawn uniformly (``None`` = the 41 of the catalogue); ids are positions in it.
        object_size: largest extent of an object before its random scale (uniform in ``scale_range``), metres.
        placement_radius: object centres lie within this distance of the origin; min_gap: clearance between the
            objects' footprint circles; distance_range: camera distance to the look-at point (metres).
        elevation_range_deg: camera elevations above the ground; fov_deg: horizontal field of view (degrees).
        scene_bounds: ``((xmin, ymin, zmin), (xmax, ymax, zmax))`` every box lies in (checked).
        mesh_faces: face budget of the scanned meshes (0 = full scans).
        color_mode: ``"category"`` (the category's catalogue colour) or ``"random"`` (per instance, from
            :data:`threedq.data.catalog.RANDOM_COLOR_PALETTE`, with the layout ``"category"`` draws).
        capture_level, capture_effects: sensor effects on each scene (:func:`threedq.data.sensor.apply_capture`).

    Convention: metres, degrees, world z up; see :mod:`threedq.data.layout`.
    """

    image_size: tuple[int, int] = (128, 128)
    num_views: int = 28
    num_rings: int = 4
    min_objects: int = 1
    max_objects: int = 3
    categories: tuple[str, ...] | None = None
    object_size: float = 0.5
    scale_range: tuple[float, float] = (0.75, 1.25)
    placement_radius: float = 0.8
    min_gap: float = 0.02
    elevation_range_deg: tuple[float, float] = (20.0, 80.0)
    distance_range: tuple[float, float] = (2.8, 3.6)
    fov_deg: float = 55.0
    scene_bounds: tuple[tuple[float, float, float], tuple[float, float, float]] = DEFAULT_SCENE_BOUNDS
    shadows: bool = True
    ground_size: float = 12.0
    mesh_faces: int = DEFAULT_MAX_FACES
    color_mode: str = "category"
    capture_level: float = 0.0
    capture_effects: tuple[str, ...] | None = None

    def __post_init__(self) -> None:
        def put(name: str, value: Any) -> None:
            object.__setattr__(self, name, value)

        size = self.image_size
        ok = not isinstance(size, (str, bytes)) and hasattr(size, "__len__") and len(size) == 2
        _need(ok and all(_is_int(s) and 1 <= s <= 4096 for s in size),
              f"image_size: expected (H, W), two ints in [1, 4096], got {size!r}")
        put("image_size", (int(size[0]), int(size[1])))
        for name in ("num_views", "num_rings", "min_objects", "max_objects"):
            v = getattr(self, name)
            _need(_is_int(v) and v >= 1, f"{name}: expected an int >= 1, got {v!r}")
            put(name, int(v))
        n_lo, n_hi = self.min_objects, self.max_objects
        _need(n_lo <= n_hi, f"min_objects, max_objects: min_objects ({n_lo}) > max_objects ({n_hi})")
        cats = self.categories
        if cats is not None:
            _need(not isinstance(cats, str) and all(isinstance(c, str) for c in cats),
                  f"categories: expected a sequence of category names or None, got {cats!r}")
            cats = tuple(cats)
            _need(bool(cats), "categories: empty; give at least one name (or None for all)")
            for c in cats:
                category_by_name(c)  # raises "categories: unknown category name ..."
            _need(len(set(cats)) == len(cats), f"categories: duplicate names in {cats!r}")
            put("categories", cats)
        for name in ("object_size", "placement_radius", "min_gap", "fov_deg", "ground_size"):
            v = getattr(self, name)
            finite = not isinstance(v, bool) and isinstance(v, numbers.Real) and math.isfinite(v)
            _need(finite, f"{name}: expected a finite number, got {v!r}")
            put(name, float(v))
        _need(self.object_size > 0, f"object_size: must be > 0, got {self.object_size}")
        _need(self.placement_radius >= 0 and self.min_gap >= 0, "placement_radius, min_gap: must be >= 0")
        _need(0 < self.fov_deg < 180, f"fov_deg: must be in (0, 180), got {self.fov_deg}")
        for name, in_range, why in _RANGES:
            r = _float_pair(name, getattr(self, name))
            _need(in_range(r), f"{name}: {why}, got {r}")
            put(name, r)
        bounds = self.scene_bounds
        try:
            lo, hi = tuple(float(x) for x in bounds[0]), tuple(float(x) for x in bounds[1])
            assert len(lo) == 3 and len(hi) == 3 and len(bounds) == 2
        except (TypeError, ValueError, IndexError, AssertionError):
            raise ValueError(
                f"scene_bounds: expected ((xmin, ymin, zmin), (xmax, ymax, zmax)), got {bounds!r}") from None
        _need(all(math.isfinite(a) and math.isfinite(b) and a < b for a, b in zip(lo, hi)),
              f"scene_bounds: need finite min < max per axis, got {bounds!r}")
        put("scene_bounds", (lo, hi))
        faces = self.mesh_faces
        _need(_is_int(faces) and faces >= 0, f"mesh_faces: expected an int >= 0 (0 = full meshes), got {faces!r}")
        put("mesh_faces", int(faces))
        _need(self.color_mode in COLOR_MODES,
              f"color_mode: expected one of {', '.join(COLOR_MODES)}, got {self.color_mode!r}")
        put("capture_level", _level(self.capture_level, "capture_level"))
        if self.capture_effects is not None:
            effects = effect_names(self.capture_effects, "capture_effects")
            _need(bool(effects), "capture_effects: empty; give at least one name (or None for all)")
            put("capture_effects", effects)
        _need(isinstance(self.shadows, bool), f"shadows: expected a bool, got {self.shadows!r}")
        # a normalised mesh's footprint circle has radius <= sqrt(0.5) * size and its height is <= size
        s_max = self.object_size * self.scale_range[1]
        reach = self.placement_radius + math.sqrt(0.5) * s_max
        _need(reach <= min(-lo[0], hi[0], -lo[1], hi[1]) and s_max <= hi[2] and lo[2] <= 0,
              f"scene_bounds: {self.scene_bounds} cannot hold every object: objects reach "
              f"{reach:.3f} m from the origin in x/y (placement_radius + sqrt(0.5) * object_size * "
              f"scale_range[1]) and up to z = {s_max:.3f} m from z = 0; enlarge the bounds or shrink "
              "placement_radius/object_size")
        _need(self.ground_size >= 2 * reach,
              f"ground_size: {self.ground_size} m is smaller than the object area ({2 * reach:.2f} m)")

    @property
    def category_names(self) -> tuple[str, ...]:
        """The categories drawn from, in id order."""
        return CATEGORY_NAMES if self.categories is None else self.categories

    @property
    def symmetry_order(self) -> tuple[int, ...]:
        """Yaw symmetry order per category (see :mod:`threedq.data.catalog`), in id order."""
        return tuple(category_by_name(n).symmetry_order for n in self.category_names)

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready dict of every field (``categories`` resolved to the explicit list of names)."""
        d = asdict(self)
        d["categories"] = list(self.category_names)
        d["scene_bounds"] = [list(self.scene_bounds[0]), list(self.scene_bounds[1])]
        if d["color_mode"] == "category":
            del d["color_mode"]  # defaults of these options are left out: the hash stays that of configs without them
        for name, default in (("capture_level", 0.0), ("capture_effects", None)):
            if d[name] == default:
                del d[name]
        return {k: list(v) if isinstance(v, tuple) else v for k, v in d.items()}

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> GeneratorConfig:
        """Inverse of :meth:`to_dict` (unknown keys raise ``ValueError``)."""
        names = {f.name for f in fields(cls)}
        unknown = sorted(set(d) - names)
        if unknown:
            raise ValueError(f"config: unknown generator option(s) {unknown}")
        kw = dict(d)
        tuples = ("image_size", "scale_range", "elevation_range_deg", "distance_range", "categories", "capture_effects")
        for k in tuples:
            if kw.get(k) is not None:
                kw[k] = tuple(kw[k])
        if "scene_bounds" in kw:
            kw["scene_bounds"] = (tuple(kw["scene_bounds"][0]), tuple(kw["scene_bounds"][1]))
        return cls(**kw)

    def hash(self) -> str:
        """Stable SHA-1 (hex) of the sorted-key JSON of :meth:`to_dict`."""
        text = json.dumps(self.to_dict(), sort_keys=True, separators=(",", ":"))
        return hashlib.sha1(text.encode("utf-8")).hexdigest()
