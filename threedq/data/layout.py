"""Scene layouts of the embedded dataset: objects, their poses, the light and the cameras (numpy only, no GL).

A scene holds ``min_objects``..``max_objects`` objects (uniformly drawn categories), each scaled, yawed and put on
the ground plane without overlap, lit by a random directional key light plus ambient light, and seen by
``num_views`` cameras on rings of elevations around the scene centre. :func:`sample_scene` draws it all from one seed
sequence; :func:`threedq.data.render_scene.render_scene` turns the layout into pixels.

Convention:
    World frame in metres, right-handed, z up, ground at z = 0, scene centred on the origin. Cameras use OpenCV axes
    (x right, y down, z forward), ``world_T_cam`` is camera-to-world, ``K`` has pixel centres at integer coordinates,
    ``fx = fy = W / (2 tan(fov / 2))``, principal point ``((W - 1) / 2, (H - 1) / 2)``. Depth is camera-frame z in
    metres (0 = sky); instance 0 is ground or sky, object ``i`` (1-based row of ``boxes``) is ``i``. Boxes are
    ``(cx, cy, cz, sx, sy, sz, yaw)``: centre of the object's scaled, yawed bounding box, its extents in the object
    frame, yaw counter-clockwise about +z, radians in ``[0, 2 pi)``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from threedq.boxes import box_corners
from threedq.data.catalog import RANDOM_COLOR_PALETTE
from threedq.data.generator_config import GENERATOR_VERSION, GeneratorConfig
from threedq.data.meshes import DEFAULT_MAX_FACES, category_extents
from threedq.data.render import Lighting

__all__ = ["SceneLayout", "SceneObject", "intrinsics", "sample_scene"]

_MAX_PLACEMENT_TRIES = 100  # per object; an object that finds no free spot is left out
_LOOK_AT = np.array([0.0, 0.0, 0.2])  # cameras look at this point ...
_LOOK_AT_JITTER = np.array([0.1, 0.1, 0.05])  # ... plus U(-j, j) per axis, per scene
_LIGHT_ELEVATION_DEG = (30.0, 75.0)
_LIGHT_INTENSITY = (0.6, 1.0)
_AMBIENT = (0.2, 0.4)
_COLOR_STREAM = 0xC0102  # spawn-key suffix of the colour stream of color_mode="random"


@dataclass
class SceneObject:
    """One placed object: ``category`` id and ``name``, ``scale`` (metres per normalised unit), ``yaw`` (radians in
    ``[0, 2 pi)``, counter-clockwise about +z), ``position`` ``[3]`` of its bounding-box bottom centre (z = 0), ``box``
    ``[7]`` and ``color`` (sRGB in ``[0, 1]`` with ``color_mode="random"``, else ``None``: the category's)."""

    category: int
    name: str
    scale: float
    yaw: float
    position: np.ndarray
    box: np.ndarray
    color: tuple[float, float, float] | None = None

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
    """Everything about a scene except its pixels: the ``objects`` (row ``i`` is instance ``i + 1``), ``K``
    ``[V, 3, 3]`` and ``world_T_cam`` ``[V, 4, 4]`` (float64 holding float32 values), the ``lighting``, ``image_size``
    ``(H, W)``, the config's ``category_names``, the meshes' ``mesh_faces`` and JSON-ready ``meta`` for the record."""

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
    """Round to float32 and back (what is rendered is what is stored)."""
    return np.asarray(a, np.float64).astype(np.float32).astype(np.float64)


def intrinsics(config: GeneratorConfig) -> np.ndarray:
    """``[3, 3]`` float64 pinhole intrinsics of every camera (see the module docstring's convention)."""
    H, W = config.image_size
    f = W / (2.0 * math.tan(math.radians(config.fov_deg) / 2.0))
    return np.array([[f, 0.0, (W - 1) / 2.0], [0.0, f, (H - 1) / 2.0], [0.0, 0.0, 1.0]])


def sample_scene(config: GeneratorConfig, seed_sequence: np.random.SeedSequence) -> SceneLayout:
    """Draw one scene's objects, light and cameras from ``seed_sequence``; ``meta`` holds ``generator_version`` and
    ``config_hash``.

    Draw order (changing it needs a new :data:`GENERATOR_VERSION`): number of objects; per object category, scale, yaw,
    then placement tries; light; look-at jitter; per ring azimuth offset, per view elevation (uniform in the ring's
    band) and distance. Random colours come from a second stream of the same seed, in object order.
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
    lighting = Lighting(direction=(math.cos(el) * math.cos(az), math.cos(el) * math.sin(az), math.sin(el)),
                        intensity=float(rng.uniform(*_LIGHT_INTENSITY)), ambient=float(rng.uniform(*_AMBIENT)))

    target = _LOOK_AT + rng.uniform(-1.0, 1.0, size=3) * _LOOK_AT_JITTER
    e_lo, e_hi = config.elevation_range_deg
    rings = min(config.num_rings, config.num_views)
    base, extra = divmod(config.num_views, rings)
    sizes = [base + (1 if r < extra else 0) for r in range(rings)]
    band = (e_hi - e_lo) / len(sizes)
    poses = []
    for ring, count in enumerate(sizes):
        offset = float(rng.uniform(0.0, 2.0 * math.pi / count))
        for k in range(count):
            azimuth = offset + 2.0 * math.pi * k / count
            elevation = math.radians(float(rng.uniform(e_lo + ring * band, e_lo + (ring + 1) * band)))
            dist = float(rng.uniform(*config.distance_range))
            ce = math.cos(elevation)
            d = np.array([ce * math.cos(azimuth), ce * math.sin(azimuth), math.sin(elevation)])
            poses.append(_look_at(target + dist * d, target))
    world_T_cam = _f32(np.stack(poses))
    K = _f32(np.broadcast_to(intrinsics(config), (config.num_views, 3, 3)).copy())
    if config.color_mode == "random":
        key = (*seed_sequence.spawn_key, _COLOR_STREAM)
        colors = np.random.default_rng(np.random.SeedSequence(seed_sequence.entropy, spawn_key=key))
        for o in objects:
            o.color = RANDOM_COLOR_PALETTE[int(colors.integers(len(RANDOM_COLOR_PALETTE)))]
    meta = {"generator_version": GENERATOR_VERSION, "config_hash": config.hash()}
    return SceneLayout(objects, K, world_T_cam, lighting, config.image_size, names, config.mesh_faces, meta)
