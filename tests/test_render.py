"""The moderngl renderer against hand-computed depth and silhouettes, and the meshes it draws.

Convention checked: OpenCV cameras (x right, y down, z forward), camera-to-world poses, pixel centres
at integer coordinates, depth = camera-frame z in metres (0 = nothing hit), image row 0 at the top.
"""

from __future__ import annotations

import numpy as np
import pytest

from threedq.data.meshes import MeshData, box_mesh, category_mesh, cylinder_mesh, decimate, normalize_mesh, sphere_mesh
from threedq.data.render import Lighting, Renderer, RenderObject, create_context, projection_from_K

F, SIZE = 80.0, 64  # focal length and image side of the test camera
C = (SIZE - 1) / 2  # principal point 31.5: pixel columns 31 and 32 straddle the optical axis
LIGHT = Lighting(direction=(0.3, 0.2, 0.93), intensity=0.8, ambient=0.3)


@pytest.fixture(scope="module")
def renderer():
    r = Renderer(ground_size=12.0, shadows=True)
    yield r
    r.release()


def _K() -> np.ndarray:
    return np.array([[[F, 0.0, C], [0.0, F, C], [0.0, 0.0, 1.0]]])


def _cube(side: float, x: float = 0.0, y: float = 0.0, instance_id: int = 1) -> RenderObject:
    T = np.diag([side, side, side, 1.0])
    T[:3, 3] = (x, y, 0.0)
    return RenderObject(f"cube{instance_id}", box_mesh(), (0.8, 0.1, 0.1), T, instance_id)


def _pose(R_columns: tuple, eye: tuple) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = np.array(R_columns, dtype=np.float64).T  # columns = camera x, y, z axes in the world
    T[:3, 3] = eye
    return T[None]


def _expected_run(half_size: float, depth: float) -> np.ndarray:
    """Pixel indices whose centres see a face of half-width ``half_size`` at ``depth`` (no centre on an edge)."""
    idx = np.arange(SIZE)
    inside = np.abs(idx - C) * depth / F < half_size
    return idx[inside]


def test_cube_from_above_depth_and_silhouette(renderer):
    # camera 3 m above the origin looking straight down: x_cam = world x, y_cam = world -y, z_cam = world -z
    h, s = 3.0, 0.4
    pose = _pose(((1, 0, 0), (0, -1, 0), (0, 0, -1)), (0.0, 0.0, h))
    small = 0.2
    objs = [_cube(s), _cube(small, x=0.7, y=0.5, instance_id=2)]
    out = renderer.render(objs, _K(), pose, (SIZE, SIZE), LIGHT)
    depth, inst = out.depth[0], out.instance[0]

    # the top face is at camera z = h - s everywhere it is seen, the ground at z = h
    top = h - s
    assert depth[31, 31] == pytest.approx(top, abs=1e-5)
    assert depth[32, 32] == pytest.approx(top, abs=1e-5)
    assert np.allclose(depth[inst == 0], h, atol=1e-5)  # the ground plane is parallel to the image
    # silhouette: 12 x 12 pixel centres with |u - 31.5| * 2.6 / 80 < 0.2
    run = _expected_run(s / 2, top)
    assert run.tolist() == list(range(26, 38))
    mask = inst == 1
    assert mask.sum() == len(run) ** 2
    rows, cols = np.nonzero(mask)
    assert rows.min() == cols.min() == 26 and rows.max() == cols.max() == 37
    assert np.allclose(depth[mask], top, atol=1e-5)
    # world +x is image right, world +y is image up (smaller row): the small cube at (0.7, 0.5)
    zc = h - small
    u, v = C + F * 0.7 / zc, C - F * 0.5 / zc
    r2, c2 = np.nonzero(inst == 2)
    assert r2.min() <= v <= r2.max() and c2.min() <= u <= c2.max()
    assert (r2.max() - r2.min() + 1) == len(_expected_run(small / 2, zc))  # 6 pixels
    # colour: the cube is red-ish, the ground grey, the sky absent
    assert out.rgb[0, 31, 31, 0] > 2 * out.rgb[0, 31, 31, 1]
    assert out.rgb.dtype == np.uint8 and out.depth.dtype == np.float32 and out.instance.dtype == np.int32


