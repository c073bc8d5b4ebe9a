"""The embedded dataset generator: CLEVR-veggie-like multi-view RGB-D scenes, offline and deterministic.

A scene holds ``min_objects``..``max_objects`` objects (categories of :mod:`threedq.data.catalog`,
uniformly drawn), each scaled, yawed and put on a grey ground plane without overlap, lit by a random
directional key light plus ambient light, and seen by ``num_views`` RGB-D cameras on rings of
elevations around the scene centre. It is written as a canonical :class:`threedq.scene.SceneRecord`
to ``out/<split>/scene_<index:06d>.npz``; ``out/index.json`` lists the scenes at the end.

Randomness: scene ``i`` of split ``s`` draws everything from
``np.random.default_rng(np.random.SeedSequence([seed_s, code_s, i]))`` with split codes train 0, val 1,
test 2, ``seed_s = seed`` for train and val and ``test_seed`` for test. So every scene is independent of
every other scene, of the number of scenes, of the worker count and of the scheduling.

Resuming: a scene file that loads, validates and whose ``meta`` names the same generator version,
config hash, seed, split and index is kept untouched; anything else is (re)written atomically.

Convention:
    World frame in metres, right-handed, z up, ground at z = 0, scene centred on the origin. Cameras
    use OpenCV axes (x right, y down, z forward), ``world_T_cam`` is camera-to-world, ``K`` has pixel
    centres at integer coordinates, ``fx = fy = W / (2 tan(fov / 2))``, principal point
    ``((W - 1) / 2, (H - 1) / 2)``. Depth is camera-frame z in metres (0 = sky); instance 0 is ground or
    sky, object ``i`` (1-based row of ``boxes``) is ``i``. Boxes are ``(cx, cy, cz, sx, sy, sz, yaw)``:
    centre of the object's scaled, yawed bounding box, its extents in the object frame, yaw about +z
    (counter-clockwise seen from above, radians, in ``[0, 2 pi)``).
"""

from __future__ import annotations

import hashlib
import json
import math
import multiprocessing
import numbers
import os
import sys
import time
import warnings
from collections.abc import Sequence
from dataclasses import asdict, dataclass, field, fields
from pathlib import Path
from typing import Any

import numpy as np

from threedq.boxes import box_corners
from threedq.data.catalog import CATEGORY_NAMES, category_by_name
from threedq.data.meshes import DEFAULT_MAX_FACES, category_extents, category_mesh
from threedq.data.render import Lighting, Renderer, RenderObject
from threedq.scene import DatasetIndex, SceneRecord, SceneValidationError, load_scene, save_index, save_scene

__all__ = [
    "DEFAULT_SCENE_BOUNDS",
    "GENERATOR_VERSION",
    "SPLITS",
    "SPLIT_CODES",
    "GeneratorConfig",
    "SceneLayout",
    "SceneObject",
    "derive_test_seed",
    "generate_dataset",
    "intrinsics",
    "make_renderer",
    "render_scene",
    "sample_scene",
    "scene_file",
    "scene_seed_sequence",
    "split_sizes",
]

#: Bump whenever equal arguments would produce different files (resumed runs then regenerate).
GENERATOR_VERSION = "1.0.0"
SPLITS: tuple[str, ...] = ("train", "val", "test")
SPLIT_CODES: dict[str, int] = {"train": 0, "val": 1, "test": 2}
DEFAULT_SCENE_BOUNDS: tuple[tuple[float, float, float], tuple[float, float, float]] = (
    (-1.28, -1.28, -0.32),
    (1.28, 1.28, 0.96),
)

# Scene constants (documented here rather than configurable: they shape the look, not the task).
_MAX_PLACEMENT_TRIES = 100  # per object; an object that finds no free spot is left out
_LOOK_AT = np.array([0.0, 0.0, 0.2])  # cameras look at this point ...
_LOOK_AT_JITTER = np.array([0.1, 0.1, 0.05])  # ... plus U(-j, j) per axis, per scene
_LIGHT_ELEVATION_DEG = (30.0, 75.0)
_LIGHT_INTENSITY = (0.6, 1.0)
_AMBIENT = (0.2, 0.4)
_TEST_SEED_SALT = 0x7E57_5EED


