"""Kinect captures in Open3D's reconstruction layout, imported into canonical records on first use (capture layout: the
module docstring of ``threedq/data/formats/open3d.py``)."""

from threedq.datamodules.capture_folder import CaptureDataModule

__all__ = ["KinectOpen3dDataModule"]


class KinectOpen3dDataModule(CaptureDataModule):
    """Kinect captures in Open3D's reconstruction layout; arguments as :class:`CaptureDataModule`."""

    FORMAT = "open3d"
