"""Datasets: the embedded CLEVR-veggie-like generator, capture-format readers, drawing and caches.

``generate_dataset(out, num_scenes, seed)`` writes ``out/<split>/scene_XXXXXX.npz`` canonical scene records and
``out/index.json`` (see :mod:`threedq.scene`). Importing this package does not import moderngl; only rendering does.
"""

from threedq.data.catalog import CATEGORIES, CATEGORY_NAMES, Category
from threedq.data.generate import generate_dataset
from threedq.data.generator_config import GeneratorConfig
from threedq.data.layout import sample_scene

__all__ = ["CATEGORIES", "CATEGORY_NAMES", "Category", "GeneratorConfig", "generate_dataset", "sample_scene"]
