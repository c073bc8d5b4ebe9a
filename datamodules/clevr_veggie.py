"""The embedded CLEVR-veggie-like dataset: generated offline on first use (or by ``threedq data generate``), then read
from disk as a scene folder (:mod:`threedq.datamodules.scene_folder`).

41 categories (CLEVR's 3 shapes x 8 colours + 17 scanned YCB meshes), up to 3 objects and 28 posed RGB-D views per
scene by default; the scene model: :mod:`threedq.data.layout`.
"""

from __future__ import annotations

import logging
from typing import Any, ClassVar, Literal

from jsonargparse.typing import PositiveInt

from threedq.datamodules.scene_folder import SceneFolderDataModule

from threedq.data.generate import generate_dataset
from threedq.data.generator_config import GeneratorConfig
from threedq.locks import exclusive
from threedq.scene import INDEX_NAME, SceneValidationError, load_index

__all__ = ["ClevrVeggieDataModule"]

log = logging.getLogger(__name__)


class ClevrVeggieDataModule(SceneFolderDataModule):
    """Scenes of the embedded generator; generates (and caches) them when ``data_dir`` has no index.

    Args:
        data_dir: dataset folder (created and filled on first use).
        num_scenes: scenes to generate in all splits.
        split_fractions: train/val/test fractions of ``num_scenes``.
        generator_seed: seed of the scene generator (the test split uses its own derived stream).
        image_size: rendered ``[H, W]``.
        num_views: cameras per scene.
        max_objects: objects per scene (also the padding size of samples).
        generator_workers: processes used for generation.
        categories: category names to draw from (``None``: the embedded data's 41).
        color_mode: ``"category"`` (catalogue colours) or ``"random"`` (a random palette colour per instance).
        sensor_captures: as :class:`~threedq.datamodules.scene_folder.SceneFolderDataModule`'s (clean renders: off).
        **kwargs: the arguments of :class:`~threedq.datamodules.scene_folder.SceneFolderDataModule`.
    """

    #: the stage configs that serve this kind of data (threedq.pipeline.presets)
    PRESETS: ClassVar[dict[str, str]] = {"mining": "stages/mining.yaml", "quantizer": "stages/quantizer.yaml"}

    def __init__(
        self, data_dir: str = "data/clevr_veggie", num_scenes: PositiveInt = 300,
        split_fractions: tuple[float, float, float] = (0.8, 0.1, 0.1), generator_seed: int = 0,
        image_size: tuple[int, int] = (128, 128), num_views: PositiveInt = 28, max_objects: PositiveInt = 3,
        generator_workers: PositiveInt = 2, categories: list[str] | None = None,
        color_mode: Literal["category", "random"] = "category", sensor_captures: bool = False, **kwargs: Any,
    ) -> None:
        super().__init__(data_dir=data_dir, max_objects=max_objects, sensor_captures=sensor_captures, **kwargs)
        self.num_scenes = num_scenes
        self.split_fractions = tuple(split_fractions)
        self.generator_seed = generator_seed
        self.generator_workers = generator_workers
        self.generator_config = GeneratorConfig(
            image_size=tuple(image_size), num_views=num_views, max_objects=max_objects,
            categories=None if categories is None else tuple(categories), color_mode=color_mode,
        )

    def prepare_data(self) -> None:
        """Generate the dataset if ``data_dir`` has no ``index.json``; another process generating it is waited for."""
        if not (self.data_dir / INDEX_NAME).is_file():
            with exclusive(self.data_dir, what="generating"):
                if not (self.data_dir / INDEX_NAME).is_file():  # not made meanwhile by the process waited for
                    log.info("generating %d scenes into %s", self.num_scenes, self.data_dir)
                    generate_dataset(self.data_dir, num_scenes=self.num_scenes, seed=self.generator_seed,
                                     config=self.generator_config, split_fractions=self.split_fractions,
                                     workers=self.generator_workers)
                    return
        index = load_index(self.data_dir)
        made_with = index.generator.get("config_hash")
        if made_with is not None and made_with != self.generator_config.hash():
            raise SceneValidationError(str(self.data_dir / INDEX_NAME), "generator",
                                       "the dataset was generated with a different generator config than this "
                                       "DataModule asks for; point data_dir elsewhere or delete the folder to "
                                       "regenerate")

    def setup(self, stage: str | None = None) -> None:
        if not (self.data_dir / INDEX_NAME).is_file():
            self.prepare_data()
        super().setup(stage)