# --------------------------------------------------------------------------------------------------
# configuration
# --------------------------------------------------------------------------------------------------
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

    Convention: metres, degrees, world z up; see the module docstring.
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
        return {k: list(v) if isinstance(v, tuple) else v for k, v in d.items()}

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> GeneratorConfig:
        """Inverse of :meth:`to_dict` (unknown keys raise ``ValueError``)."""
        names = {f.name for f in fields(cls)}
        unknown = sorted(set(d) - names)
        if unknown:
            raise ValueError(f"config: unknown generator option(s) {unknown}")
        kw = dict(d)
        for k in ("image_size", "scale_range", "elevation_range_deg", "distance_range", "categories"):
            if kw.get(k) is not None:
                kw[k] = tuple(kw[k])
        if "scene_bounds" in kw:
            kw["scene_bounds"] = (tuple(kw["scene_bounds"][0]), tuple(kw["scene_bounds"][1]))
        return cls(**kw)

    def hash(self) -> str:
        """Stable SHA-1 (hex) of the sorted-key JSON of :meth:`to_dict`."""
        text = json.dumps(self.to_dict(), sort_keys=True, separators=(",", ":"))
        return hashlib.sha1(text.encode("utf-8")).hexdigest()


# --------------------------------------------------------------------------------------------------
# scene sampling (numpy only)
# --------------------------------------------------------------------------------------------------
@dataclass
class SceneObject:
    """One placed object.

    Attributes:
        category: id (position in the config's category list).
        name: category name.
        scale: metres per normalised unit (the object's largest extent).
        yaw: radians in ``[0, 2 pi)``, counter-clockwise about +z.
        position: ``[3]`` where the object's bounding-box bottom centre sits (z = 0).
        box: ``[7]`` ``(cx, cy, cz, sx, sy, sz, yaw)``.

    Convention: world frame, metres, z up.
    """

    category: int
    name: str
    scale: float
    yaw: float
    position: np.ndarray
    box: np.ndarray

    @property
    def world_T_obj(self) -> np.ndarray:
        """``[4, 4]`` float64: uniform scale, then yaw about +z, then translation to ``position``."""
        c, s = math.cos(self.yaw), math.sin(self.yaw)
        T = np.eye(4)
        T[:3, :3] = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]]) * self.scale
        T[:3, 3] = self.position
        return T


@dataclass
class SceneLayout:
    """Everything about a scene except its pixels.

    Attributes:
        objects: the placed objects (row ``i`` is instance ``i + 1``).
        K: ``[V, 3, 3]`` float64 intrinsics (values representable in float32).
        world_T_cam: ``[V, 4, 4]`` float64 camera-to-world poses (values representable in float32).
        lighting: the scene's light.
        image_size: ``(H, W)``.
        category_names: the config's category names in id order.
        mesh_faces: face budget of the meshes (:func:`threedq.data.meshes.category_mesh`).
        meta: JSON-ready facts copied into the record's ``meta``.

    Convention: see the module docstring.
    """

    objects: list[SceneObject]
    K: np.ndarray
    world_T_cam: np.ndarray
    lighting: Lighting
    image_size: tuple[int, int]
    category_names: tuple[str, ...]
    mesh_faces: int = DEFAULT_MAX_FACES
    meta: dict[str, Any] = field(default_factory=dict)

    @property
    def boxes(self) -> np.ndarray:
        """``[M, 7]`` float64."""
        return np.stack([o.box for o in self.objects]).astype(np.float64)

    @property
    def categories(self) -> np.ndarray:
        """``[M]`` int64."""
        return np.array([o.category for o in self.objects], np.int64)


