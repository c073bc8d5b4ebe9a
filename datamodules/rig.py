"""Recorded multi-camera rigs, e.g. CARLA's 17 cameras, imported into canonical records on first use (capture layout:
the module docstring of ``threedq/data/formats/rig.py``)."""

from threedq.datamodules.capture_folder import CaptureDataModule

__all__ = ["CameraRigDataModule"]


class CameraRigDataModule(CaptureDataModule):
    """recorded multi-camera rigs, e.g. CARLA's 17 cameras; arguments as :class:`CaptureDataModule`."""

    FORMAT = "rig"
