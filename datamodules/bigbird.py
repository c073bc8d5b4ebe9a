"""BigBIRD raw turntable captures, imported into canonical records on first use (capture layout: the module docstring of
``threedq/data/formats/bigbird.py``)."""

from threedq.datamodules.capture_folder import CaptureDataModule

__all__ = ["BigBirdDataModule"]


class BigBirdDataModule(CaptureDataModule):
    """BigBIRD raw turntable captures; arguments as :class:`~threedq.datamodules.capture_folder.CaptureDataModule`."""

    FORMAT = "bigbird"