def _look_at(eye: np.ndarray, target: np.ndarray) -> np.ndarray:
    """Camera-to-world ``[4, 4]`` with OpenCV axes, z towards ``target``, image x horizontal (world up +z)."""
    z = target - eye
    z /= np.linalg.norm(z)
    x = np.cross(z, np.array([0.0, 0.0, 1.0]))
    x /= np.linalg.norm(x)
    y = np.cross(z, x)  # points down in the image (world -z side)
    T = np.eye(4)
    T[:3, 0], T[:3, 1], T[:3, 2], T[:3, 3] = x, y, z, eye
    return T


def _f32(a: np.ndarray) -> np.ndarray:
    """Round to float32 and back: what is rendered is then exactly what is stored."""
    return np.asarray(a, np.float64).astype(np.float32).astype(np.float64)


def intrinsics(config: GeneratorConfig) -> np.ndarray:
    """``[3, 3]`` float64 pinhole intrinsics of every camera: square pixels, centred principal point.

    Convention: pixel centres at integer coordinates: ``cx = (W - 1) / 2``, ``cy = (H - 1) / 2``,
    ``fx = fy = W / (2 tan(fov_deg / 2))``.
    """
    H, W = config.image_size
    f = W / (2.0 * math.tan(math.radians(config.fov_deg) / 2.0))
    return np.array([[f, 0.0, (W - 1) / 2.0], [0.0, f, (H - 1) / 2.0], [0.0, 0.0, 1.0]])


def _ring_sizes(num_views: int, num_rings: int) -> list[int]:
    rings = min(num_rings, num_views)
    base, extra = divmod(num_views, rings)
    return [base + (1 if r < extra else 0) for r in range(rings)]


def sample_scene(config: GeneratorConfig, seed_sequence: np.random.SeedSequence) -> SceneLayout:
    """Draw one scene's objects, light and cameras from ``seed_sequence`` (pure numpy, no GL).

    Draw order (part of the format, do not change without bumping :data:`GENERATOR_VERSION`): number of
    objects; per object category, scale, yaw, then placement tries; light; look-at jitter; per ring
    azimuth offset, per view elevation (uniform in the ring's band) and distance.

    Returns:
        :class:`SceneLayout`; ``meta`` holds ``generator_version`` and ``config_hash``.

    Raises:
        AssertionError: a box left ``config.scene_bounds`` (cannot happen for a validated config).

    Convention: see the module docstring.
    """
    rng = np.random.default_rng(seed_sequence)
    names = config.category_names
    n_objects = int(rng.integers(config.min_objects, config.max_objects + 1))
    objects: list[SceneObject] = []
    circles: list[tuple[float, float, float]] = []  # (x, y, footprint radius)
    for _ in range(n_objects):
        cat = int(rng.integers(len(names)))
        ext = category_extents(names[cat], config.mesh_faces)
        scale = config.object_size * float(rng.uniform(*config.scale_range))
        yaw = float(rng.uniform(0.0, 2.0 * math.pi))
        radius = 0.5 * scale * math.hypot(ext[0], ext[1])
        for _try in range(_MAX_PLACEMENT_TRIES):
            r = config.placement_radius * math.sqrt(float(rng.uniform()))
            a = float(rng.uniform(0.0, 2.0 * math.pi))
            x, y = r * math.cos(a), r * math.sin(a)
            if all(math.hypot(x - cx, y - cy) >= radius + cr + config.min_gap for cx, cy, cr in circles):
                break
        else:
            continue  # no free spot: leave this object out
        circles.append((x, y, radius))
        size = scale * ext
        box = np.array([x, y, size[2] / 2.0, size[0], size[1], size[2], yaw])
        objects.append(SceneObject(cat, names[cat], scale, yaw, np.array([x, y, 0.0]), box))

    lo, hi = np.array(config.scene_bounds[0]), np.array(config.scene_bounds[1])
    corners = box_corners(np.stack([o.box for o in objects]))
    assert np.all(corners >= lo - 1e-9) and np.all(corners <= hi + 1e-9), "a box left the scene bounds"

    az = float(rng.uniform(0.0, 2.0 * math.pi))
    el = math.radians(float(rng.uniform(*_LIGHT_ELEVATION_DEG)))
    lighting = Lighting(
        direction=(math.cos(el) * math.cos(az), math.cos(el) * math.sin(az), math.sin(el)),
        intensity=float(rng.uniform(*_LIGHT_INTENSITY)),
        ambient=float(rng.uniform(*_AMBIENT)),
    )

    target = _LOOK_AT + rng.uniform(-1.0, 1.0, size=3) * _LOOK_AT_JITTER
    e_lo, e_hi = config.elevation_range_deg
    sizes = _ring_sizes(config.num_views, config.num_rings)
    band = (e_hi - e_lo) / len(sizes)
    poses = []
    for ring, count in enumerate(sizes):
        offset = float(rng.uniform(0.0, 2.0 * math.pi / count))
        for k in range(count):
            azimuth = offset + 2.0 * math.pi * k / count
            elevation = math.radians(float(rng.uniform(e_lo + ring * band, e_lo + (ring + 1) * band)))
            dist = float(rng.uniform(*config.distance_range))
            d = np.array(
                [math.cos(elevation) * math.cos(azimuth), math.cos(elevation) * math.sin(azimuth), math.sin(elevation)]
            )
            poses.append(_look_at(target + dist * d, target))
    world_T_cam = _f32(np.stack(poses))
    K = _f32(np.broadcast_to(intrinsics(config), (config.num_views, 3, 3)).copy())
    meta = {"generator_version": GENERATOR_VERSION, "config_hash": config.hash()}
    return SceneLayout(objects, K, world_T_cam, lighting, config.image_size, names, config.mesh_faces, meta)


