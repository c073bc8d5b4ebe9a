"""Glue from a sampled scene layout to the renderer: one :class:`~threedq.scene.SceneRecord` per layout.

Convention: see :mod:`threedq.data.layout`.
"""

from __future__ import annotations

import numpy as np

from threedq.data.catalog import category_by_name
from threedq.data.generator_config import GeneratorConfig
from threedq.data.layout import SceneLayout
from threedq.data.meshes import category_mesh
from threedq.data.render import Renderer, RenderObject
from threedq.scene import SceneRecord

__all__ = ["make_renderer", "render_scene"]


def make_renderer(config: GeneratorConfig) -> Renderer:
    """A :class:`~threedq.data.render.Renderer` set up for ``config`` (ground, shadows)."""
    return Renderer(ground_size=config.ground_size, shadows=config.shadows)


def render_scene(layout: SceneLayout, renderer: Renderer) -> SceneRecord:
    """Render a layout's views and pack them with its boxes into a :class:`SceneRecord` (with ``instance``); ``meta``
    is ``layout.meta`` plus the object names, colours (if any) and the light."""
    objects = [RenderObject(key=f"{o.name}/{layout.mesh_faces}", mesh=category_mesh(o.name, layout.mesh_faces),
                            color=o.color if o.color is not None else category_by_name(o.name).color,
                            world_T_obj=o.world_T_obj, instance_id=i + 1) for i, o in enumerate(layout.objects)]
    out = renderer.render(objects, layout.K, layout.world_T_cam, layout.image_size, layout.lighting)
    meta = dict(layout.meta)
    meta["object_names"] = [o.name for o in layout.objects]
    if any(o.color is not None for o in layout.objects):
        meta["object_colors"] = [[round(float(c), 6) for c in o.color] if o.color is not None else None
                                 for o in layout.objects]
    light = layout.lighting
    meta["light"] = {"direction": [round(float(x), 6) for x in light.direction],
                     "intensity": round(light.intensity, 6), "ambient": round(light.ambient, 6)}
    return SceneRecord(rgb=out.rgb, depth=out.depth, K=layout.K.astype(np.float32),
                       world_T_cam=layout.world_T_cam.astype(np.float32), boxes=layout.boxes.astype(np.float32),
                       categories=layout.categories, instance=out.instance, meta=meta)
