"""TUM RGB-D sequences: imported into canonical records on first use, then read as a scene folder.

Expected tree of each capture: the module docstring of ``threedq/data/formats/tum.py``; see
:class:`~threedq.datamodules.capture_folder.CaptureDataModule` for the arguments.
"""

from __future__ import annotations

from threedq.datamodules.capture_folder import CaptureDataModule

__all__ = ["TumRGBDDataModule"]


class TumRGBDDataModule(CaptureDataModule):
    """TUM RGB-D sequences; arguments as :class:`~threedq.datamodules.capture_folder.CaptureDataModule`."""

    FORMAT = "tum"
