"""Datasets: the embedded CLEVR-veggie-like generator (catalogue, meshes, renderer, generation loop).

``generate_dataset(out, num_scenes, seed)`` writes ``out/<split>/scene_XXXXXX.npz`` canonical scene
records and ``out/index.json`` (see :mod:`threedq.scene`). Importing this package does not import
moderngl; only rendering does.

Modules, one job each: :mod:`~threedq.data.catalog` (categories), :mod:`~threedq.data.meshes`
(their meshes), :mod:`~threedq.data.generator_config` (:class:`GeneratorConfig`),
:mod:`~threedq.data.layout` (sampling a scene's objects, light and cameras),
:mod:`~threedq.data.render` (the OpenGL renderer), :mod:`~threedq.data.render_scene` (layout ->
rendered record), :mod:`~threedq.data.splits` (split sizes, per-scene seeds, file names),
:mod:`~threedq.data.generate` (the resumable dataset writer), :mod:`~threedq.data.box_files` (per-scene
box files), :mod:`~threedq.data.proposal_cache` (pseudo-boxes of a whole split, cached),
:mod:`~threedq.data.draw` (projected boxes, colourised depth and instances) and
:mod:`~threedq.data.contact_sheet` (a dataset's contact-sheet PNG).
"""

from threedq.data.catalog import CATEGORIES, CATEGORY_NAMES, Category
from threedq.data.generate import generate_dataset
from threedq.data.generator_config import GeneratorConfig
from threedq.data.layout import sample_scene

__all__ = ["CATEGORIES", "CATEGORY_NAMES", "Category", "GeneratorConfig", "generate_dataset", "sample_scene"]
