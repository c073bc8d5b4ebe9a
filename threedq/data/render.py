"""Offscreen OpenGL (moderngl) renderer of posed RGB-D views with exact metric depth and instance ids.

One pass writes an RGBA8 colour target and an RG32F target holding camera-frame z (from the fragment shader) and the
instance id. All views of a scene are tiles of one atlas framebuffer, read back with one ``glReadPixels`` per target;
an optional shadow map per scene gives cast shadows.

Convention:
    World frame in metres, z up. Cameras use OpenCV axes (x right, y down, z forward); ``world_T_cam`` ``[V, 4, 4]`` is
    camera-to-world; ``K`` ``[V, 3, 3]`` has pixel centres at integer coordinates. Pixel centre ``(u, v)`` maps to NDC
    ``x = 2 (u + 0.5) / W - 1``, ``y = 2 (v + 0.5) / H - 1``: NDC y points down the image, so GL framebuffer row ``v``
    (from the bottom, as ``glReadPixels`` returns it) is image row ``v`` (from the top). Depth is camera-frame z in
    metres, 0 where no surface was hit; instance 0 is the ground or background. No anti-aliasing.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from threedq.data.meshes import MeshData

__all__ = ["Lighting", "RenderObject", "RenderOutput", "Renderer", "create_context", "ground_mesh", "projection_from_K"]

_INSTALL_HINT = (
    "threedq renders its dataset with moderngl. Install it with `pip install moderngl glcontext`; on a "
    "headless Linux machine also install Mesa's EGL and software rasteriser (Debian/Ubuntu: "
    "`apt-get install libegl1 libgl1-mesa-dri`), or run on a machine with a working OpenGL 3.3 driver."
)

_VERTEX_SHADER = """
#version 330
uniform mat4 proj;          // OpenCV camera -> clip
uniform mat4 cam_T_obj;
uniform mat4 world_T_obj;
uniform mat4 light_T_world; // world -> shadow-map clip
in vec3 in_position;
in vec3 in_normal;
out vec3 v_world;
out vec3 v_normal;
out float v_camz;
void main() {
    vec4 p = vec4(in_position, 1.0);
    vec4 pc = cam_T_obj * p;
    v_camz = pc.z;
    v_world = (world_T_obj * p).xyz;
    v_normal = mat3(world_T_obj) * in_normal;
    gl_Position = proj * pc;
}
"""

_FRAGMENT_SHADER = """
#version 330
uniform vec3 albedo;
uniform float instance_id;
uniform vec3 cam_pos;
uniform vec3 light_dir;      // unit, from the surface towards the light
uniform float light_intensity;
uniform float ambient;
uniform float specular;
uniform float shininess;
uniform bool use_shadow;
uniform mat4 light_T_world;
uniform float shadow_texel;  // shadow-map texel size in metres
uniform sampler2DShadow shadow_map;
in vec3 v_world;
in vec3 v_normal;
in float v_camz;
layout(location = 0) out vec4 out_color;
layout(location = 1) out vec2 out_depth_id;

float visibility(vec3 n) {
    if (!use_shadow) return 1.0;
    float ndl = clamp(dot(n, light_dir), 0.0, 1.0);
    vec3 p = v_world + n * shadow_texel * (1.0 + 2.0 * (1.0 - ndl));
    vec3 s = (light_T_world * vec4(p, 1.0)).xyz * 0.5 + 0.5;
    if (any(lessThan(s.xy, vec2(0.0))) || any(greaterThan(s.xy, vec2(1.0))) || s.z > 1.0) return 1.0;
    return texture(shadow_map, s);  // bilinear 2x2 percentage-closer filtering
}