# --------------------------------------------------------------------------------------------------
# rendering
# --------------------------------------------------------------------------------------------------
def make_renderer(config: GeneratorConfig, backend: str | None = None) -> Renderer:
    """A :class:`~threedq.data.render.Renderer` set up for ``config`` (ground, shadows)."""
    return Renderer(backend=backend, ground_size=config.ground_size, shadows=config.shadows)


def render_scene(layout: SceneLayout, renderer: Renderer) -> SceneRecord:
    """Render a layout's views and pack them with its boxes into a :class:`SceneRecord`.

    Returns:
        The record: ``rgb`` ``[V, H, W, 3]`` u8, ``depth`` ``[V, H, W]`` f32, ``instance`` ``[V, H, W]``
        i32, ``K`` ``[V, 3, 3]``, ``world_T_cam`` ``[V, 4, 4]``, ``boxes`` ``[M, 7]``, ``categories`` ``[M]``;
        ``meta`` is ``layout.meta`` plus the object names and the light.

    Convention: see the module docstring.
    """
    objects = [
        RenderObject(
            key=f"{o.name}/{layout.mesh_faces}",
            mesh=category_mesh(o.name, layout.mesh_faces),
            color=category_by_name(o.name).color,
            world_T_obj=o.world_T_obj,
            instance_id=i + 1,
        )
        for i, o in enumerate(layout.objects)
    ]
    out = renderer.render(objects, layout.K, layout.world_T_cam, layout.image_size, layout.lighting)
    meta = dict(layout.meta)
    meta["object_names"] = [o.name for o in layout.objects]
    meta["light"] = {
        "direction": [round(float(x), 6) for x in layout.lighting.direction],
        "intensity": round(layout.lighting.intensity, 6),
        "ambient": round(layout.lighting.ambient, 6),
    }
    return SceneRecord(
        rgb=out.rgb,
        depth=out.depth,
        K=layout.K.astype(np.float32),
        world_T_cam=layout.world_T_cam.astype(np.float32),
        boxes=layout.boxes.astype(np.float32),
        categories=layout.categories,
        instance=out.instance,
        meta=meta,
    )


