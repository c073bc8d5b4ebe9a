"""TUM RGB-D sequences, imported into canonical records on first use (capture layout: the module docstring of
``threedq/data/formats/tum.py``)."""

from threedq.datamodules.capture_folder import CaptureDataModule

__all__ = ["TumRGBDDataModule"]


class TumRGBDDataModule(CaptureDataModule):
    """TUM RGB-D sequences; arguments as :class:`~threedq.datamodules.capture_folder.CaptureDataModule`."""

    FORMAT = "tum"
