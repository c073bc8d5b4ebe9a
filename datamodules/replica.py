"""Replica scenes as exported for NICE-SLAM, imported into canonical records on first use (capture layout: the module
docstring of ``threedq/data/formats/replica.py``)."""

from threedq.datamodules.capture_folder import CaptureDataModule

__all__ = ["ReplicaDataModule"]


class ReplicaDataModule(CaptureDataModule):
    """Replica scenes as exported for NICE-SLAM; arguments as :class:`CaptureDataModule`."""

    FORMAT = "replica"
