"""recorded multi-camera rigs, e.g. CARLA's 17 cameras: imported into canonical records on first use, then read as a scene folder.

Expected tree of each capture: the module docstring of ``threedq/data/formats/rig.py``; see
:class:`~threedq.datamodules.capture_folder.CaptureDataModule` for the arguments.
"""

from __future__ import annotations

from threedq.datamodules.capture_folder import CaptureDataModule

__all__ = ["CameraRigDataModule"]


class CameraRigDataModule(CaptureDataModule):
    """recorded multi-camera rigs, e.g. CARLA's 17 cameras; arguments as :class:`~threedq.datamodules.capture_folder.CaptureDataModule`."""

    FORMAT = "rig"
