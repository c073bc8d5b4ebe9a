"""Datasets: the embedded CLEVR-veggie-like generator (catalogue, meshes, renderer, generation loop).

``generate_dataset(out, num_scenes, seed)`` writes ``out/<split>/scene_XXXXXX.npz`` canonical scene
records and ``out/index.json`` (see :mod:`threedq.scene`). Importing this package does not import
moderngl; only rendering does.
"""

from threedq.data.catalog import CATEGORIES, CATEGORY_NAMES, Category
from threedq.data.generate import GeneratorConfig, generate_dataset, sample_scene

__all__ = ["CATEGORIES", "CATEGORY_NAMES", "Category", "GeneratorConfig", "generate_dataset", "sample_scene"]