void main() {
    vec3 n = normalize(v_normal);
    vec3 to_cam = normalize(cam_pos - v_world);
    if (dot(n, to_cam) < 0.0) n = -n;  // light both sides (scanned meshes, insides of mugs)
    float ndl = max(dot(n, light_dir), 0.0);
    float vis = visibility(n);
    vec3 h = normalize(light_dir + to_cam);
    float spec = specular * pow(max(dot(n, h), 0.0), shininess) * step(0.0, ndl - 1e-4);
    vec3 c = albedo * (ambient + light_intensity * ndl * vis) + vec3(light_intensity * vis * spec);
    out_color = vec4(clamp(c, 0.0, 1.0), 1.0);
    out_depth_id = vec2(v_camz, instance_id);
}
"""

_SHADOW_VERTEX_SHADER = """
#version 330
uniform mat4 light_T_obj;
in vec3 in_position;
void main() { gl_Position = light_T_obj * vec4(in_position, 1.0); }
"""

_SHADOW_FRAGMENT_SHADER = "#version 330\nvoid main() {}\n"


@dataclass(frozen=True)
class Lighting:
    """A directional key light (``direction``: unit 3-vector towards the light; ``intensity``) plus ``ambient`` light.

    Convention: world frame, z up; intensity and ambient multiply the sRGB albedo in ``[0, 1]`` linearly (no gamma).
    """

    direction: tuple[float, float, float]
    intensity: float
    ambient: float


@dataclass(frozen=True)
class RenderObject:
    """One mesh instance to draw: ``key`` caches the mesh's GPU buffers (equal keys must mean equal meshes), ``mesh``
    in its object frame, sRGB albedo ``color`` in ``[0, 1]``, ``world_T_obj`` ``[4, 4]`` (rotation times a uniform
    scale, plus a translation) and ``instance_id`` (0 is reserved for the ground and background)."""

    key: str
    mesh: MeshData
    color: tuple[float, float, float]
    world_T_obj: np.ndarray
    instance_id: int


@dataclass
class RenderOutput:
    """Rendered views: ``rgb`` ``[V, H, W, 3]`` uint8, ``depth`` ``[V, H, W]`` float32 (camera z, m, 0 = none),
    ``instance`` ``[V, H, W]`` int32 (0 = ground/background); image row 0 is the top."""

    rgb: np.ndarray
    depth: np.ndarray
    instance: np.ndarray


def create_context(backend: str | None = None):
    """A standalone (offscreen) OpenGL >= 3.3 core context; ``backend`` ``None`` tries EGL first, then the default.

    Raises:
        RuntimeError: no context could be created; the message says what to install.
    """
    try:
        import moderngl
    except ImportError as e:  # pragma: no cover - moderngl is a hard dependency
        raise RuntimeError(f"moderngl is not importable ({e}). {_INSTALL_HINT}") from e
    attempts: list[dict] = [{"backend": "egl"}, {}] if backend is None else [{"backend": backend}]
    errors = []
    for kwargs in attempts:
        try:
            return moderngl.create_standalone_context(require=330, **kwargs)
        except Exception as e:  # noqa: BLE001 - every failure mode of the GL loaders is reported below
            errors.append(f"{kwargs.get('backend', 'default')}: {type(e).__name__}: {e}")
    raise RuntimeError("cannot create an OpenGL context (" + "; ".join(errors) + "). " + _INSTALL_HINT)


def projection_from_K(K: np.ndarray, image_size: tuple[int, int], near: float, far: float) -> np.ndarray:
    """OpenGL projection ``[4, 4]`` (float64) for OpenCV camera coordinates, ``K`` ``[3, 3]`` and ``image_size``
    ``(H, W)``: NDC as in the module docstring, camera z in ``[near, far]`` to NDC z in ``[-1, 1]``."""
    H, W = image_size
    fx, s, cx = float(K[0, 0]), float(K[0, 1]), float(K[0, 2])
    fy, cy = float(K[1, 1]), float(K[1, 2])
    P = np.zeros((4, 4))
    P[0, 0], P[0, 1], P[0, 2] = 2 * fx / W, 2 * s / W, (2 * cx + 1) / W - 1
    P[1, 1], P[1, 2] = 2 * fy / H, (2 * cy + 1) / H - 1
    P[2, 2], P[2, 3] = (far + near) / (far - near), -2 * far * near / (far - near)
    P[3, 2] = 1.0
    return P


def ground_mesh(size: float) -> MeshData:
    """A square ``size x size`` quad on z = 0 centred at the origin, normal +z (2 triangles; metres)."""
    h = size / 2
    v = np.array([[-h, -h, 0], [h, -h, 0], [h, h, 0], [-h, h, 0]], np.float32)
    n = np.tile(np.array([0, 0, 1], np.float32), (4, 1))
    return MeshData(v, n, np.array([[0, 1, 2], [0, 2, 3]], np.uint32))


def _mat_bytes(m: np.ndarray) -> bytes:
    """Column-major float32 bytes of a matrix, as GLSL ``mat4`` uniforms expect."""
    return np.ascontiguousarray(np.asarray(m, np.float64).T, np.float32).tobytes()


def _look_at_ortho(direction: np.ndarray, centre: np.ndarray, radius: float, depth: float) -> np.ndarray:
    """World -> clip ``[4, 4]`` of an orthographic light camera looking along ``-direction`` at ``centre``: it covers
    ``[-radius, radius]^2`` across the light direction and ``depth`` metres along it, from ``radius`` before ``centre``.
    """
    f = -direction / np.linalg.norm(direction)  # forward (from the light into the scene)
    up = np.array([0.0, 0.0, 1.0]) if abs(f[2]) < 0.99 else np.array([1.0, 0.0, 0.0])
    x = np.cross(f, up)
    x /= np.linalg.norm(x)
    y = np.cross(x, f)
    eye = centre - f * (radius + 0.1)
    view = np.eye(4)
    view[0, :3], view[1, :3], view[2, :3] = x, y, -f  # OpenGL eye frame: looks along -z
    view[:3, 3] = -view[:3, :3] @ eye
    proj = np.diag([1.0 / radius, 1.0 / radius, -2.0 / depth, 1.0])
    proj[2, 3] = -1.0
    return proj @ view


class Renderer:
    """Offscreen renderer of RGB, metric depth and instance ids for many views of one scene at a time.

    One per process (it owns a GL context), reused for every scene; mesh buffers are cached by :attr:`RenderObject.key`.

    Args:
        ground_size: side of the square ground plane at z = 0, metres (0 = no ground); ground_color: its sRGB albedo.
        shadows: draw cast shadows of the objects; shadow_map_size: its side in texels.
        near, far: clip distances of the cameras, metres.
        specular, shininess: Blinn-Phong highlight of the objects; ground_specular: that of the ground.
        max_atlas_size: largest side of the atlas framebuffer that holds the views (pixels).
    """

    def __init__(self, backend: str | None = None, ground_size: float = 12.0,
                 ground_color: tuple[float, float, float] = (0.55, 0.55, 0.55), shadows: bool = True,
                 shadow_map_size: int = 512, near: float = 0.05, far: float = 50.0, specular: float = 0.25,
                 ground_specular: float = 0.05, shininess: float = 24.0, max_atlas_size: int = 4096) -> None:
        if not 0 < near < far:
            raise ValueError(f"near, far: need 0 < near < far, got near={near}, far={far}")
        import moderngl

        self.ctx = create_context(backend)
        self.ground_color = tuple(float(c) for c in ground_color)
        self.shadows = bool(shadows)
        self.near, self.far = float(near), float(far)
        ctx = self.ctx
        self._prog = ctx.program(vertex_shader=_VERTEX_SHADER, fragment_shader=_FRAGMENT_SHADER)
        self.specular, self.ground_specular = float(specular), float(ground_specular)
        self._prog["shininess"].value = float(shininess)
        self._shadow_prog = ctx.program(vertex_shader=_SHADOW_VERTEX_SHADER, fragment_shader=_SHADOW_FRAGMENT_SHADER)
        self._meshes: dict[str, tuple] = {}
        self._atlases: dict[tuple[int, int, int, int], object] = {}
        limit = min(int(ctx.info["GL_MAX_TEXTURE_SIZE"]), int(ctx.info["GL_MAX_RENDERBUFFER_SIZE"]))
        self.max_atlas_size = max(1, min(int(max_atlas_size), limit))
        self._ground = ground_mesh(ground_size) if ground_size > 0 else None
        self._shadow_tex = ctx.depth_texture((shadow_map_size, shadow_map_size))
        self._shadow_tex.compare_func = "<="
        self._shadow_tex.filter = (moderngl.LINEAR, moderngl.LINEAR)
        self._shadow_tex.repeat_x = self._shadow_tex.repeat_y = False
        self._shadow_fbo = ctx.framebuffer(depth_attachment=self._shadow_tex)
        self._prog["shadow_map"].value = 0

    def _mesh_buffers(self, key: str, mesh: MeshData) -> tuple:
        entry = self._meshes.get(key)
        if entry is None:
            data = np.ascontiguousarray(np.concatenate([mesh.vertices, mesh.normals], axis=1), np.float32)
            vbo = self.ctx.buffer(data.tobytes())
            ibo = self.ctx.buffer(np.ascontiguousarray(mesh.faces, np.uint32).tobytes())
            vao = self.ctx.vertex_array(self._prog, [(vbo, "3f 3f", "in_position", "in_normal")], ibo,
                                        index_element_size=4)
            svao = self.ctx.vertex_array(self._shadow_prog, [(vbo, "3f 12x", "in_position")], ibo, index_element_size=4)
            entry = self._meshes[key] = (vbo, ibo, vao, svao)
        return entry

    def _layout(self, num_views: int, H: int, W: int) -> tuple[int, int, int]:
        """Atlas grid ``(cols, rows, views per pass)`` for ``num_views`` tiles of ``H x W``."""
        max_cols, max_rows = max(1, self.max_atlas_size // W), max(1, self.max_atlas_size // H)
        if W > self.max_atlas_size or H > self.max_atlas_size:
            raise ValueError(f"image_size: {H}x{W} exceeds the renderer's limit of {self.max_atlas_size} pixels")
        per_pass = min(num_views, max_cols * max_rows)
        cols = min(max_cols, max(1, math.ceil(math.sqrt(per_pass * H / W))))
        rows = math.ceil(per_pass / cols)
        if rows > max_rows:
            rows = max_rows
            cols = min(max_cols, math.ceil(per_pass / rows))
        return cols, rows, min(per_pass, cols * rows)

    def _atlas(self, cols: int, rows: int, H: int, W: int):
        key = (cols, rows, H, W)
        fbo = self._atlases.get(key)
        if fbo is None:
            size = (cols * W, rows * H)
            color = self.ctx.renderbuffer(size, components=4, dtype="f1")
            depth_id = self.ctx.renderbuffer(size, components=2, dtype="f4")
            zbuf = self.ctx.depth_renderbuffer(size)
            fbo = self._atlases[key] = self.ctx.framebuffer(color_attachments=[color, depth_id], depth_attachment=zbuf)
        return fbo

    def release(self) -> None:
        """Free the GL context and everything on it (the renderer is unusable afterwards)."""
        if getattr(self, "ctx", None) is not None:
            self.ctx.release()
            self.ctx = None

    def __enter__(self) -> Renderer:  # noqa: PYI034 - typing.Self needs Python 3.11
        return self

    def __exit__(self, *exc) -> None:
        self.release()

    def _shadow_pass(self, objects: Sequence[RenderObject], lighting: Lighting) -> None:
        prog = self._prog
        if not self.shadows or not objects:
            prog["use_shadow"].value = False
            return
        centres, radii = [], []
        for o in objects:
            lo, hi = o.mesh.bounds
            corners = np.array([[x, y, z, 1.0] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])])
            w = corners @ np.asarray(o.world_T_obj, np.float64).T
            c = w[:, :3].mean(axis=0)
            centres.append(c)
            radii.append(np.linalg.norm(w[:, :3] - c, axis=1).max())
        centres_a, radii_a = np.array(centres), np.array(radii)
        centre = centres_a.mean(axis=0)
        radius = float((np.linalg.norm(centres_a - centre, axis=1) + radii_a).max()) + 0.02
        light_T_world = _look_at_ortho(np.asarray(lighting.direction, np.float64), centre, radius, depth=radius + 40.0)
        self._shadow_fbo.use()
        self._shadow_fbo.clear(depth=1.0)
        self.ctx.polygon_offset = (2.0, 2.0)
        for o in objects:
            svao = self._mesh_buffers(o.key, o.mesh)[3]
            self._shadow_prog["light_T_obj"].write(_mat_bytes(light_T_world @ np.asarray(o.world_T_obj, np.float64)))
            svao.render()
        self.ctx.polygon_offset = (0.0, 0.0)
        prog["use_shadow"].value = True
        prog["light_T_world"].write(_mat_bytes(light_T_world))
        prog["shadow_texel"].value = 2 * radius / self._shadow_tex.width
        self._shadow_tex.use(location=0)

    def render(self, objects: Sequence[RenderObject], K: np.ndarray, world_T_cam: np.ndarray,
               image_size: tuple[int, int], lighting: Lighting) -> RenderOutput:
        """Render ``V`` views of the objects (besides the ground) from ``K`` ``[V, 3, 3]`` and ``world_T_cam``
        ``[V, 4, 4]`` at ``image_size`` ``(H, W)``; returns a :class:`RenderOutput`. Convention: the module docstring.
        """
        if self.ctx is None:
            raise RuntimeError("the renderer was released")
        import moderngl

        H, W = int(image_size[0]), int(image_size[1])
        K = np.asarray(K, np.float64)
        world_T_cam = np.asarray(world_T_cam, np.float64)
        V = world_T_cam.shape[0]
        if K.shape != (V, 3, 3) or world_T_cam.shape != (V, 4, 4):
            raise ValueError(f"K, world_T_cam: expected [V,3,3] and [V,4,4], got {K.shape} and {world_T_cam.shape}")
        ctx, prog = self.ctx, self._prog
        ctx.enable_only(moderngl.DEPTH_TEST)
        self._shadow_pass(objects, lighting)
        ctx.enable_only(moderngl.DEPTH_TEST)
        light = np.asarray(lighting.direction, np.float64)
        prog["light_dir"].value = tuple(float(x) for x in light / np.linalg.norm(light))
        prog["light_intensity"].value = float(lighting.intensity)
        prog["ambient"].value = float(lighting.ambient)

        draw = []  # (vao, colour, specular, instance id, world_T_obj); objects first so the ground is depth-culled
        for o in objects:
            if not 0 < int(o.instance_id) < 2**24:
                raise ValueError(f"instance_id: must be in [1, 2^24), got {o.instance_id}")
            vao = self._mesh_buffers(o.key, o.mesh)[2]
            draw.append((vao, o.color, self.specular, int(o.instance_id), np.asarray(o.world_T_obj, np.float64)))
        if self._ground is not None:
            vao = self._mesh_buffers("__ground__", self._ground)[2]
            draw.append((vao, self.ground_color, self.ground_specular, 0, np.eye(4)))
        cam_T_world = np.linalg.inv(world_T_cam)

        rgb = np.empty((V, H, W, 3), np.uint8)
        depth = np.empty((V, H, W), np.float32)
        instance = np.empty((V, H, W), np.int32)
        cols, rows, per_pass = self._layout(V, H, W)
        fbo = self._atlas(cols, rows, H, W)
        for start in range(0, V, per_pass):
            n = min(per_pass, V - start)
            fbo.use()
            fbo.scissor = None
            fbo.clear(0.0, 0.0, 0.0, 0.0, depth=1.0, viewport=(0, 0, cols * W, rows * H))
            for t in range(n):
                v = start + t
                tile = ((t % cols) * W, (t // cols) * H, W, H)
                fbo.viewport = fbo.scissor = tile
                prog["proj"].write(_mat_bytes(projection_from_K(K[v], (H, W), self.near, self.far)))
                prog["cam_pos"].value = tuple(float(x) for x in world_T_cam[v, :3, 3])
                for vao, colour, spec, inst, world_T_obj in draw:
                    prog["cam_T_obj"].write(_mat_bytes(cam_T_world[v] @ world_T_obj))
                    prog["world_T_obj"].write(_mat_bytes(world_T_obj))
                    prog["albedo"].value = tuple(float(c) for c in colour)
                    prog["specular"].value = spec
                    prog["instance_id"].value = float(inst)
                    vao.render()
            fbo.scissor = None
            full = (0, 0, cols * W, rows * H)
            c = np.frombuffer(fbo.read(viewport=full, components=3, attachment=0), np.uint8)
            d = np.frombuffer(fbo.read(viewport=full, components=2, attachment=1, dtype="f4"), np.float32)
            c = c.reshape(rows, H, cols, W, 3).transpose(0, 2, 1, 3, 4).reshape(rows * cols, H, W, 3)
            d = d.reshape(rows, H, cols, W, 2).transpose(0, 2, 1, 3, 4).reshape(rows * cols, H, W, 2)
            rgb[start : start + n] = c[:n]
            depth[start : start + n] = d[:n, ..., 0]
            instance[start : start + n] = np.rint(d[:n, ..., 1])
        return RenderOutput(rgb=rgb, depth=depth, instance=instance)