# --------------------------------------------------------------------------------------------------
# datasets
# --------------------------------------------------------------------------------------------------
def scene_seed_sequence(seed: int, split: str, index: int) -> np.random.SeedSequence:
    """The seed sequence of scene ``index`` of ``split`` (``seed`` is the split's seed: ``test_seed`` for test)."""
    return np.random.SeedSequence([int(seed), SPLIT_CODES[split], int(index)])


def derive_test_seed(seed: int) -> int:
    """The default test seed: a 32-bit value drawn from its own stream of ``seed``."""
    return int(np.random.SeedSequence([int(seed), _TEST_SEED_SALT]).generate_state(1, dtype=np.uint32)[0])


def split_sizes(num_scenes: int, split_fractions: Sequence[float], splits: Sequence[str]) -> dict[str, int]:
    """Scenes per requested split: ``num_scenes`` shared by the requested splits' fractions.

    The fractions of the requested splits are renormalised; counts are rounded by largest remainder
    (ties to the earlier split), then every split with a positive fraction gets at least one scene
    (taken from the largest) when ``num_scenes`` allows it. Deterministic.
    """
    fr = [float(split_fractions[SPLIT_CODES[s]]) for s in splits]
    total = sum(fr)
    raw = [round(num_scenes * f / total, 9) for f in fr]
    counts = [math.floor(r) for r in raw]
    order = sorted(range(len(splits)), key=lambda i: (-(raw[i] - counts[i]), i))
    for i in order[: num_scenes - sum(counts)]:
        counts[i] += 1
    positive = [i for i, f in enumerate(fr) if f > 0]
    if num_scenes >= len(positive):
        for i in positive:
            if counts[i] == 0:
                j = max(range(len(counts)), key=lambda k: (counts[k], -k))
                counts[j] -= 1
                counts[i] += 1
    return dict(zip(splits, counts))


def scene_file(split: str, index: int) -> str:
    """Path of a scene file relative to the dataset folder, e.g. ``train/scene_000042.npz``."""
    return f"{split}/scene_{index:06d}.npz"


@dataclass(frozen=True)
class _Task:
    split: str
    index: int
    seed: int


def _scene_is_current(path: Path, expected: dict[str, Any], config: GeneratorConfig) -> bool:
    """``path`` loads, validates (bounds, categories) and its meta matches ``expected``."""
    if not path.is_file():
        return False
    try:
        rec = load_scene(path, validate=True, bounds=config.scene_bounds, num_categories=len(config.category_names))
    except SceneValidationError:
        return False
    if any(rec.meta.get(k) != v for k, v in expected.items()):
        return False
    H, W = config.image_size
    return rec.rgb.shape == (config.num_views, H, W, 3) and rec.instance is not None


def _run_task(task: _Task, out: Path, config: GeneratorConfig, config_hash: str, renderer_fn) -> tuple[str, int, str]:
    """Keep or (re)write one scene file; returns ``(split, index, "kept" | "written")``."""
    path = out / scene_file(task.split, task.index)
    expected = {
        "generator_version": GENERATOR_VERSION,
        "config_hash": config_hash,
        "seed": task.seed,
        "split": task.split,
        "index": task.index,
    }
    if _scene_is_current(path, expected, config):
        return task.split, task.index, "kept"
    layout = sample_scene(config, scene_seed_sequence(task.seed, task.split, task.index))
    layout.meta.update(expected)
    record = render_scene(layout, renderer_fn())
    save_scene(path, record)
    return task.split, task.index, "written"


# Per-process state of pool workers (each spawned worker owns one GL context). Not configuration:
# it is filled once by the pool initializer from the arguments it is given.
_WORKER: dict[str, Any] = {}


