"""ScanNet SensReader exports: imported into canonical records on first use, then read as a scene folder.

Expected tree of each capture: the module docstring of ``threedq/data/formats/scannet.py``; see
:class:`~threedq.datamodules.capture_folder.CaptureDataModule` for the arguments.
"""

from __future__ import annotations

from threedq.datamodules.capture_folder import CaptureDataModule

__all__ = ["ScanNetDataModule"]


class ScanNetDataModule(CaptureDataModule):
    """ScanNet SensReader exports; arguments as :class:`~threedq.datamodules.capture_folder.CaptureDataModule`."""

    FORMAT = "scannet"
