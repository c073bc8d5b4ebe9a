"""The DataModule of an on-disk capture format: import the captures once, then read canonical records.

``prepare_data`` imports each split's capture folder (``capture_dirs[split]``: one capture or a folder of captures,
in the format's layout) into ``data_dir`` (``index.json`` and ``<split>/<capture>.npz``) with
:func:`threedq.data.formats.importer.import_captures`, unless ``data_dir/index.json`` exists; the rest is
:class:`~threedq.datamodules.scene_folder.SceneFolderDataModule`. A subclass per format only names its ``FORMAT``.
"""

from __future__ import annotations

import logging
from typing import Any, ClassVar

from jsonargparse.typing import PositiveFloat, PositiveInt

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
        reader_options: keyword arguments of the format's reader (e.g. ``intrinsics`` for TUM).
        **kwargs: the arguments of :class:`~threedq.datamodules.scene_folder.SceneFolderDataModule`.
    """

    FORMAT: ClassVar[str] = ""

    def __init__(self, capture_dirs: dict[str, str], data_dir: str, max_views: PositiveInt = 28,
                 max_depth: PositiveFloat = 10.0, reader_options: dict[str, Any] | None = None, **kwargs: Any) -> None:
        super().__init__(data_dir=data_dir, **kwargs)
        bad = [s for s in capture_dirs if s not in ("train", "val", "test")]
        if bad:
            raise ValueError(f"capture_dirs: expected keys among train, val, test, got {bad[0]!r}")
        self.capture_dirs = dict(capture_dirs)
        self.max_views = max_views
        self.max_depth = max_depth
        self.reader_options = dict(reader_options or {})

    def prepare_data(self) -> None:
        if (self.data_dir / INDEX_NAME).is_file():
            return
        for split, src in self.capture_dirs.items():
            summary = import_captures(self.FORMAT, src, self.data_dir, split=split, max_views=self.max_views,
                                      max_depth=self.max_depth, reader_options=self.reader_options, progress=False)
            for line in summary.lines():
                log.info(line)

    def setup(self, stage: str | None = None) -> None:
        self.prepare_data()  # idempotent; a single process needs no separate prepare step
        super().setup(stage)