def _init_worker(out: str, config_dict: dict[str, Any], raster_threads: int) -> None:
    # Mesa's llvmpipe rasterises with one thread per core by default; with several workers that
    # oversubscribes the cores (measured: 2 workers x 2 threads on 2 cores ~1.6x slower than x 1).
    # Read once, when the GL driver loads, i.e. below; a user's own setting wins.
    os.environ.setdefault("LP_NUM_THREADS", str(raster_threads))
    _WORKER.clear()
    _WORKER["out"] = Path(out)
    _WORKER["config"] = GeneratorConfig.from_dict(config_dict)
    _WORKER["hash"] = _WORKER["config"].hash()
    try:
        _WORKER["renderer"] = make_renderer(_WORKER["config"])
    except Exception as e:  # noqa: BLE001 - reported by the first task (a failing initializer would respawn forever)
        _WORKER["error"] = f"{type(e).__name__}: {e}"


def _worker_renderer() -> Renderer:
    if "error" in _WORKER:
        raise RuntimeError(f"worker process {os.getpid()} could not create its renderer: {_WORKER['error']}")
    return _WORKER["renderer"]


def _worker_task(task: _Task) -> tuple[str, int, str]:
    return _run_task(task, _WORKER["out"], _WORKER["config"], _WORKER["hash"], _worker_renderer)


def _remove_stale_temporaries(folder: Path, min_age_s: float = 3600.0) -> None:
    """Delete temporary files a killed run left behind (``.scene_XXXXXX.npz.*.tmp``, older than an hour)."""
    if folder.is_dir():
        now = time.time()
        for p in folder.glob(".scene_*.npz.*.tmp"):
            try:
                if now - p.stat().st_mtime > min_age_s:
                    p.unlink()
            except OSError:
                pass