def test_cube_from_the_side_depth_silhouette_and_orientation(renderer):
    # camera at (2, 0, 0.2) (the cube's mid-height) looking along world -x
    d, s, ch = 2.0, 0.4, 0.2
    pose = _pose(((0, 1, 0), (0, 0, -1), (-1, 0, 0)), (d, 0.0, ch))
    out = renderer.render([_cube(s)], _K(), pose, (SIZE, SIZE), LIGHT)
    depth, inst = out.depth[0], out.instance[0]
    front = d - s / 2
    assert depth[31, 31] == pytest.approx(front, abs=1e-5)
    run = _expected_run(s / 2, front)  # 18 pixel centres: |u - 31.5| * 1.8 / 80 < 0.2
    assert len(run) == 18
    mask = inst == 1
    assert mask.sum() == 18 * 18
    rows, cols = np.nonzero(mask)
    assert rows.min() == cols.min() == run[0] and rows.max() == cols.max() == run[-1]
    assert np.allclose(depth[mask], front, atol=1e-5)
    # row 0 is the top of the image: sky above the horizon (depth 0), ground below
    assert depth[0, 0] == 0 and inst[0, 0] == 0 and out.rgb[0, 0, 0].tolist() == [0, 0, 0]
    for v in (40, 50, SIZE - 1):
        # a ground pixel of row v is hit at camera z = camera height * f / (v - cy)
        assert depth[v, 0] == pytest.approx(ch * F / (v - C), rel=1e-5)


def test_exact_depth_on_a_tilted_plane(renderer):
    # a camera pitched down 15 deg (the top rows see the sky): every ground pixel's depth equals the
    # ray-plane intersection
    pitch = np.radians(15.0)
    z = np.array([0.0, np.cos(pitch), -np.sin(pitch)])
    x = np.array([1.0, 0.0, 0.0])
    y = np.cross(z, x)
    eye = np.array([0.1, -2.0, 1.5])
    pose = _pose((x, y, z), eye)
    out = renderer.render([], _K(), pose, (SIZE, SIZE), LIGHT)
    v, u = np.mgrid[0:SIZE, 0:SIZE].astype(np.float64)
    rays_cam = np.stack([(u - C) / F, (v - C) / F, np.ones_like(u)], -1)
    rays_world = rays_cam @ pose[0, :3, :3].T
    t = -eye[2] / rays_world[..., 2]  # z_cam of the hit, since rays have z_cam = 1
    hit = (t > 0) & (np.abs(eye[:2] + t[..., None] * rays_world[..., :2]) < 6.0).all(-1)
    depth = out.depth[0]
    assert hit.sum() > 1000
    np.testing.assert_allclose(depth[hit], t[hit], rtol=2e-6)
    assert np.all(depth[~hit] == 0) and (t <= 0).sum() > 100  # above the horizon or past the ground's edge


def test_render_is_deterministic_and_views_are_independent(renderer):
    pose_a = _pose(((1, 0, 0), (0, -1, 0), (0, 0, -1)), (0.0, 0.0, 3.0))
    pose_b = _pose(((0, 1, 0), (0, 0, -1), (-1, 0, 0)), (2.0, 0.0, 0.2))
    both = np.concatenate([pose_a, pose_b, pose_a])
    objs = [_cube(0.4)]
    out = renderer.render(objs, np.repeat(_K(), 3, 0), both, (SIZE, SIZE), LIGHT)
    again = renderer.render(objs, np.repeat(_K(), 3, 0), both, (SIZE, SIZE), LIGHT)
    single = renderer.render(objs, _K(), pose_b, (SIZE, SIZE), LIGHT)
    for a, b in ((out.rgb, again.rgb), (out.depth, again.depth), (out.instance, again.instance)):
        assert np.array_equal(a, b)
    assert np.array_equal(out.depth[1], single.depth[0]) and np.array_equal(out.rgb[1], single.rgb[0])
    assert np.array_equal(out.depth[0], out.depth[2])


def test_many_views_split_over_passes():
    # a tiny atlas forces several passes; every view must still land in its own slot
    with Renderer(max_atlas_size=64 * 2) as r:
        poses = np.concatenate(
            [_pose(((1, 0, 0), (0, -1, 0), (0, 0, -1)), (0.0, 0.0, 2.0 + 0.1 * i)) for i in range(7)]
        )
        out = r.render([_cube(0.4)], np.repeat(_K(), 7, 0), poses, (SIZE, SIZE), LIGHT)
    for i in range(7):
        assert out.depth[i, 31, 31] == pytest.approx(2.0 + 0.1 * i - 0.4, abs=1e-5)


def test_projection_maps_pixel_centres():
    K = np.array([[70.0, 0.0, 20.0], [0.0, 75.0, 14.5], [0.0, 0.0, 1.0]])
    H, W = 30, 41
    P = projection_from_K(K, (H, W), 0.1, 10.0)
    for u, v, z in ((0, 0, 1.0), (40, 29, 3.0), (20, 14.5, 0.5)):
        p = np.array([(u - K[0, 2]) * z / K[0, 0], (v - K[1, 2]) * z / K[1, 1], z, 1.0])
        c = P @ p
        ndc = c[:3] / c[3]
        assert ndc[0] == pytest.approx(2 * (u + 0.5) / W - 1)
        assert ndc[1] == pytest.approx(2 * (v + 0.5) / H - 1)  # NDC y runs down the image
    assert (P @ [0, 0, 0.1, 1])[2] / 0.1 == pytest.approx(-1) and (P @ [0, 0, 10, 1])[2] / 10 == pytest.approx(1)


