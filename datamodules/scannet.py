"""ScanNet SensReader exports, imported into canonical records on first use (capture layout: the module docstring of
``threedq/data/formats/scannet.py``)."""

from threedq.datamodules.capture_folder import CaptureDataModule

__all__ = ["ScanNetDataModule"]


class ScanNetDataModule(CaptureDataModule):
    """ScanNet SensReader exports; arguments as :class:`~threedq.datamodules.capture_folder.CaptureDataModule`."""

    FORMAT = "scannet"