def generate_dataset(
    out: str | Path,
    num_scenes: int,
    seed: int = 0,
    config: GeneratorConfig | None = GeneratorConfig(),
    split_fractions: tuple[float, float, float] = (0.8, 0.1, 0.1),
    test_seed: int | None = None,
    splits: Sequence[str] = SPLITS,
    workers: int = 2,
    progress: bool = True,
) -> DatasetIndex:
    """Generate (or complete) a dataset folder and write its ``index.json`` last.

    Args:
        out: dataset folder (created if needed).
        num_scenes: scenes over the requested splits (see :func:`split_sizes`).
        seed: seed of the train and val scenes (an int >= 0).
        config: scene parameters (``None`` = ``GeneratorConfig()``).
        split_fractions: ``(train, val, test)`` shares (renormalised over the requested splits).
        test_seed: seed of the test scenes; ``None`` derives one from ``seed`` (:func:`derive_test_seed`).
        splits: which splits to generate, any of ``("train", "val", "test")``. ``index.json`` lists
            exactly these splits' scenes.
        workers: processes rendering in parallel ("spawn" pool, one GL context each); 1 = in this process.
        progress: show a tqdm progress bar.

    Returns:
        The :class:`~threedq.scene.DatasetIndex` written to ``out/index.json``.

    Raises:
        ValueError: a bad argument (the message names it).
        RuntimeError: no OpenGL context could be created (the message says what to install).

    Convention: see the module docstring; files are ``out/<split>/scene_<index:06d>.npz``.
    """
    config = GeneratorConfig() if config is None else config
    if not isinstance(config, GeneratorConfig):
        raise ValueError(f"config: expected a GeneratorConfig, got {type(config).__name__}")  # noqa: TRY004 - the API promises ValueError naming the argument
    if not _is_int(num_scenes) or num_scenes < 1:
        raise ValueError(f"num_scenes: expected an int >= 1, got {num_scenes!r}")
    if not _is_int(seed) or seed < 0:
        raise ValueError(f"seed: expected an int >= 0, got {seed!r}")
    if test_seed is not None and (not _is_int(test_seed) or test_seed < 0):
        raise ValueError(f"test_seed: expected an int >= 0 or None, got {test_seed!r}")
    if not _is_int(workers) or workers < 1:
        raise ValueError(f"workers: expected an int >= 1, got {workers!r}")
    if isinstance(splits, str) or not all(isinstance(s, str) for s in splits):
        raise ValueError(f"splits: expected a sequence of split names, got {splits!r}")
    splits = tuple(splits)
    if not splits or any(s not in SPLITS for s in splits) or len(set(splits)) != len(splits):
        raise ValueError(f"splits: expected distinct names from {SPLITS}, got {splits!r}")
    splits = tuple(s for s in SPLITS if s in splits)  # canonical order
    try:
        fractions = tuple(float(f) for f in split_fractions)
    except (TypeError, ValueError):
        raise ValueError(f"split_fractions: expected 3 numbers (train, val, test), got {split_fractions!r}") from None
    if len(fractions) != 3 or not all(math.isfinite(f) and f >= 0 for f in fractions):
        raise ValueError(
            f"split_fractions: expected 3 non-negative numbers (train, val, test), got {split_fractions!r}"
        )
    if sum(fractions[SPLIT_CODES[s]] for s in splits) <= 0:
        raise ValueError(f"split_fractions: the requested splits {splits} all have fraction 0")

    out = Path(out)
    eff_test_seed = derive_test_seed(seed) if test_seed is None else int(test_seed)
    sizes = split_sizes(int(num_scenes), fractions, splits)
    split_seed = {"train": int(seed), "val": int(seed), "test": eff_test_seed}
    tasks = [_Task(s, i, split_seed[s]) for s in splits for i in range(sizes[s])]
    for s in splits:
        (out / s).mkdir(parents=True, exist_ok=True)
        _remove_stale_temporaries(out / s)
    config_hash = config.hash()

    from tqdm import tqdm

    bar = tqdm(total=len(tasks), disable=not progress, desc="threedq scenes", unit="scene", dynamic_ncols=True)
    kept = 0
    try:
        n_proc = min(workers, len(tasks))
        main_file = getattr(sys.modules.get("__main__"), "__file__", None)
        if n_proc > 1 and main_file is not None and not os.path.isfile(main_file):
            # "spawn" re-runs the main script in each worker; a script read from stdin cannot be
            # re-run and the pool would restart its crashing workers forever.
            warnings.warn(
                f"workers={workers}: the main script {main_file!r} is not a file; rendering in-process", stacklevel=2
            )
            n_proc = 1
        if n_proc <= 1:
            renderer: list[Renderer] = []

            def get_renderer() -> Renderer:
                if not renderer:
                    renderer.append(make_renderer(config))
                return renderer[0]

            try:
                for task in tasks:
                    kept += _run_task(task, out, config, config_hash, get_renderer)[2] == "kept"
                    bar.update(1)
            finally:
                for r in renderer:
                    r.release()
        else:
            ctx = multiprocessing.get_context("spawn")
            threads = max(1, (os.cpu_count() or 1) // n_proc)
            with ctx.Pool(n_proc, initializer=_init_worker, initargs=(str(out), config.to_dict(), threads)) as pool:
                for _, _, status in pool.imap_unordered(_worker_task, tasks, chunksize=1):
                    kept += status == "kept"
                    bar.update(1)
                    bar.set_postfix(kept=kept, refresh=False)
    finally:
        bar.close()

    index = DatasetIndex(
        categories=list(config.category_names),
        symmetry_order=list(config.symmetry_order),
        scenes=[{"file": scene_file(t.split, t.index), "split": t.split} for t in tasks],
        scene_bounds=config.scene_bounds,
        generator={
            "name": "threedq.data.generate",
            "version": GENERATOR_VERSION,
            "config": config.to_dict(),
            "config_hash": config_hash,
            "seed": int(seed),
            "test_seed": eff_test_seed,
            "split_fractions": list(fractions),
            "num_scenes": int(num_scenes),
            "split_sizes": {s: sizes[s] for s in splits},
        },
        seed=int(seed),
    )
    save_index(out, index)
    return index
