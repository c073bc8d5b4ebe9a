"""Configuration of the embedded dataset generator: :class:`GeneratorConfig`, its validation and hash.

A config holds everything that shapes the generated scenes (image size, cameras, objects, placement,
scene bounds, shadows, mesh budget), not the seed, sizes or splits of a dataset. Its :meth:`~GeneratorConfig.hash`
and :data:`GENERATOR_VERSION` are written into every scene file, so a resumed run knows which files are stale.

Convention: metres, degrees, world z up (see :mod:`threedq.data.layout`).
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
from threedq.data.sensor import effect_names

__all__ = ["COLOR_MODES", "DEFAULT_SCENE_BOUNDS", "GENERATOR_VERSION", "GeneratorConfig"]

#: Bump whenever equal arguments would produce different files (resumed runs then regenerate).
#: 1.1.0: primitives from ``trimesh.creation`` and quadric decimation of the scanned meshes
#: (:mod:`threedq.data.meshes`) instead of hand-made meshes and vertex clustering.
GENERATOR_VERSION = "1.1.0"
#: How objects are coloured (see :class:`GeneratorConfig`).
COLOR_MODES = ("category", "random")
DEFAULT_SCENE_BOUNDS: tuple[tuple[float, float, float], tuple[float, float, float]] = (
    (-1.28, -1.28, -0.32),
    (1.28, 1.28, 0.96),
)


def _is_int(x: Any) -> bool:
    return isinstance(x, numbers.Integral) and not isinstance(x, bool)


def _float_pair(name: str, value: Any) -> tuple[float, float]:
    try:
        a, b = (float(v) for v in value)
    except (TypeError, ValueError):
        raise ValueError(f"{name}: expected two numbers (low, high), got {value!r}") from None
    if not (math.isfinite(a) and math.isfinite(b)) or a > b:
        raise ValueError(f"{name}: expected finite numbers with low <= high, got {value!r}")
    return a, b


@dataclass(frozen=True)
class GeneratorConfig:
    """Everything that shapes the generated scenes (not the seed, sizes or splits of a dataset).

    Attributes:
        image_size: ``(H, W)`` pixels.
        num_views: cameras per scene.
        num_rings: elevation rings the cameras are spread over (at most ``num_views`` are used).
        min_objects, max_objects: objects per scene, uniform in ``[min, max]`` (an object that finds
            no free spot after bounded rejection sampling is left out; never the first one).
        categories: category names to draw uniformly from (``None`` = all 41 of the catalogue, in
            catalogue order). Category ids in the records are positions in this list.
        object_size: largest extent of an object before its random scale, metres.
        scale_range: the random scale factor is uniform in this range.
        placement_radius: object centres lie within this distance of the origin, metres.
        min_gap: clearance between the objects' footprint circles, metres.
        elevation_range_deg: camera elevations above the ground plane, degrees.
        distance_range: camera distance to the look-at point, metres (uniform per view).
        fov_deg: horizontal field of view, degrees (square pixels).
        scene_bounds: ``((xmin, ymin, zmin), (xmax, ymax, zmax))`` every box lies in (checked).
        shadows: render cast shadows.
        ground_size: side of the square ground plane, metres.
        mesh_faces: face budget of the scanned meshes (decimated beyond it; 0 = full 16384-face scans).
        color_mode: ``"category"`` (each object takes its category's catalogue colour: the embedded data, where a
            category is a shape and a colour) or ``"random"`` (each instance takes a colour drawn uniformly from
            :data:`threedq.data.catalog.RANDOM_COLOR_PALETTE`, one palette for every category, so that only the
            shape tells categories apart; the layout is the one ``"category"`` draws from the same seed).

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
        if (
            isinstance(size, (str, bytes))
            or not hasattr(size, "__len__")
            or len(size) != 2
            or not all(_is_int(s) and 1 <= s <= 4096 for s in size)
        ):
            raise ValueError(f"image_size: expected (H, W), two ints in [1, 4096], got {size!r}")
        put("image_size", (int(size[0]), int(size[1])))
        for name in ("num_views", "num_rings", "min_objects", "max_objects"):
            v = getattr(self, name)
            if not _is_int(v) or v < 1:
                raise ValueError(f"{name}: expected an int >= 1, got {v!r}")
            put(name, int(v))
        if self.min_objects > self.max_objects:
            raise ValueError(
                f"min_objects, max_objects: min_objects ({self.min_objects}) > max_objects ({self.max_objects})"
            )
        cats = self.categories
        if cats is not None:
            if isinstance(cats, str) or not all(isinstance(c, str) for c in cats):
                raise ValueError(f"categories: expected a sequence of category names or None, got {cats!r}")
            cats = tuple(cats)
            if not cats:
                raise ValueError("categories: empty; give at least one name (or None for all)")
            for c in cats:
                category_by_name(c)  # raises "categories: unknown category name ..."
            if len(set(cats)) != len(cats):
                raise ValueError(f"categories: duplicate names in {cats!r}")
            put("categories", cats)
        for name in ("object_size", "placement_radius", "min_gap", "fov_deg", "ground_size"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, numbers.Real) or not math.isfinite(v):
                raise ValueError(f"{name}: expected a finite number, got {v!r}")
            put(name, float(v))
        if self.object_size <= 0:
            raise ValueError(f"object_size: must be > 0, got {self.object_size}")
        if self.placement_radius < 0 or self.min_gap < 0:
            raise ValueError("placement_radius, min_gap: must be >= 0")
        if not 0 < self.fov_deg < 180:
            raise ValueError(f"fov_deg: must be in (0, 180), got {self.fov_deg}")
        put("scale_range", _float_pair("scale_range", self.scale_range))
        if self.scale_range[0] <= 0:
            raise ValueError(f"scale_range: must be positive, got {self.scale_range}")
        put("elevation_range_deg", _float_pair("elevation_range_deg", self.elevation_range_deg))
        if not (0 <= self.elevation_range_deg[0] and self.elevation_range_deg[1] <= 89):
            raise ValueError(f"elevation_range_deg: must lie in [0, 89] degrees, got {self.elevation_range_deg}")
        put("distance_range", _float_pair("distance_range", self.distance_range))
        if self.distance_range[0] <= 0.2:
            raise ValueError(
                f"distance_range: cameras must be > 0.2 m from the look-at point, got {self.distance_range}"
            )
        try:
            lo = tuple(float(x) for x in self.scene_bounds[0])
            hi = tuple(float(x) for x in self.scene_bounds[1])
            assert len(lo) == 3 and len(hi) == 3 and len(self.scene_bounds) == 2
        except (TypeError, ValueError, IndexError, AssertionError):
            raise ValueError(
                f"scene_bounds: expected ((xmin, ymin, zmin), (xmax, ymax, zmax)), got {self.scene_bounds!r}"
            ) from None
        if not all(math.isfinite(a) and math.isfinite(b) and a < b for a, b in zip(lo, hi)):
            raise ValueError(f"scene_bounds: need finite min < max per axis, got {self.scene_bounds!r}")
        put("scene_bounds", (lo, hi))
        if not _is_int(self.mesh_faces) or self.mesh_faces < 0:
            raise ValueError(f"mesh_faces: expected an int >= 0 (0 = full meshes), got {self.mesh_faces!r}")
        put("mesh_faces", int(self.mesh_faces))
        if self.color_mode not in COLOR_MODES:
            raise ValueError(f"color_mode: expected one of {', '.join(COLOR_MODES)}, got {self.color_mode!r}")
        lvl = self.capture_level
        if isinstance(lvl, bool) or not isinstance(lvl, numbers.Real) or not math.isfinite(lvl) or lvl < 0:
            raise ValueError(f"capture_level: expected a finite number >= 0, got {lvl!r}")
        put("capture_level", float(lvl))
        if self.capture_effects is not None:
            effects = effect_names(self.capture_effects, "capture_effects")
            if not effects:
                raise ValueError("capture_effects: empty; give at least one name (or None for all)")
            put("capture_effects", effects)
        if not isinstance(self.shadows, bool):
            raise ValueError(f"shadows: expected a bool, got {self.shadows!r}")  # noqa: TRY004 - the API promises ValueError naming the argument
        # Every box must fit the bounds whatever is drawn: a normalised mesh has extents <= 1, so its
        # footprint circle has radius <= sqrt(0.5) * size and its height is <= size.
        s_max = self.object_size * self.scale_range[1]
        reach = self.placement_radius + math.sqrt(0.5) * s_max
        if reach > min(-lo[0], hi[0], -lo[1], hi[1]) or s_max > hi[2] or lo[2] > 0:
            raise ValueError(
                f"scene_bounds: {self.scene_bounds} cannot hold every object: objects reach "
                f"{reach:.3f} m from the origin in x/y (placement_radius + sqrt(0.5) * object_size * "
                f"scale_range[1]) and up to z = {s_max:.3f} m from z = 0; enlarge the bounds or shrink "
                "placement_radius/object_size"
            )
        if self.ground_size < 2 * reach:
            raise ValueError(f"ground_size: {self.ground_size} m is smaller than the object area ({2 * reach:.2f} m)")

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
            del d["color_mode"]  # the default is left out, so that the datasets made before the option keep their hash
        for name, default in (("capture_level", 0.0), ("capture_effects", None)):
            if d[name] == default:
                del d[name]  # likewise
        return {k: list(v) if isinstance(v, tuple) else v for k, v in d.items()}

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> GeneratorConfig:
        """Inverse of :meth:`to_dict` (unknown keys raise ``ValueError``)."""
        names = {f.name for f in fields(cls)}
        unknown = sorted(set(d) - names)
        if unknown:
            raise ValueError(f"config: unknown generator option(s) {unknown}")
        kw = dict(d)
        for k in ("image_size", "scale_range", "elevation_range_deg", "distance_range", "categories",
                  "capture_effects"):
            if kw.get(k) is not None:
                kw[k] = tuple(kw[k])
        if "scene_bounds" in kw:
            kw["scene_bounds"] = (tuple(kw["scene_bounds"][0]), tuple(kw["scene_bounds"][1]))
        return cls(**kw)

    def hash(self) -> str:
        """Stable SHA-1 (hex) of the sorted-key JSON of :meth:`to_dict`."""
        text = json.dumps(self.to_dict(), sort_keys=True, separators=(",", ":"))
        return hashlib.sha1(text.encode("utf-8")).hexdigest()
