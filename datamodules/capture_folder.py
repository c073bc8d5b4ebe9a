"""The DataModule of an on-disk capture format: import the captures once, then read canonical records.

``prepare_data`` runs :func:`threedq.data.formats.importer.import_captures` for each split's capture folder
into ``data_dir`` (skipped when ``data_dir/index.json`` exists); everything after is
:class:`~threedq.datamodules.scene_folder.SceneFolderDataModule` on canonical records. One subclass per
format (``datamodules/<dataset>.py``) only names its format.

Expected trees: ``capture_dirs[split]`` is one capture, or a folder of captures, in the format's layout (the
parser's module docstring in ``threedq/data/formats/``); ``data_dir`` receives ``index.json`` and
``<split>/<capture>.npz``.
"""

from __future__ import annotations

import logging
from typing import Any, ClassVar

from threedq.datamodules.scene_folder import SceneFolderDataModule

from threedq.data.formats.importer import import_captures
from threedq.scene import INDEX_NAME

__all__ = ["CaptureDataModule"]

log = logging.getLogger(__name__)


class CaptureDataModule(SceneFolderDataModule):
    """Captures of one format (``FORMAT``), imported into ``data_dir`` on first use.

    Args:
        capture_dirs: ``{split: capture folder}`` (``train``, ``val``, ``test``).
        data_dir: the canonical dataset folder written by the import.
        max_views: views kept per scene (farthest camera positions).
        max_depth: depth beyond this many metres becomes 0.
        parser_options: keyword arguments of the format's parser (e.g. ``intrinsics`` for TUM).
        batch_size, num_workers, num_input_views, num_target_views, max_objects, seed, boxes, match_iou,
            max_boxes, train_random_views: as in :class:`~threedq.datamodules.scene_folder.SceneFolderDataModule`.
    """

    FORMAT: ClassVar[str] = ""

    def __init__(
        self,
        capture_dirs: dict[str, str],
        data_dir: str,
        max_views: int = 28,
        max_depth: float = 10.0,
        parser_options: dict[str, Any] | None = None,
        batch_size: int = 2,
        num_workers: int = 0,
        num_input_views: int = 1,
        num_target_views: int = 1,
        max_objects: int = 3,
        seed: int = 0,
        boxes: str = "gt",
        match_iou: float = 0.5,
        max_boxes: int = 8,
        train_random_views: bool = True,
    ) -> None:
        super().__init__(
            data_dir=data_dir,
            batch_size=batch_size,
            num_workers=num_workers,
            num_input_views=num_input_views,
            num_target_views=num_target_views,
            max_objects=max_objects,
            seed=seed,
            boxes=boxes,
            match_iou=match_iou,
            max_boxes=max_boxes,
            train_random_views=train_random_views,
        )
        bad = [s for s in capture_dirs if s not in ("train", "val", "test")]
        if bad:
            raise ValueError(f"capture_dirs: expected keys among train, val, test, got {bad[0]!r}")
        self.capture_dirs = dict(capture_dirs)
        self.max_views = max_views
        self.max_depth = max_depth
        self.parser_options = dict(parser_options or {})

    def prepare_data(self) -> None:
        if (self.data_dir / INDEX_NAME).is_file():
            return
        for split, src in self.capture_dirs.items():
            summary = import_captures(
                self.FORMAT,
                src,
                self.data_dir,
                split=split,
                max_views=self.max_views,
                max_depth=self.max_depth,
                parser_options=self.parser_options,
                progress=False,
            )
            for line in summary.lines():
                log.info(line)

    def setup(self, stage: str | None = None) -> None:
        self.prepare_data()  # idempotent; a single process needs no separate prepare step
        super().setup(stage)