def test_unknown_backend_raises_runtime_error_with_install_hint():
    with pytest.raises(RuntimeError, match="pip install moderngl"):
        create_context(backend="no-such-backend")


def test_bad_instance_id_rejected(renderer):
    with pytest.raises(ValueError, match="instance_id"):
        renderer.render(
            [_cube(0.4, instance_id=0)], _K(), _pose(((1, 0, 0), (0, -1, 0), (0, 0, -1)), (0, 0, 3.0)), (8, 8), LIGHT
        )


# -- meshes ---------------------------------------------------------------------------------------
@pytest.mark.parametrize("make", [box_mesh, sphere_mesh, cylinder_mesh])
def test_primitives_are_unit_and_resting_on_the_ground(make):
    m = make()
    lo, hi = m.bounds
    np.testing.assert_allclose(lo, [-0.5, -0.5, 0.0], atol=1e-6)
    np.testing.assert_allclose(hi, [0.5, 0.5, 1.0], atol=1e-6)
    np.testing.assert_allclose(np.linalg.norm(m.normals, axis=1), 1.0, atol=1e-6)
    # outward normals and counter-clockwise faces: the face normal agrees with the vertex normals
    v = m.vertices[m.faces].astype(np.float64)
    fn = np.cross(v[:, 1] - v[:, 0], v[:, 2] - v[:, 0])
    assert np.all(np.einsum("fk,fk->f", fn, m.normals[m.faces].sum(1)) > 0)


def test_primitive_tessellation():
    # trimesh.creation with the tessellation of the hand-made meshes it replaced: flat box sides,
    # a 48-sided cylinder with smooth sides and flat caps
    box = box_mesh()
    assert box.vertices.shape == (24, 3) and box.faces.shape == (12, 3)
    assert set(map(tuple, np.abs(box.normals).round(6))) == {(1, 0, 0), (0, 1, 0), (0, 0, 1)}
    cyl = cylinder_mesh()
    assert cyl.vertices.shape == (194, 3) and cyl.faces.shape == (192, 3)
    caps = np.abs(cyl.normals[:, 2]) > 0.5
    assert caps.sum() == 2 * 49 and np.all(np.abs(cyl.normals[caps, 2]) == 1)
    np.testing.assert_allclose(np.linalg.norm(cyl.vertices[~caps, :2], axis=1), 0.5, atol=1e-6)
    np.testing.assert_allclose(cyl.normals[~caps, :2], cyl.vertices[~caps, :2] / 0.5, atol=1e-6)


def test_sphere_is_smooth_and_round():
    m = sphere_mesh()
    assert len(m.faces) == 1280
    r = np.linalg.norm(m.vertices - [0, 0, 0.5], axis=1)
    np.testing.assert_allclose(r, 0.5, atol=1e-6)
    np.testing.assert_allclose(m.normals, (m.vertices - [0, 0, 0.5]) / 0.5, atol=1e-5)


def test_normalize_and_decimate_scanned_mesh():
    full = category_mesh("mug", max_faces=0)
    assert len(full.faces) == 16384
    dec = category_mesh("mug")
    assert len(dec.faces) <= 4096
    for m in (full, dec):
        lo, hi = m.bounds
        assert abs(lo[0] + hi[0]) < 1e-6 and abs(lo[1] + hi[1]) < 1e-6 and abs(lo[2]) < 1e-6
        assert (hi - lo).max() == pytest.approx(1.0, abs=1e-6)
    np.testing.assert_allclose(dec.extents, full.extents, atol=0.01)
    assert decimate(full, 10**6) is full  # within budget: unchanged
    a, b = decimate(full, 1000), decimate(full, 1000)  # deterministic, within budget, clean
    for x, y in ((a.vertices, b.vertices), (a.normals, b.normals), (a.faces, b.faces)):
        np.testing.assert_array_equal(x, y)
    assert len(a.faces) <= 1000
    assert len(np.unique(np.sort(a.faces, axis=1), axis=0)) == len(a.faces)  # no back-to-back duplicates
    np.testing.assert_allclose(np.linalg.norm(a.normals, axis=1), 1.0, atol=1e-5)
    shifted = MeshData(box_mesh().vertices * 3 + np.float32(2), box_mesh().normals, box_mesh().faces)
    np.testing.assert_allclose(normalize_mesh(shifted).bounds, box_mesh().bounds, atol=1e-6)
