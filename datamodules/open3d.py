"""Kinect captures in Open3D's reconstruction layout: imported into canonical records on first use, then read as a scene folder.

Expected tree of each capture: the module docstring of ``threedq/data/formats/open3d.py``; see
:class:`~threedq.datamodules.capture_folder.CaptureDataModule` for the arguments.
"""

from __future__ import annotations

from threedq.datamodules.capture_folder import CaptureDataModule

__all__ = ["KinectOpen3dDataModule"]


class KinectOpen3dDataModule(CaptureDataModule):
    """Kinect captures in Open3D's reconstruction layout; arguments as :class:`~threedq.datamodules.capture_folder.CaptureDataModule`."""

    FORMAT = "open3d"
